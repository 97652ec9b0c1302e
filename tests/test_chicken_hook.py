"""chicken_hook: task registry and option errors, model (physical, mirror-symmetric,
collision filter), initial distribution and the shift options' contract, success predicate
on hand-built states (MuJoCo C), and (slow) the scripted expert in MJX: the generic expert
check on the task's shared episodes (``task_rollouts.expert_episodes``), then both sides,
``wide_init=1.5`` (the shift the paper applies to this task) and perturbed episodes
(``asymmetric_quality=1.0``), all through the same compiled rollout program.
"""

import dataclasses
import types

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts.chicken_hook import ChickenHookExpertConfig
from equibim_jax.experts.chicken_hook import make_expert as chicken_expert
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names
from equibim_jax.tasks.chicken_hook import ChickenHook

from task_rollouts import collides, expert_fixtures, run_starts

TASK = "chicken_hook"


@pytest.fixture(scope="module")
def env():
    return make_env(TASK, obs=("qpos",))


def _data(env, qpos):
    d = mujoco.MjData(env.mj_model)
    d.qpos[:] = np.asarray(qpos, np.float64)
    d.ctrl[:] = env.home_ctrl
    mujoco.mj_forward(env.mj_model, d)
    return d


def _simulate(env, d, seconds):
    for _ in range(int(round(seconds / env.mj_model.opt.timestep))):
        mujoco.mj_step(env.mj_model, d)
    return d


def _terms(env, d, scene=None):
    scene = scene or env.scene
    t = scene.terms(mjx.put_data(env.mj_model, d), env)
    _, success, _ = scene.evaluate(mjx.put_data(env.mj_model, d), {}, env)
    return {k: float(v) for k, v in t.items()}, bool(success)


def _hanging_state(env, dz=0.004):
    """The toy hung on the peg (its loop's top corner ``dz`` above the peg), arms at home,
    then left to settle for 1.5 s in MuJoCo C."""
    sc = env.scene
    x = sc.hook_x - 0.06
    z = sc.peg_axis_height(x) - sc.loop_hang_drop - sc.ring_centre_z + dz
    q = sc.placed_qpos(jnp.asarray(env.home_qpos), env, [x, 0.0, z])
    return _simulate(env, _data(env, q), 1.5)


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors(env):
    assert TASK in task_names()
    entry = task_entry(TASK)
    assert entry.robot == "robot_b" and entry.step_limit == 600
    assert entry.env_defaults["obs"] == ("qpos", "point_cloud") and entry.env_defaults["n_points"] == 64
    assert ChickenHook.main_object == "chicken" and ChickenHook.sided is False
    with pytest.raises(ValueError, match="robot"):
        make_env(TASK, robot="robot_a")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['colour'\]"):
        make_env(TASK, colour="red")
    with pytest.raises(ValueError, match="side must be 'both'"):
        make_scene(TASK, side="left")
    with pytest.raises(ValueError, match="side must be one of"):
        make_scene(TASK, side="middle")
    with pytest.raises(ValueError, match="wide_init must be a factor >= 1"):
        make_scene(TASK, wide_init=0.5)
    with pytest.raises(ValueError, match="asymmetric_quality must be a fraction"):
        make_scene(TASK, asymmetric_quality=1.5)
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, toy_x_range=(0.2, 0.1))
    with pytest.raises(ValueError, match="symmetric about 0"):
        make_scene(TASK, yaw_range=(0.0, 0.3))
    with pytest.raises(ValueError, match="ring_segments"):
        make_scene(TASK, ring_segments=7)
    with pytest.raises(ValueError, match="hole"):
        make_scene(TASK, peg_radius=0.02)
    with pytest.raises(ValueError, match="peg_tilt_deg"):
        make_scene(TASK, peg_tilt_deg=60.0)
    with pytest.raises(ValueError, match="ChickenHook scene"):
        chicken_expert(types.SimpleNamespace(scene=object()))
    with pytest.raises(ValueError, match="durations"):
        ChickenHookExpertConfig(durations=(10, 10))


# ---------------------------------------------------------------------------- model
def test_model_physical_and_mirror_symmetric(env):
    m = env.mj_model
    assert env.sym.dynamics_exact, env.sym.dynamics.describe()
    toy = m.body("chicken").id
    assert 0.06 <= m.body_subtreemass[toy] <= 0.1
    # the toy's free joint maps onto itself
    a = int(m.jnt_qposadr[m.joint("chicken").id])
    assert np.array_equal(np.asarray(env.sym.qpos.perm[a : a + 7]), np.arange(a, a + 7))
    # the loop: a closed polygon whose hole is a few cm wide, around the peg's 1 cm
    sc = env.scene
    corners = sc.ring_corners()
    assert np.allclose(np.linalg.norm(corners[:, 1:] - [0, sc.ring_centre_z], axis=1), sc.ring_radius)
    hole = 2 * (sc.ring_radius * np.cos(np.pi / sc.ring_segments) - sc.ring_capsule)
    assert 0.03 < hole and hole > 2 * sc.peg_radius + 0.02
    # collision filter: the grippers touch the knobs only; the loop the peg only; the body
    # the table and the post; the hook never the grippers
    g = lambda n: m.geom(n).id
    pads = [g(p) for side in env.info.gripper_pads for p in side] + [g("left_palm"), g("right_palm")]
    toy_geoms = [i for i in range(m.ngeom) if m.geom_bodyid[i] == toy]
    for pad in pads:
        touching = {m.geom(i).name for i in toy_geoms if collides(m, pad, i)}
        assert touching == {"chicken_knob_left", "chicken_knob_right"}
        for h in ("hook_peg", "hook_post"):
            assert not collides(m, pad, g(h))
    for k in range(sc.ring_segments):
        partners = [m.geom(i).name for i in range(m.ngeom) if collides(m, g(f"chicken_loop_{k}"), i)]
        assert partners == ["hook_peg"]
    partners = {m.geom(i).name for i in range(m.ngeom) if collides(m, g("chicken_hull"), i)}
    assert partners == {"table", "hook_post"}
    assert not any(collides(m, g("chicken_body"), i) for i in range(m.ngeom))


def test_toy_stands_and_hangs_physically(env):
    sc = env.scene
    q = sc.placed_qpos(jnp.asarray(env.home_qpos), env, [0.15, 0.0, sc.rest_height])
    d = _simulate(env, _data(env, q), 1.0)
    b = env.mj_model.body("chicken").id
    assert np.abs(d.xpos[b] - [0.15, 0.0, sc.rest_height]).max() < 1e-3
    assert d.xmat[b][8] > 0.999  # upright
    # hung on the peg, it stays there (the peg's tilt keeps it from sliding off the tip)
    d = _hanging_state(env)
    _simulate(env, d, 1.5)
    assert d.xpos[b][0] > sc.peg_tip[0] + 0.02 and d.xpos[b][2] > sc.min_height


# ---------------------------------------------------------------------------- init
def _starts(scene, env, n=256, seed=3):
    keys = jax.random.split(jax.random.key(seed), n)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    return np.asarray(qpos), jax.tree.map(np.asarray, info)


def test_initial_distribution_and_shift_contract(env):
    sc = env.scene
    a = int(env.mj_model.jnt_qposadr[env.mj_model.joint("chicken").id])
    q, info = _starts(sc, env)
    assert set(info) == {"side", "yaw", "perturbed"}
    assert info["side"].dtype == np.float32 and info["yaw"].dtype == np.float32
    assert info["perturbed"].dtype == bool and not info["perturbed"].any()
    assert set(np.unique(info["side"])) == {-1.0, 1.0}
    x, y = q[:, a], q[:, a + 1]
    np.testing.assert_allclose(np.sign(q[:, a + 3]), info["side"])  # quaternion s (cos, 0, 0, sin)
    yaw = 2 * np.arctan2(q[:, a + 6] * info["side"], q[:, a + 3] * info["side"])
    assert np.all((x >= 0.13) & (x <= 0.17)) and np.all(np.abs(y) <= 0.01 + 1e-7)
    np.testing.assert_allclose(yaw, info["yaw"], atol=1e-5)
    assert np.abs(yaw).max() <= 0.3 + 1e-6
    np.testing.assert_allclose(q[:, a + 2], sc.rest_height)
    np.testing.assert_array_equal(q[:, : a], np.broadcast_to(env.home_qpos[:a], q[:, :a].shape))

    # same key, one option: it changes only what it names
    qm, im = _starts(dataclasses.replace(sc, mirrored_orientation=True), env)
    np.testing.assert_array_equal(np.delete(qm, np.arange(a + 3, a + 7), axis=1),
                                  np.delete(q, np.arange(a + 3, a + 7), axis=1))
    np.testing.assert_allclose(im["yaw"], -info["yaw"], atol=1e-6)
    qp, ip = _starts(dataclasses.replace(sc, asymmetric_quality=1.0), env)
    np.testing.assert_array_equal(qp, q)
    assert ip["perturbed"].all()  # no sides: every episode is perturbed
    qh, ih = _starts(dataclasses.replace(sc, asymmetric_quality=0.5), env, n=512)
    assert 0.4 < ih["perturbed"].mean() < 0.6
    qw, _ = _starts(dataclasses.replace(sc, wide_init=1.5), env)
    xw = qw[:, a]
    assert xw.min() < 0.13 and xw.max() > 0.17 and np.all((xw >= 0.12) & (xw <= 0.18))
    assert np.abs(qw[:, a + 1]).max() > 0.01 and np.abs(qw[:, a + 1]).max() <= 0.015 + 1e-7

    # the mirror of a start is the start drawn with the other side sign
    class Flipped(ChickenHook):
        def draw_side(self, key):
            return -super().draw_side(key)

    qf, inf = _starts(Flipped(), env)
    mirrored = np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(q)))
    np.testing.assert_allclose(mirrored, qf, atol=1e-6)
    mi = jax.vmap(lambda i: sc.mirror_info(i, env))(info)
    for k in ("side", "yaw", "perturbed"):
        np.testing.assert_allclose(np.asarray(mi[k]), inf[k], atol=1e-6)


# ---------------------------------------------------------------------------- success
def test_success_predicate_on_hand_built_states(env):
    sc = env.scene
    # at a start, settled for 0.2 s: on the table
    q, _ = _starts(sc, env, n=1)
    t, ok = _terms(env, _simulate(env, _data(env, q[0]), 0.2))
    assert not ok and not t["off_table"] and not t["on_peg"] and not t["high"]
    # hanging on the peg, the arms at home: success
    d = _hanging_state(env)
    t, ok = _terms(env, d)
    assert ok, t
    assert t["on_peg"] and t["off_table"] and t["high"] and t["released"]
    # the same state with a stricter height: not high enough
    z = float(d.xpos[env.mj_model.body("chicken").id][2])
    t, ok = _terms(env, d, dataclasses.replace(sc, min_height=z + 0.01))
    assert not ok and not t["high"]
    # the toy in the air beside the hook (no contact): not on the peg
    q = sc.placed_qpos(jnp.asarray(env.home_qpos), env, [0.15, 0.0, 0.09])
    t, ok = _terms(env, _data(env, q))
    assert not ok and not t["on_peg"] and t["off_table"]
    # a gripper pad on a knob: not released
    m = env.mj_model
    d0 = _data(env, env.home_qpos)
    pad = m.geom(env.info.gripper_pads[0][0]).id
    knob = sc.knob_local()[0]
    q = sc.placed_qpos(jnp.asarray(env.home_qpos), env, d0.geom_xpos[pad] - knob)
    t, ok = _terms(env, _data(env, q))
    assert not ok and not t["released"] and t["pad_knob_dist"] < 0


# ---------------------------------------------------------------------------- slow
N_DEFAULT, N_WIDE, N_PERTURBED = 2, 6, 12


class _Flipped(ChickenHook):
    """The scene drawing every start with the other side sign (its start is the mirror
    image of the default scene's start from the same key)."""

    def draw_side(self, key):
        return -super().draw_side(key)


episodes, test_expert_generic_checks = expert_fixtures(TASK)


@pytest.fixture(scope="module")
def rollouts(episodes):
    """The shared episodes' compiled rollout program run from starts drawn by four scenes on
    the same model: N_DEFAULT seeds, their mirror images (the starts drawn with the other
    side sign, exactly the mirrored states), N_WIDE starts with ``wide_init=1.5`` and
    N_PERTURBED with ``asymmetric_quality=1.0``; the program resets to each draw."""
    env = episodes.env
    sc = env.scene
    scenes = [(sc, N_DEFAULT), (_Flipped(), N_DEFAULT), (dataclasses.replace(sc, wide_init=1.5), N_WIDE),
              (dataclasses.replace(sc, asymmetric_quality=1.0), N_PERTURBED)]
    k0, k1, k2 = jax.random.split(jax.random.key(5), 3)

    @jax.jit  # one small program for the four scenes' draws (vmap alone runs op by op)
    def draws():
        parts = [jax.vmap(lambda k, s=s: s.init(k, env))(jax.random.split(k, n))
                 for (s, n), k in zip(scenes, (k0, k0, k1, k2))]
        return jax.tree.map(lambda *a: jnp.concatenate(a), *parts)

    qpos, info = draws()
    _, final, _ = run_starts(episodes, qpos, info)
    return jax.tree.map(np.asarray, info), np.asarray(final.info["success"])


@pytest.mark.slow
def test_expert_succeeds_on_both_sides(rollouts):
    info, success = rollouts
    n = 2 * N_DEFAULT
    assert set(info["side"][:n]) == {-1.0, 1.0}
    assert success[:n].all(), success[:n]


@pytest.mark.slow
def test_expert_succeeds_with_wide_init(rollouts):
    info, success = rollouts
    sl = slice(2 * N_DEFAULT, 2 * N_DEFAULT + N_WIDE)
    assert not info["perturbed"][sl].any()
    assert success[sl].sum() >= N_WIDE - 1, success[sl]


@pytest.mark.slow
def test_perturbed_episodes_fail(rollouts):
    info, success = rollouts
    sl = slice(2 * N_DEFAULT + N_WIDE, None)
    assert info["perturbed"][sl].all()
    assert not success[sl].any(), success[sl]
