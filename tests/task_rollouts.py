"""Shared by the task test files: expert episodes from seeded starts and their mirror images,
and the generic checks every task's expert must pass."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.experts import make_expert, make_rollout
from equibim_jax.tasks import make_env


def collides(m, g1: int, g2: int) -> bool:
    """Whether MuJoCo's contype/conaffinity filter lets geoms g1 and g2 collide."""
    return bool((m.geom_contype[g1] & m.geom_conaffinity[g2]) or (m.geom_contype[g2] & m.geom_conaffinity[g1]))


# ------------------------------------------------------------------ generic expert episodes
# One compiled program per task serves both the generic expert check (success rate and S on
# recorded demos) and the task file's own checks of the expert (what it grasped, where the
# objects went, the mirrored start, starts drawn by other scenes of the task). Tasks without a
# test file of their own get the generic check from test_all_tasks.py.
N_STARTS = 50  # the first 50 of the 200 seeded starts that `equibim experts --episodes 200` runs
N_PAIRS = 25  # of these, the first 25 also run from their mirror images (one batch each)
EXPERT_SEED = 2024  # `equibim experts`' default seed
EPISODE_OBS = ("qpos", "ee")  # observed at every step (recorded in ``traj["obs"]``)
START_OBS = "point_cloud"  # rendered for the initial and final states only: per step it would
#                            double the program's run time and add to its compile time


@dataclasses.dataclass(frozen=True)
class ExpertEpisodes:
    """The task's expert run from ``N_STARTS`` seeded starts and the mirror images of the first
    ``N_PAIRS``, for ``length`` steps (the script's horizon + 10).

    ``s0``, ``final`` and ``traj`` hold ``2 * N_PAIRS`` episodes: index ``i < N_PAIRS`` is start
    ``i``, index ``N_PAIRS + i`` its mirror image (``env.mirror_state``). States are as the env
    (observing ``EPISODE_OBS``) returns them, with the ``START_OBS`` point cloud of the same
    data added to ``obs``; ``traj`` as numpy arrays ``[2 * N_PAIRS, length, ...]`` with
    ``action``, ``success``, ``reward``, ``qpos`` and ``obs`` (``EPISODE_OBS``). ``success``
    holds the latched final success of all ``N_STARTS``.

    ``run(qpos [N_PAIRS, nq], info, mirror [N_PAIRS] bool) -> (s0, final, traj)`` is the
    compiled program itself: ``env.reset_to`` each drawn start (``scene.init``'s pair, from
    any scene of the task on the same model), ``env.mirror_state`` where ``mirror``, then the
    expert (``run_starts`` batches it). ``draw(keys [n]) -> (qpos, info)`` is the env's own
    scene's draw.
    """

    task: str
    env: object
    length: int
    s0: object
    final: object
    traj: dict
    success: np.ndarray
    run: object
    draw: object


def expert_episodes(task: str, **options) -> ExpertEpisodes:
    """Run the expert of ``task`` (env built with ``obs=EPISODE_OBS`` and ``options``) from the
    first ``N_STARTS`` starts of ``equibim experts``' seeds and from the mirror images of the
    first ``N_PAIRS``: one compiled program (reset, mirror, rollout) over batches of
    ``N_PAIRS``, and a small one rendering the point clouds of its first and last states."""
    env = make_env(task, obs=EPISODE_OBS, **options)
    cloud_env = make_env(task, obs=(START_OBS,), **options)
    expert = make_expert(env)
    length = expert.horizon + 10
    roll = make_rollout(env, expert, length=length, obs=True)

    @jax.jit
    def draw(keys):
        return jax.vmap(lambda k: env.scene.init(k, env))(keys)

    @jax.jit
    def run(qpos, info, mirror):
        s = jax.vmap(env.reset_to)(qpos, info)
        sm = jax.vmap(env.mirror_state)(s)
        s0 = jax.tree.map(lambda a, b: jnp.where(mirror.reshape((-1,) + (1,) * (a.ndim - 1)), b, a), s, sm)
        return (s0, *jax.vmap(roll.from_state)(s0))

    @jax.jit
    def clouds(data):
        return jax.vmap(cloud_env.observe)(data)[START_OBS]

    keys = jax.random.split(jax.random.key(EXPERT_SEED), 200)[:N_STARTS]
    qpos, info = draw(keys)
    part = lambda t, i: jax.tree.map(lambda a: a[i : i + N_PAIRS], t)
    cat = lambda a, b: jax.tree.map(lambda x, y: jnp.concatenate([x, y]), a, b)
    no = jnp.zeros(N_PAIRS, bool)
    success = []
    for i in range(0, N_STARTS, N_PAIRS):
        s0, final, traj = run(part(qpos, i), part(info, i), no)
        success.append(np.asarray(final.info["success"]))
        if i == 0:
            pair = (s0, final, traj), run(part(qpos, 0), part(info, 0), ~no)
    (s0, final, traj), (s0_m, final_m, traj_m) = pair
    with_cloud = lambda s: s.replace(obs={**s.obs, START_OBS: clouds(s.data)})
    s0, final = with_cloud(cat(s0, s0_m)), with_cloud(cat(final, final_m))
    traj = jax.tree.map(np.asarray, cat(traj, traj_m))
    return ExpertEpisodes(task, env, length, s0, final, traj, np.concatenate(success), run, draw)


def check_expert_episodes(ep: ExpertEpisodes, min_rate: float = 0.95) -> None:
    """The generic checks of a task's expert: a success rate of at least ``min_rate`` over the
    ``N_STARTS`` starts; shapes, finite values and no success at reset; and ``S`` maps each
    recorded demo onto the one recorded from the mirrored start: actions to float round-off
    (the script is open loop), ``qpos`` and ``ee`` observations up to the drift of two contact
    simulations, with the same outcomes."""
    env, n, length = ep.env, N_PAIRS, ep.length
    print(f"\n{ep.task}: expert success {ep.success.sum()}/{N_STARTS} over {length} steps; failed "
          f"{np.flatnonzero(~ep.success).tolist()}")
    assert ep.success.mean() >= min_rate
    nq = env.mj_model.nq
    assert ep.s0.data.qpos.shape == (2 * n, nq)
    assert ep.s0.obs["qpos"].shape == (2 * n, 2 * (env.info.n_arm + 1))
    assert ep.s0.obs["ee"].shape == (2 * n, 2 * 10)
    assert ep.s0.obs["point_cloud"].shape == (2 * n, env.config.n_points, 3)
    assert not np.asarray(ep.s0.info["success"]).any() and not np.asarray(ep.s0.reward).any()
    t = ep.traj
    assert t["action"].shape == (2 * n, length, env.action_size)
    assert t["qpos"].shape == (2 * n, length, nq) and t["success"].shape == (2 * n, length)
    for leaf in jax.tree.leaves(t):
        assert np.all(np.isfinite(leaf))
    assert np.all(np.asarray(ep.final.info["step"]) == length)
    assert not np.any(np.asarray(ep.final.metrics["nan_action"]))
    act, act_m = t["action"][:n], t["action"][n:]
    act_err = np.abs(np.asarray(env.action_symmetry(jnp.asarray(act))) - act_m).max()
    obs_err = {f: np.abs(np.asarray(env.obs_symmetry.ops[f](jnp.asarray(t["obs"][f][:n]))) - t["obs"][f][n:])
               for f in ("qpos", "ee")}
    print(f"max |a_mirror - S a| = {act_err:.1e}; obs qpos/ee error median "
          f"{np.median(obs_err['qpos']):.1e}/{np.median(obs_err['ee']):.1e}, "
          f"99th pct {np.percentile(obs_err['qpos'], 99):.1e}/{np.percentile(obs_err['ee'], 99):.1e}")
    assert act_err < 1e-3
    assert np.median(obs_err["qpos"]) < 1e-3 and np.percentile(obs_err["qpos"], 99) < 0.05
    assert np.median(obs_err["ee"]) < 1e-3 and np.percentile(obs_err["ee"], 99) < 0.05
    ok = np.asarray(ep.final.info["success"])
    np.testing.assert_array_equal(ok[n:], ok[:n])  # same outcomes
    assert np.abs(act_m - act).max() > 0.05  # the other arm acted: the check is not vacuous


def expert_fixtures(task: str, **options):
    """The two module-level pieces every task test file needs, defined once here:
    ``episodes`` (a module-scoped fixture: ``expert_episodes(task, **options)``) and
    ``test_expert_generic_checks`` (slow: ``check_expert_episodes`` on those episodes).

    Usage, at module level of ``tests/test_<task>.py``::

        episodes, test_expert_generic_checks = expert_fixtures("click_bell")

    The test function carries ``expert_task = task``, which ``test_all_tasks`` checks.
    """

    @pytest.fixture(scope="module")
    def episodes():
        """The task's shared expert episodes: 50 seeded starts, the first 25 also from their
        mirror images, one compiled program (``expert_episodes``)."""
        return expert_episodes(task, **options)

    @pytest.mark.slow  # the expert-rollout compile; CI runs it with the slow suite
    def test_expert_generic_checks(episodes):
        """Success rate over 50 starts, shapes, and S on the recorded demos (``check_expert_episodes``)."""
        check_expert_episodes(episodes)

    test_expert_generic_checks.expert_task = task
    return episodes, test_expert_generic_checks


def run_starts(ep: ExpertEpisodes, qpos, info, mirror=None):
    """Run the expert of ``ep`` from any batch of drawn starts ``(qpos [n, nq], info)`` (the
    pair a scene of the task returns from ``scene.init``; ``mirror [n]`` bool: start from the
    mirror image instead, default none) through the episodes' compiled program, ``N_PAIRS``
    at a time (the last batch padded with copies of the first start). Returns
    ``(s0, final, traj)`` with leading dimension ``n``; ``traj`` as numpy arrays."""
    n = int(qpos.shape[0])
    mirror = jnp.zeros(n, bool) if mirror is None else jnp.asarray(mirror, bool)
    args = (qpos, info, mirror)
    pad = -n % N_PAIRS
    if pad:
        args = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[:1], pad, axis=0)]), args)
    compiled = ep.run._cache_size()
    outs = [ep.run(*jax.tree.map(lambda a: a[i : i + N_PAIRS], args)) for i in range(0, n + pad, N_PAIRS)]
    assert ep.run._cache_size() == compiled, "the starts are not (qpos, info) of the episodes' task: it recompiled"
    s0, final, traj = jax.tree.map(lambda *a: jnp.concatenate(a)[:n], *outs)
    return s0, final, jax.tree.map(np.asarray, traj)


def assert_same_point_set(a: np.ndarray, b: np.ndarray, atol: float) -> None:
    """Assert that two ``[P, 3]`` clouds hold the same points, duplicates counted: the best
    one-to-one matching (an assignment on the distance matrix) moves no point by more than
    ``atol``. Robust to order and to near-ties that defeat a sort by rounded coordinates."""
    from scipy.optimize import linear_sum_assignment

    assert a.shape == b.shape, (a.shape, b.shape)
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    rows, cols = linear_sum_assignment(d)
    worst = d[rows, cols].max()
    assert worst <= atol, f"the clouds differ: a matched point is {worst:.2e} away (atol {atol:.0e})"
