"""move_can_pot: task registry and option errors, model, initial distribution and its mirror
symmetry, jitted reset/step, success predicate, scripted expert (success on both sides
and mirror equivariance).

The slow expert tests share one compiled rollout program per module, the task's
``task_rollouts.expert_episodes``: the expert from 50 seeded starts and from the mirror
images of the first 25 (so both sides are always covered), run 10 steps past the end of
its script. The same episodes serve the generic expert check (success rate, shapes, ``S`` on
the recorded demos) and this file's task-specific checks.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts import make_expert
from equibim_jax.experts.move_can_pot import CanExpertConfig
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.move_can_pot import MoveCanPot

from task_rollouts import N_PAIRS, assert_same_point_set, collides, expert_fixtures

TASK = "move_can_pot"
N_SEEDS = N_PAIRS  # starts kept whole in the shared expert episodes, each with its mirror image
REFLECT = np.array([1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def env():
    return make_env(TASK, side="both")


episodes, test_expert_generic_checks = expert_fixtures(TASK)


@pytest.fixture(scope="module")
def rollouts(episodes):
    """(initial states [2N], final states [2N], traj) for N starts then their N mirror images."""
    return episodes.s0, episodes.final, episodes.traj


def _poses(env, qpos):
    """(can [B, 3], pot [B, 3], pot yaw [B]) from qpos [B, nq]."""
    can, pot, yaw = jax.vmap(lambda q: env.scene.poses_from_qpos(q, env))(jnp.asarray(qpos))
    return np.asarray(can), np.asarray(pot), np.asarray(yaw)


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors(env):
    assert TASK in task_names()
    assert task_entry(TASK).expert is not None and task_entry(TASK).step_limit == 400
    with pytest.raises(ValueError, match="valid tasks: .*move_can_pot"):
        make_env("move_can_pan")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['lid'\].*valid options: .*pot_max_yaw"):
        make_env(TASK, lid=True)
    with pytest.raises(ValueError, match="side must be one of"):
        make_env(TASK, side="centre")
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, can_y_range=(0.3, 0.2))
    with pytest.raises(ValueError, match="starts clear of the pot"):
        make_scene(TASK, can_y_range=(0.08, 0.3))
    with pytest.raises(ValueError, match="pot_max_yaw"):
        make_scene(TASK, pot_max_yaw=2.0)
    with pytest.raises(ValueError, match="no room beside the pot"):
        make_scene(TASK, beside_max_dy=0.09)
    with pytest.raises(ValueError, match="half sizes"):
        make_scene(TASK, can_half=(0.02, 0.02))
    with pytest.raises(ValueError, match="not a valid"):
        make_scene(TASK, success_dx="near")
    with pytest.raises(ValueError, match="unknown option"):
        make_scene(TASK, n_points=3)  # an env option, not a scene one
    with pytest.raises(ValueError, match="place_gap"):
        make_expert(env, config=CanExpertConfig(place_gap=0.15))
    with pytest.raises(ValueError, match="grasp_below_top"):
        make_expert(env, config=CanExpertConfig(grasp_below_top=-0.01))
    assert {"obs", "action", "episode_length", "side", "can_y_range", "pot_max_yaw"} <= set(task_options(TASK))
    assert env.config.episode_length == 400  # the task's step limit
    assert env.config.obs == ("qpos", "point_cloud") and env.config.n_points == 64
    assert env.scene == MoveCanPot(side="both")
    assert make_scene(TASK, can_y_range="0.21,0.29").can_y_range == (0.21, 0.29)  # strings are parsed


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    assert m.neq == 0 and m.nmocap == 0  # no welds, no mocap
    assert m.jnt_type[m.joint("can").id] == mujoco.mjtJoint.mjJNT_FREE
    assert abs(m.body_mass[m.body("can").id] - 0.06) < 1e-9
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    # pot: x slides along the plane (keeps its sign), y and the yaw flip
    for name, sign in (("pot_x", 1.0), ("pot_y", -1.0), ("pot_yaw", -1.0)):
        j = m.joint(name).id
        assert env.sym.joints[j] == j and env.sym.joint_signs[j] == sign
    # no cylinder anywhere (MJX has no box-cylinder collision, the renderer draws none)
    assert not np.any(m.geom_type == mujoco.mjtGeom.mjGEOM_CYLINDER)
    # Few contact pairs: the can touches the grippers, the table and the pot; the pot only the can.
    geom = lambda n: m.geom(n).id
    gripper = {geom(f"{s}_{g}") for s in ("left", "right") for g in ("pad_a", "pad_b", "palm")}
    partners = lambda g: {h for h in range(m.ngeom) if m.geom_bodyid[h] != m.geom_bodyid[g] and collides(m, g, h)}
    assert partners(geom("can")) == gripper | {geom("table"), geom("pot")}
    assert partners(geom("pot")) == {geom("can")}


def test_pot_at_yaw_zero_is_its_own_mirror_image(env):
    q = env.scene.placed_qpos(jnp.asarray(env.home_qpos), env, (0.3, 0.25, env.scene.can_half[2]),
                              pot_xy_yaw=(0.29, 0.0, 0.0))
    qm = env.sym.qpos(q)
    _, pot, yaw = _poses(env, np.asarray(q)[None])
    _, pot_m, yaw_m = _poses(env, np.asarray(qm)[None])
    np.testing.assert_allclose(pot_m, pot, atol=1e-9)
    assert yaw_m[0] == 0.0 and yaw[0] == 0.0


def test_initial_distribution(env):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    can, pot, yaw = _poses(env, qpos)
    side = np.asarray(info["side"])
    assert 0.45 < (side > 0).mean() < 0.55
    np.testing.assert_array_equal(np.sign(can[:, 1]), side)
    assert np.all((can[:, 0] >= scene.can_x_range[0]) & (can[:, 0] <= scene.can_x_range[1]))
    assert np.all((np.abs(can[:, 1]) >= 0.2) & (np.abs(can[:, 1]) <= 0.3))
    np.testing.assert_allclose(can[:, 2], scene.can_half[2], atol=1e-6)  # standing on the table
    assert np.all(pot[:, 1] == 0.0)
    assert np.all((pot[:, 0] >= scene.pot_x_range[0]) & (pot[:, 0] <= scene.pot_x_range[1]))
    assert np.all(np.abs(yaw) <= math.pi / 8 + 1e-6) and np.abs(yaw).max() > 0.9 * math.pi / 8
    # The law is mirror-symmetric: from the same key, side="right" draws the can's mirror
    # image of what side="left" draws and the same pot, and the yaw's law is that of -yaw
    # (uniform on a symmetric interval: its quantiles are odd).
    draw = lambda side_opt: _poses(env, jax.jit(jax.vmap(
        lambda k: dataclasses.replace(scene, side=side_opt).init(k, env)[0]))(keys[:256]))
    (can_l, pot_l, yaw_l), (can_r, pot_r, yaw_r) = draw("left"), draw("right")
    np.testing.assert_array_equal(can_r, can_l * REFLECT)
    np.testing.assert_array_equal(pot_r, pot_l)
    np.testing.assert_array_equal(yaw_r, yaw_l)
    np.testing.assert_allclose(np.quantile(yaw, [0.1, 0.5, 0.9]), -np.quantile(yaw, [0.9, 0.5, 0.1]), atol=0.03)
    # the can starts clear of the pot's footprint
    assert np.all(np.abs(can[:, 1]) - scene.can_half[1] > scene.pot_reach_y(np.abs(yaw)))
    # the point-cloud crop holds every can and pot the distribution can place
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    assert np.all(can[:, :2] - 0.025 >= lo[:2]) and np.all(can[:, :2] + 0.025 <= hi[:2])
    assert np.all(pot[:, 0] - 0.085 >= lo[0]) and np.all(pot[:, 0] + 0.085 <= hi[0])
    assert 2 * scene.can_half[2] <= hi[2] and 2 * scene.pot_half[2] <= hi[2]
    np.testing.assert_allclose(np.asarray(qpos)[:, : env.info.nq_robot],
                               np.broadcast_to(env.home_qpos[: env.info.nq_robot], (len(keys), env.info.nq_robot)))
    for side_opt, sgn in (("left", 1.0), ("right", -1.0)):
        e = make_env(TASK, side=side_opt, obs=("qpos",))
        _, inf = jax.vmap(lambda k: e.scene.init(k, e))(keys[:16])
        assert np.all(np.asarray(inf["side"]) == sgn)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_mirror_of_a_start_is_a_start(env, rollouts):
    """``env.mirror_state`` of sampled starts: can and pot reflected, yaw negated, side
    flipped, arms at home, every constraint of the distribution met, the cloud reflected."""
    s0, _, _ = rollouts
    scene, n = env.scene, N_SEEDS
    can, pot, yaw = _poses(env, s0.data.qpos)
    side = np.asarray(s0.info["side"])
    np.testing.assert_allclose(can[n:], can[:n] * REFLECT, atol=1e-6)
    np.testing.assert_allclose(pot[n:], pot[:n] * REFLECT, atol=1e-6)
    np.testing.assert_allclose(yaw[n:], -yaw[:n], atol=1e-6)
    np.testing.assert_array_equal(side[n:], -side[:n])
    np.testing.assert_array_equal(np.sign(can[:, 1]), side)
    assert np.all((np.abs(can[:, 1]) >= 0.2) & (np.abs(can[:, 1]) <= 0.3))
    assert np.all(np.abs(pot[:, 1]) == 0.0) and np.all(np.abs(yaw) <= scene.pot_max_yaw)
    q = np.asarray(s0.data.qpos)[:, : env.info.nq_robot]
    np.testing.assert_allclose(q, np.broadcast_to(env.home_qpos[: env.info.nq_robot], q.shape), atol=1e-6)
    pts = np.asarray(s0.obs["point_cloud"])
    for i in range(n):
        assert_same_point_set(pts[i] * REFLECT, pts[n + i], atol=1e-5)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_jit_reset_step_shapes_no_nan(env, rollouts):
    """Reset and step (inside the jitted rollout) give the documented shapes, finite values,
    and no success at reset."""
    s0, final, traj = rollouts
    b = 2 * N_SEEDS
    for s in (s0, final):
        assert s.obs["qpos"].shape == (b, 14)
        assert s.obs["point_cloud"].shape == (b, 64, 3)
        assert s.reward.shape == (b,) and s.done.shape == (b,)
        assert all(np.all(np.isfinite(np.asarray(v))) for v in s.obs.values())
        assert np.all(np.isfinite(np.asarray(s.data.qpos)))
    assert not np.any(np.asarray(s0.info["success"])) and not np.any(np.asarray(s0.reward))
    assert traj["action"].shape[::2] == (b, 14) and traj["success"].shape == traj["action"].shape[:2]
    assert np.all(np.isfinite(traj["action"])) and np.all(np.isfinite(traj["qpos"]))
    assert np.all(np.asarray(final.info["step"]) == traj["action"].shape[1])
    assert not np.any(np.asarray(final.metrics["nan_action"]))


# ---------------------------------------------------------------------------- predicate
def _evaluate(env, qpos, side, opening=None):
    """(success, terms) of a state built by hand on the host (no stepping)."""
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(qpos)
    if opening is not None:
        for s, o in enumerate(opening):
            d.qpos[env.grip_qadr[s]] = np.asarray(env.info.gripper_ctrl(o))
    mujoco.mj_forward(m, d)
    _, success, metrics = env.scene.evaluate(mjx.put_data(m, d), {"side": jnp.asarray(side)}, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def _placed_qpos(env, dx=0.0, dy=0.12, dz=0.0, tilt_deg=0.0, side=1.0, yaw=0.0):
    scene = env.scene
    pot = (0.29, 0.0, yaw)
    half = np.deg2rad(tilt_deg) / 2
    quat = (np.cos(half), np.sin(half), 0.0, 0.0)  # about x
    can = (pot[0] + dx, side * dy, env.info.table_height + scene.can_half[2] + dz)
    return np.asarray(scene.placed_qpos(jnp.asarray(env.home_qpos), env, can, quat, pot_xy_yaw=pot))


def test_success_predicate_cases(env):
    ev = lambda side=1.0, opening=None, **kw: _evaluate(env, _placed_qpos(env, side=side, **kw), side, opening)
    assert ev()[0]  # beside the pot, upright, both grippers at home (open)
    assert ev(side=-1.0)[0]
    assert ev(dx=0.03, dy=0.19, dz=0.01, tilt_deg=10.0, yaw=0.39)[0]  # inside every tolerance
    ok, t = ev(dx=0.04)
    assert not ok and abs(t["can_pot_dx"] - 0.04) < 1e-5  # in front of the pot's side, not beside it
    assert not ev(dy=0.25)[0]  # too far from the pot
    # on the other side of the pot than it started
    ok, t = _evaluate(env, _placed_qpos(env, side=-1.0), 1.0)
    assert not ok and t["can_pot_dy_own_side"] < 0
    assert not ev(dz=0.03)[0]  # held above the table
    ok, t = ev(tilt_deg=20.0)
    assert not ok and abs(t["can_tilt_deg"] - 20.0) < 1e-3
    # standing on top of the pot, or (unphysically) inside its footprint
    ok, t = ev(dy=0.0, dz=2 * env.scene.pot_half[2])
    assert not ok and t["clear_of_pot"] == 0.0
    ok, t = ev(dy=0.05)
    assert not ok and t["clear_of_pot"] == 0.0
    # a gripper squeezing the 5 cm can (opening ~0.51) or closed is not released
    held = float(env.info.opening_for_gap(2 * env.scene.can_half[1]))
    assert 0.45 < held < 0.6
    assert not ev(opening=(held, 1.0))[0]
    assert not ev(opening=(1.0, 0.0))[0]
    q0, info0 = env.scene.init(jax.random.key(5), env)  # where it starts
    assert not _evaluate(env, q0, info0["side"])[0]


# ---------------------------------------------------------------------------- expert
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_success_both_sides(env, rollouts):
    s0, final, traj = rollouts
    success, side = np.asarray(final.info["success"]), np.asarray(s0.info["side"])
    assert set(side.tolist()) == {-1.0, 1.0}
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    print(f"\nexpert success {success.sum()}/{success.size}, sides {side}, first success step {first}")
    assert success.sum() >= success.size - 1
    # the grasp held by friction: the can rose by about the carry lift
    a = env.scene._ids(env)["can_qadr"]
    lift = traj["qpos"][:, :, a + 2].max(axis=1) - np.asarray(s0.data.qpos)[:, a + 2]
    assert np.all(lift > 0.04), lift


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(env, rollouts):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored can trajectory."""
    _, _, traj = rollouts
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    a = env.scene._ids(env)["can_qadr"]
    can, can_m = traj["qpos"][:n, :, a : a + 3], traj["qpos"][n:, :, a : a + 3]
    can_err = np.abs(can_m - can * REFLECT).max()
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; "
          f"max can position error = {can_err * 1000:.3f} mm over {acts.shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the other arm acted: the check is not vacuous
    assert act_err < 1e-3
    assert can_err < 5e-3
