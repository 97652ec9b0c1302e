"""beat_block_hammer: task registry and option errors, model, initial distribution and its
mirror symmetry, jitted reset/step, success predicate, scripted expert (success on both
sides and mirror equivariance).

The slow expert tests share one compiled rollout program per module, the task's
``task_rollouts.expert_episodes``: the expert from 50 seeded starts and from the mirror
images of the first 25 (so both sides are always covered), run 10 steps past the end of
its script. The same episodes serve the generic expert check (success rate, shapes, ``S`` on
the recorded demos) and this file's task-specific checks.
"""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts import make_expert
from equibim_jax.experts.beat_block_hammer import HammerExpertConfig
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.beat_block_hammer import HEAD_BIT, BeatBlockHammer

from task_rollouts import N_PAIRS, assert_same_point_set, collides, expert_fixtures

TASK = "beat_block_hammer"
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


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors(env):
    assert TASK in task_names()
    assert task_entry(TASK).expert is not None and task_entry(TASK).step_limit == 400
    with pytest.raises(ValueError, match="valid tasks: .*beat_block_hammer"):
        make_env("beat_block_hammers")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['nails'\].*valid options: .*block_y_range"):
        make_env(TASK, nails=3)
    with pytest.raises(ValueError, match="side must be one of"):
        make_env(TASK, side="middle")
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, block_x_range=(0.4, 0.3))
    with pytest.raises(ValueError, match="three positive half sizes"):
        make_scene(TASK, block_half=(0.02, 0.0, 0.02))
    with pytest.raises(ValueError, match="clear of the hammer's head"):
        make_scene(TASK, block_y_range=(0.03, 0.2))
    with pytest.raises(ValueError, match="clear of the hammer's head"):  # a wider yaw turns the corners out
        make_scene(TASK, block_y_range=(0.041, 0.2), max_yaw=0.78)
    make_scene(TASK, block_y_range=(0.041, 0.2), max_yaw=0.0)  # unturned, 4 cm from the plane fits
    with pytest.raises(ValueError, match="max_yaw"):
        make_scene(TASK, max_yaw=2.0)
    with pytest.raises(ValueError, match="reach below the handle"):
        make_scene(TASK, head_half=(0.02, 0.016, 0.01))
    with pytest.raises(ValueError, match="foot_radius"):
        make_scene(TASK, foot_radius=0.03)
    with pytest.raises(ValueError, match="head_mass must be positive"):
        make_scene(TASK, head_mass=0.0)
    with pytest.raises(ValueError, match="touch_tol"):
        make_scene(TASK, touch_tol=-0.001)
    with pytest.raises(ValueError, match="not a valid"):
        make_scene(TASK, max_yaw="wide")
    with pytest.raises(ValueError, match="unknown option"):
        make_scene(TASK, episode_length=3)  # an env option, not a scene one
    with pytest.raises(ValueError, match="grasp_from_head"):
        make_expert(env, config=HammerExpertConfig(grasp_from_head=0.02))  # pads on the head
    with pytest.raises(ValueError, match="durations"):
        HammerExpertConfig(durations=(10, 10))
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env(TASK, action="ee", obs=("qpos",)))
    assert {"obs", "action", "episode_length", "side", "block_x_range", "max_yaw"} <= set(task_options(TASK))
    assert env.config.episode_length == 400  # the task's step limit
    assert env.config.obs == ("qpos", "point_cloud") and env.config.n_points == 64
    assert env.scene == BeatBlockHammer(side="both")
    assert make_scene(TASK, side="left", max_yaw="0.3").max_yaw == 0.3  # strings are parsed


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    scene = env.scene
    # friction grasp only: no equality constraints (welds), no mocap bodies
    assert m.neq == 0 and m.nmocap == 0
    assert m.jnt_type[m.joint("hammer").id] == mujoco.mjtJoint.mjJNT_FREE
    assert abs(m.body_mass[m.body("hammer").id] - 0.095) < 1e-9
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    # the hammer is its own mirror image; the block's joints mirror as x, y (polar) and yaw
    # (axial about z): x keeps its sign, y and yaw flip
    assert env.sym.bodies[m.body("hammer").id] == m.body("hammer").id
    for name, sign in (("block_x", 1.0), ("block_y", -1.0), ("block_yaw", -1.0)):
        j = m.joint(name).id
        assert env.sym.joints[j] == j and env.sym.joint_signs[j] == sign
    # Few contact pairs: the handle touches only the grippers, the head the table and the
    # block, the foot the table, the block only the head.
    geom = lambda n: m.geom(n).id
    gripper = {geom(f"{s}_{g}") for s in ("left", "right") for g in ("pad_a", "pad_b", "palm")}
    partners = lambda g: {h for h in range(m.ngeom) if m.geom_bodyid[h] != m.geom_bodyid[g] and collides(m, g, h)}
    assert partners(geom("hammer_handle")) == gripper
    assert partners(geom("hammer_head")) == {geom("table"), geom("block")}
    assert partners(geom("hammer_foot")) == {geom("table")}
    assert partners(geom("block")) == {geom("hammer_head")}
    assert m.geom_contype[geom("hammer_head")] == HEAD_BIT
    # primitives MJX collides: no cylinders
    assert not np.any(m.geom_type == mujoco.mjtGeom.mjGEOM_CYLINDER)
    # The hammer rests level on its head and foot: 1 s of host physics from its start pose
    # moves it by well under a millimetre and tilts it by well under a degree.
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(scene.init(jax.random.key(3), env)[0])
    mujoco.mj_forward(m, d)
    a = scene._ids(env)["hammer_qadr"]
    p0 = d.qpos[a : a + 3].copy()
    for _ in range(int(1.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    assert np.abs(d.qpos[a : a + 3] - p0).max() < 5e-4
    assert 2 * np.degrees(np.arccos(min(1.0, abs(d.qpos[a + 3])))) < 1.0
    np.testing.assert_allclose(p0, (scene.hammer_x, 0.0, scene.rest_height), atol=1e-9)


def test_initial_distribution(env):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    blk = np.asarray(jax.vmap(lambda q: scene.block_from_qpos(q, env))(qpos))
    side = np.asarray(info["side"])
    assert 0.45 < (side > 0).mean() < 0.55
    np.testing.assert_array_equal(np.sign(blk[:, 1]), side)
    x, y, yaw = blk.T
    assert np.all((x >= scene.block_x_range[0]) & (x <= scene.block_x_range[1]))
    assert np.all((np.abs(y) >= scene.block_y_range[0]) & (np.abs(y) <= scene.block_y_range[1]))
    assert np.all(np.abs(yaw) <= scene.max_yaw) and np.abs(yaw).max() > 0.9 * scene.max_yaw
    # the block's footprint is clear of the hammer's head (|y| <= head_half[1]) at any yaw
    bx, by, _ = scene.block_half
    reach = bx * np.abs(np.sin(yaw)) + by * np.abs(np.cos(yaw))
    assert np.all(np.abs(y) - reach > scene.head_half[1])
    # the hammer always starts at its rest pose, on the mirror plane; the arms at home
    a = scene._ids(env)["hammer_qadr"]
    np.testing.assert_array_equal(np.asarray(qpos)[:, a : a + 7],
                                  np.broadcast_to(env.home_qpos[a : a + 7], (len(keys), 7)))
    np.testing.assert_allclose(env.home_qpos[a : a + 7], [scene.hammer_x, 0, scene.rest_height, 1, 0, 0, 0])
    np.testing.assert_allclose(np.asarray(qpos)[:, : env.info.nq_robot],
                               np.broadcast_to(env.home_qpos[: env.info.nq_robot], (len(keys), env.info.nq_robot)))
    # The law is mirror-symmetric, exactly: from the same key, side="right" draws the mirror
    # image of what side="left" draws (y and yaw flip), and side="both" picks either with
    # probability 1/2.
    draw = lambda side_opt: np.asarray(jax.vmap(lambda q: scene.block_from_qpos(q, env))(jax.jit(jax.vmap(
        lambda k: dataclasses.replace(scene, side=side_opt).init(k, env)[0]))(keys[:256])))
    np.testing.assert_array_equal(draw("right"), draw("left") * np.array([1.0, -1.0, -1.0]))
    # the point-cloud crop holds the block and the hammer wherever they start
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    r = np.hypot(bx, by)
    assert np.all(x - r >= lo[0]) and np.all(x + r <= hi[0]) and np.all(np.abs(y) + r <= hi[1])
    assert scene.hammer_x - scene.handle_half[0] >= lo[0]
    assert scene.hammer_x + scene.head_local[0] + scene.head_half[0] <= hi[0]
    for side_opt, sgn in (("left", 1.0), ("right", -1.0)):
        e = make_env(TASK, side=side_opt, obs=("qpos",))
        _, inf = jax.vmap(lambda k: e.scene.init(k, e))(keys[:16])
        assert np.all(np.asarray(inf["side"]) == sgn)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_mirror_of_a_start_is_a_start(env, rollouts):
    """``env.mirror_state`` of sampled starts: block reflected (yaw negated), hammer in
    place, side flipped, arms at home, the distribution's constraints still met, and the
    point cloud reflected."""
    s0, _, _ = rollouts
    scene, n = env.scene, N_SEEDS
    blk = np.asarray(jax.vmap(lambda q: scene.block_from_qpos(q, env))(s0.data.qpos))
    side = np.asarray(s0.info["side"])
    np.testing.assert_allclose(blk[n:], blk[:n] * np.array([1.0, -1.0, -1.0]), atol=1e-6)
    np.testing.assert_array_equal(side[n:], -side[:n])
    np.testing.assert_array_equal(np.sign(blk[:, 1]), side)
    assert np.all((np.abs(blk[:, 1]) >= scene.block_y_range[0]) & (np.abs(blk[:, 1]) <= scene.block_y_range[1]))
    assert np.all(np.abs(blk[:, 2]) <= scene.max_yaw)
    a = scene._ids(env)["hammer_qadr"]
    hq = np.asarray(s0.data.qpos)[:, a : a + 7]
    np.testing.assert_allclose(hq[:, :3], np.broadcast_to(env.home_qpos[a : a + 3], (2 * n, 3)), atol=1e-6)
    # the same orientation: the mirror may return the identity quaternion as -(1, 0, 0, 0)
    np.testing.assert_allclose(np.abs(hq[:, 3:] @ env.home_qpos[a + 3 : a + 7]), 1.0, atol=1e-6)
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
    assert not np.any(np.asarray(s0.metrics["touching"]))
    assert traj["action"].shape[::2] == (b, 14) and traj["success"].shape == traj["action"].shape[:2]
    assert np.all(np.isfinite(traj["action"])) and np.all(np.isfinite(traj["qpos"]))
    assert np.all(np.asarray(final.info["step"]) == traj["action"].shape[1])
    assert not np.any(np.asarray(final.metrics["nan_action"]))


# ---------------------------------------------------------------------------- predicate
def _evaluate(env, qpos):
    """(success, terms) of a state built by hand on the host (no stepping)."""
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(qpos)
    mujoco.mj_forward(m, d)
    _, success, metrics = env.scene.evaluate(mjx.put_data(m, d), {}, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def _struck_qpos(env, dx=0.0, dy=0.0, dz=-0.0005, side=1.0, yaw=0.3):
    """qpos with the block at (0.32, side 0.12) and the hammer held level with its
    striking face's centre at (dx, dy, dz) from the block's top centre (dz < 0: pressed in)."""
    scene = env.scene
    block = (0.32, side * 0.12)
    top = env.info.table_height + 2 * scene.block_half[2]
    fx, _, fz = scene.face_local
    hammer = (block[0] + dx - fx, block[1] + dy, top + dz - fz)
    return np.asarray(scene.placed_qpos(jnp.asarray(env.home_qpos), env, block[0], block[1], side * yaw,
                                        hammer_xyz=hammer))


def test_success_predicate_cases(env):
    ok, t = _evaluate(env, _struck_qpos(env))  # face pressed 0.5 mm into the block's top centre
    assert ok and t["touching"] and t["head_block_dist"] < 0 and t["face_block_xy"] < 1e-6
    assert _evaluate(env, _struck_qpos(env, side=-1.0))[0]
    assert _evaluate(env, _struck_qpos(env, dx=0.012, dy=-0.012))[0]  # 1.7 cm off: inside 2 cm
    ok, t = _evaluate(env, _struck_qpos(env, dx=0.025))
    assert not ok and t["touching"] and abs(t["face_block_xy"] - 0.025) < 1e-5  # touching, 2.5 cm off
    ok, t = _evaluate(env, _struck_qpos(env, dz=0.002))
    assert not ok and not t["touching"] and t["on_target"]  # held 2 mm above the block: no touch
    ok, t = _evaluate(env, _struck_qpos(env, dx=0.05))  # beside the block: the face hits nothing
    assert not ok and not t["touching"]
    q0, _ = env.scene.init(jax.random.key(5), env)  # the start: hammer at rest, far from the block
    ok, t = _evaluate(env, q0)
    assert not ok and not t["touching"] and t["face_block_xy"] > 0.03
    # touch_tol widens what counts as touching. MJX lists every candidate pair with its
    # distance (host MuJoCo only those within the margin), so the state above with the
    # head-block distances set to +2 mm stands for the head held 2 mm above the block.
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = _struck_qpos(env)
    mujoco.mj_forward(m, d)
    dx = mjx.put_data(m, d)
    c = dx._impl.contact
    ids = env.scene._ids(env)
    pair = np.isin(np.asarray(c.geom), [ids["head_geom"], ids["block_geom"]]).all(axis=1)
    assert pair.sum() >= 1
    c = c.replace(dist=jnp.where(jnp.asarray(pair), 0.002, c.dist))
    dx = dx.replace(_impl=dx._impl.replace(contact=c))
    assert float(env.scene.head_block_distance(dx, env)) == pytest.approx(0.002)
    wide = dataclasses.replace(env.scene, touch_tol=0.005)
    assert bool(wide.evaluate(dx, {}, env)[1]) and not bool(env.scene.evaluate(dx, {}, env)[1])


# ---------------------------------------------------------------------------- expert
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_success_both_sides(env, rollouts):
    s0, final, traj = rollouts
    success, side = np.asarray(final.info["success"]), np.asarray(s0.info["side"])
    assert set(side.tolist()) == {-1.0, 1.0}
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    print(f"\nexpert success {success.sum()}/{success.size}, sides {side}, first success step {first}")
    assert success.sum() >= success.size - 1
    ids = env.scene._ids(env)
    a = ids["hammer_qadr"]
    # the grasp held by friction: the hammer rose by about the carry height
    lift = traj["qpos"][:, :, a + 2].max(axis=1) - np.asarray(s0.data.qpos)[:, a + 2]
    assert np.all(lift > 0.06), lift
    # the block was struck, not shoved away: it moved by less than a centimetre
    q_end, q0 = traj["qpos"][:, -1], np.asarray(s0.data.qpos)
    moved = np.hypot(q_end[:, ids["x_qadr"]] - q0[:, ids["x_qadr"]], q_end[:, ids["y_qadr"]] - q0[:, ids["y_qadr"]])
    print(f"block moved by at most {moved.max() * 1000:.1f} mm")
    assert np.all(moved < 0.01), moved


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(env, rollouts):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored hammer trajectory."""
    _, _, traj = rollouts
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    a = env.scene._ids(env)["hammer_qadr"]
    ham, ham_m = traj["qpos"][:n, :, a : a + 3], traj["qpos"][n:, :, a : a + 3]
    ham_err = np.abs(ham_m - ham * REFLECT).max()
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; "
          f"max hammer position error = {ham_err * 1000:.3f} mm over {acts.shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the other arm acted: the check is not vacuous
    assert act_err < 1e-3
    assert ham_err < 5e-3
