"""Every registered task, one parameterised set of checks.

Default suite (no MJX compile): the registry entry and bad options; the initial-state
distribution is mirror-symmetric (starts drawn by the task's ``init`` against their mirror
images, coordinate by coordinate); a few starts and their mirror images are valid: no
interpenetration, objects where the task put them, success false.

Slow suite, one compiled rollout program per task: ``jit`` reset, mirror and step; shapes
and no NaN; the expert's success rate (>= 95 %) on the first 50 of the 200 seeded starts
that ``equibim experts --episodes 200`` runs (its JSON, committed under ``docs/results/``,
holds the rate on all 200); and ``S`` maps a recorded expert demo (observations and
actions) onto the demo the expert records from the mirrored start.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from scipy.stats import ks_2samp

from equibim_jax._batching import chunked_vmap
from equibim_jax.experts import make_expert, make_rollout
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names

TASKS = task_names()


@pytest.fixture(scope="module", params=TASKS)
def task(request):
    return request.param


def test_registry_entry_and_bad_options(task):
    entry = task_entry(task)
    assert entry.name == task and entry.step_limit >= 100 and entry.expert is not None
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['no_such_option'\]"):
        make_env(task, no_such_option=1)
    if "side" in entry.scene_fields:  # tasks where one arm acts pick its side
        with pytest.raises(ValueError, match="side must be one of"):
            make_scene(task, side="middle")
    with pytest.raises(ValueError, match="robot"):
        make_env(task, robot="robot_b" if entry.robot == "robot_a" else "robot_a")


def _host_forward(env, qpos):
    d = mujoco.MjData(env.mj_model)
    d.qpos[:] = np.asarray(qpos, np.float64)
    mujoco.mj_forward(env.mj_model, d)
    return d


def test_initial_distribution_is_mirror_symmetric_and_valid(task):
    env = make_env(task, obs=("qpos",))
    n = 1024
    keys = jax.random.split(jax.random.key(7), n)
    qpos, info = jax.jit(jax.vmap(lambda k: env.scene.init(k, env)))(keys)
    qpos = np.asarray(qpos, np.float64)
    assert qpos.shape == (n, env.mj_model.nq) and np.all(np.isfinite(qpos))
    mirrored = np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(qpos)), np.float64)
    np.testing.assert_allclose(np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(mirrored))), qpos, atol=1e-5)
    # Coordinate by coordinate, the starts and their mirror images follow one law (two-sample
    # KS, alpha 1e-4 per coordinate). A one-sided or skewed distribution fails here.
    varying = np.flatnonzero(qpos.std(0) > 1e-6)
    assert varying.size > 0, "the initial state does not vary"
    for i in varying:
        p = ks_2samp(qpos[:, i], mirrored[:, i]).pvalue
        assert p > 1e-4, f"{task}: qpos[{i}] has a different law in the mirrored starts (KS p = {p:.2e})"
    # A few starts and their mirror images, checked in MuJoCo: no interpenetration beyond
    # 2 mm, the success predicate false.
    for q in (*qpos[:3], *mirrored[:3]):
        d = _host_forward(env, q)
        depth = min((c.dist for c in d.contact[: d.ncon]), default=0.0)
        assert depth > -2e-3, f"{task}: a start interpenetrates by {-depth * 1000:.1f} mm"
        dx = mjx.put_data(env.mj_model, d)
        _, success, _ = env.scene.evaluate(dx, {k: v[0] for k, v in info.items()}, env)
        assert not bool(success), f"{task}: success is true at a start"


# ------------------------------------------------------------------------------ slow
N_SEEDS = 50  # the first 50 of `equibim experts`' 200 starts (all 200: `equibim experts`)
N_MIRROR = 25  # of these starts, the first 25 are also run from their mirror images


@pytest.mark.slow
def test_expert_success_and_mirror_equivariance(task):
    """The first N_SEEDS of the 200 seeded starts of ``equibim experts --seed 2024``, run to
    the end of the expert's script, plus the mirror images of the first 25: one compiled
    program."""
    env = make_env(task, obs=("qpos", "ee"))
    expert = make_expert(env)
    length = expert.horizon + 10
    roll = make_rollout(env, expert, length=length, obs=True)
    batch = N_MIRROR

    @jax.jit
    def starts(keys):
        s = jax.vmap(env.reset)(keys)
        return s, jax.vmap(env.mirror_state)(s)

    @jax.jit
    def run(s0):
        final, traj = chunked_vmap(roll.from_state, chunk=batch)(s0)
        return final.info["success"], traj

    keys = jax.random.split(jax.random.key(2024), 200)[:N_SEEDS]
    succ, trajs = [], []
    for i in range(0, N_SEEDS, batch):
        s0, s0m = starts(keys[i : i + batch])
        if i == 0:  # shapes, no NaN, success false at reset (jitted reset and mirror)
            assert s0.data.qpos.shape == (batch, env.mj_model.nq)
            assert s0.obs["qpos"].shape == (batch, 2 * (env.info.n_arm + 1))
            assert s0.obs["ee"].shape == (batch, 2 * 10)
            for s in (s0, s0m):
                assert not np.asarray(s.info["success"]).any()
                assert np.all(np.isfinite(np.asarray(s.data.qpos)))
            first = s0
            ok_m, traj_m = run(s0m)
        ok, traj = run(s0)
        succ.append(np.asarray(ok))
        if i == 0:
            trajs = traj
    success = np.concatenate(succ)
    rate = success.mean()
    print(f"\n{task}: expert success {success.sum()}/{N_SEEDS} over {length} steps; failed "
          f"{np.flatnonzero(~success).tolist()}")
    assert rate >= 0.95
    # shapes and no NaN along the episodes
    t = jax.tree.map(np.asarray, trajs)
    assert t["action"].shape == (batch, length, env.action_size)
    for leaf in jax.tree.leaves(t):
        assert np.all(np.isfinite(leaf))
    # S maps the recorded demo onto the mirrored start's demo: actions to float round-off
    # (the script is open loop), observations up to the drift of two contact simulations.
    tm = jax.tree.map(np.asarray, traj_m)
    act_err = np.abs(np.asarray(env.action_symmetry(jnp.asarray(t["action"]))) - tm["action"]).max()
    obs_err = {f: np.abs(np.asarray(env.obs_symmetry.ops[f](jnp.asarray(t["obs"][f]))) - tm["obs"][f])
               for f in ("qpos", "ee")}
    print(f"{task}: max |a_mirror - S a| = {act_err:.1e}; obs qpos/ee error median "
          f"{np.median(obs_err['qpos']):.1e}/{np.median(obs_err['ee']):.1e}, "
          f"99th pct {np.percentile(obs_err['qpos'], 99):.1e}/{np.percentile(obs_err['ee'], 99):.1e}")
    assert act_err < 1e-3
    assert np.median(obs_err["qpos"]) < 1e-3 and np.percentile(obs_err["qpos"], 99) < 0.05
    assert np.median(obs_err["ee"]) < 1e-3 and np.percentile(obs_err["ee"], 99) < 0.05
    np.testing.assert_array_equal(np.asarray(ok_m), success[:batch])  # same outcomes
    assert np.abs(tm["action"] - t["action"]).max() > 0.05  # the other arm acted: not vacuous
    del first
