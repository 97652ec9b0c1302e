"""drumstick_hook: task registry and option errors, model (physical, mirror-symmetric, few
contact pairs), initial distribution and the shift options, the success predicate on
hand-built states, the rack holding a stick in MuJoCo C, and (slow) the scripted expert
on both sides, its mirror equivariance, and its perturbed (``asymmetric_quality``) runs.

The slow tests share one compiled rollout program, the task's
``task_rollouts.expert_episodes`` (50 seeded starts and the mirror images of 25, for the
generic expert check), which also runs 4 seeded starts, their 4 mirror images, and 12
right-side starts as ``side="right", asymmetric_quality=1.0`` draws them (every one
perturbed; the model is the same, only the start's info differs).
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
from equibim_jax.experts.drumstick_hook import DrumstickExpertConfig, hang_rotation
from equibim_jax.sim.robots import robot_info
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.drumstick_hook import DrumstickHook

from task_rollouts import collides, expert_fixtures, run_starts

TASK = "drumstick_hook"
CFG = DrumstickExpertConfig()
REFLECT = np.array([1.0, -1.0, 1.0])
N_SEEDS = 4
N_PERTURBED = 12


@pytest.fixture(scope="module")
def env():
    return make_env(TASK)


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors(env):
    assert TASK in task_names()
    entry = task_entry(TASK)
    assert entry.robot == "robot_b" and entry.step_limit == 600 and entry.expert is not None
    assert env.config.obs == ("qpos", "point_cloud") and env.config.n_points == 64
    assert env.config.action == "joint" and env.config.episode_length == 600
    assert env.scene == DrumstickHook() and env.scene.main_object == "drumstick"
    assert {"side", "mirrored_orientation", "wide_init", "asymmetric_quality", "asymmetric_side",
            "stick_x_range", "hook_x"} <= set(task_options(TASK))
    with pytest.raises(ValueError, match="robot"):
        make_env(TASK, robot="robot_a")
    with pytest.raises(ValueError, match="built for robot_b"):
        DrumstickHook().build(mujoco.MjSpec(), robot_info("robot_a"))
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['colour'\]"):
        make_env(TASK, colour="red")
    with pytest.raises(ValueError, match="side must be one of"):
        make_scene(TASK, side="middle")
    with pytest.raises(ValueError, match="wide_init"):
        make_scene(TASK, wide_init=0.5)
    with pytest.raises(ValueError, match="asymmetric_quality"):
        make_scene(TASK, asymmetric_quality=1.5)
    with pytest.raises(ValueError, match="never puts the object there"):
        make_scene(TASK, side="left", asymmetric_quality=0.3)
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, stick_x_range=(0.3, 0.2))
    with pytest.raises(ValueError, match="wholly on its side"):
        make_scene(TASK, min_abs_y=0.05, stick_y_range=(0.05, 0.2))
    with pytest.raises(ValueError, match="at or above min_abs_y"):
        make_scene(TASK, stick_y_range=(0.05, 0.2))
    with pytest.raises(ValueError, match="tip_radius"):
        make_scene(TASK, tip_radius=0.012)
    with pytest.raises(ValueError, match="peg_back < 0 < peg_front"):
        make_scene(TASK, peg_back=0.01)
    with pytest.raises(ValueError, match="shaft_mass must be positive"):
        make_scene(TASK, shaft_mass=0.0)
    with pytest.raises(ValueError, match="rest_speed"):
        make_scene(TASK, rest_speed=0.0)
    assert make_scene(TASK, side="right", asymmetric_quality="0.28").asymmetric_quality == 0.28
    # expert options
    with pytest.raises(ValueError, match="durations needs 9"):
        DrumstickExpertConfig(durations=(10,) * 8)
    with pytest.raises(ValueError, match="pitch"):
        DrumstickExpertConfig(pitch=4.0)
    with pytest.raises(ValueError, match="short must be positive"):
        DrumstickExpertConfig(short=0.0)
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env(TASK, action="ee", obs=("qpos",)))


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    scene = env.scene
    assert m.neq == 0 and m.nmocap == 0  # no welds, no teleporting bodies
    assert m.jnt_type[m.joint("drumstick").id] == mujoco.mjtJoint.mjJNT_FREE
    body = m.body("drumstick").id
    assert abs(m.body_mass[body] - 0.05) < 1e-9
    np.testing.assert_allclose(m.body_ipos[body], [scene.com_offset, 0, 0], atol=1e-9)
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    # Few contact pairs: the shaft touches the grippers, the table and the rack's pegs and
    # tips; the bead only the table; the rack only the shaft.
    g = lambda n: m.geom(n).id
    gripper = {g(f"{s}_{k}") for s in ("left", "right") for k in ("fixed_jaw", "moving_jaw", "palm")}
    rack = {g(f"rack_{k}_{s}") for k in ("peg", "tip") for s in ("left", "right")}
    partners = lambda a: {h for h in range(m.ngeom)
                          if m.geom_bodyid[h] != m.geom_bodyid[a] and collides(m, a, h)}
    assert partners(g("drumstick_shaft")) == gripper | rack | {g("table")}
    assert partners(g("drumstick_tip")) == {g("table")}
    for r in rack:
        assert partners(r) == {g("drumstick_shaft")}
    for s in ("left", "right"):
        assert partners(g(f"rack_post_{s}")) == set()
    # the rack is its own mirror image
    for k in ("peg", "tip", "post"):
        a, b = g(f"rack_{k}_left"), g(f"rack_{k}_right")
        np.testing.assert_allclose(m.geom_pos[a] * REFLECT, m.geom_pos[b], atol=1e-12)
        np.testing.assert_allclose(m.geom_size[a], m.geom_size[b])
    # The grasp holds by friction with a margin: the closing jaw pushes kp * its distance
    # to the closed target at the stick's width, far more than the weight needs.
    jaw = m.actuator("left_gripper")
    push = jaw.gainprm[0] * (2 * scene.stick_radius - env.info.gripper_closed_gap)
    mu = max(m.geom_friction[g("drumstick_shaft"), 0], m.geom_friction[g("left_fixed_jaw"), 0])
    assert 2 * mu * float(push) > 5 * m.body_mass[body] * 9.81


# ---------------------------------------------------------------------------- initial law
def _draw(env, scene, keys):
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    return np.asarray(qpos), jax.tree.map(np.asarray, info)


def _stick(env, qpos):
    a = env.scene._ids(env)["qadr"]
    return qpos[:, a : a + 3], qpos[:, a + 3 : a + 7]


def test_initial_distribution_and_shift_options(env):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = _draw(env, scene, keys)
    pos, quat = _stick(env, qpos)
    side = info["side"]
    assert 0.45 < (side > 0).mean() < 0.55 and not info["perturbed"].any()
    assert info["side"].dtype == np.float32 and info["yaw"].dtype == np.float32
    np.testing.assert_array_equal(np.sign(pos[:, 1]), side)
    assert np.all((pos[:, 0] >= scene.stick_x_range[0]) & (pos[:, 0] <= scene.stick_x_range[1]))
    ay = np.abs(pos[:, 1])
    assert np.all((ay >= scene.stick_y_range[0]) & (ay <= scene.stick_y_range[1]))
    np.testing.assert_allclose(pos[:, 2], scene.stick_radius, atol=1e-6)  # resting on the table
    np.testing.assert_allclose(quat[:, 0] * side, np.abs(quat[:, 0]), atol=1e-7)  # sign s
    yaw = 2 * np.arctan2(quat[:, 3] * side, quat[:, 0] * side)
    np.testing.assert_allclose(yaw, info["yaw"], atol=1e-5)
    u = side * yaw
    assert np.all((u >= scene.yaw_range[0] - 1e-6) & (u <= scene.yaw_range[1] + 1e-6))
    # the whole stick lies on its side of the mirror plane
    assert np.all(np.abs(pos[:, 1]) - scene.stick_extent > 0.0)
    nq = env.info.nq_robot
    np.testing.assert_allclose(qpos[:, :nq], np.broadcast_to(env.home_qpos[:nq], (len(qpos), nq)))
    # the point-cloud crop holds every stick the law can place
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    assert np.all(pos[:, :2] - scene.stick_extent >= lo[:2])
    assert np.all(pos[:, :2] + scene.stick_extent <= hi[:2])

    # Exactly mirror-symmetric: from the same key, side="right" draws the mirror image of
    # what side="left" draws.
    k = keys[:256]
    ql, il = _draw(env, dataclasses.replace(scene, side="left"), k)
    qr, ir = _draw(env, dataclasses.replace(scene, side="right"), k)
    mirrored = np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(ql)))
    np.testing.assert_allclose(qr, mirrored, atol=1e-6)
    np.testing.assert_array_equal(ir["side"], -il["side"])
    np.testing.assert_allclose(ir["yaw"], -il["yaw"], atol=1e-7)

    # Each option changes only what it names (same keys).
    a = scene._ids(env)["qadr"]
    q_mo, i_mo = _draw(env, dataclasses.replace(scene, mirrored_orientation=True), k)
    diff = np.flatnonzero(np.any(q_mo != _draw(env, scene, k)[0], axis=0))
    assert set(diff.tolist()) <= set(range(a + 3, a + 7)) and diff.size > 0  # the quaternion only
    q0, i0 = _draw(env, scene, k)
    np.testing.assert_allclose(i_mo["yaw"], -i0["yaw"], atol=1e-7)
    q_aq, i_aq = _draw(env, dataclasses.replace(scene, asymmetric_quality=1.0), k)
    np.testing.assert_array_equal(q_aq, q0)
    np.testing.assert_array_equal(i_aq["perturbed"], i0["side"] < 0)  # every right-side episode
    q_w, _ = _draw(env, dataclasses.replace(scene, wide_init=1.5), keys)
    pw, _ = _stick(env, q_w)
    assert pw[:, 0].min() < scene.stick_x_range[0] - 0.01
    assert pw[:, 0].max() > scene.stick_x_range[1] + 0.01
    assert np.abs(pw[:, 1]).min() >= scene.min_abs_y - 1e-6


def test_asymmetric_quality_perturbs_a_fraction_of_one_side(env):
    """The paper's shift for this task: ``asymmetric_quality`` of the right side's episodes
    carry ``info["perturbed"]`` (about 7 of 25 at 0.28), none on the left."""
    scene = make_scene(TASK, asymmetric_quality=0.28)
    _, info = _draw(env, scene, jax.random.split(jax.random.key(3), 4000))
    right = info["side"] < 0
    assert not info["perturbed"][~right].any()
    assert abs(info["perturbed"][right].mean() - 0.28) < 0.03


# ---------------------------------------------------------------------------- predicate
def _hang_qpos(env, side=1.0, dz=-0.0002, dx=0.0):
    """qpos with the stick lying across the pegs as the expert hangs it (``dz`` above its
    resting height, ``dx`` back along the arm's plane), arms at home."""
    scene = env.scene
    base = np.array([0.0, 0.2])
    p = np.array([scene.hook_x, 0.0]) - base
    p = np.r_[p / np.linalg.norm(p), 0.0]
    rot = np.asarray(hang_rotation(jnp.asarray(p, jnp.float32), CFG.pitch))
    axis = rot[:, 2]  # the stick lies along the gripper's z axis
    com = np.array([scene.hook_x, 0.0, env.info.table_height + scene.hang_height + dz]) - dx * p
    origin = com - scene.com_offset * axis
    yaw = math.atan2(axis[1], axis[0])
    origin, yaw = origin * (REFLECT if side < 0 else 1.0), yaw * side
    quat = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    return np.asarray(scene.placed_qpos(jnp.asarray(env.home_qpos), env, origin, quat))


def _host(env, qpos, qvel=None):
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    if qvel is not None:
        d.qvel[:] = qvel
    d.ctrl[:] = env.home_ctrl
    mujoco.mj_forward(m, d)
    return d


def _evaluate(env, d, relabel=None):
    """(success, terms) of a host state; ``relabel`` turns its shaft-rack contacts into
    shaft-``relabel`` contacts (a stand-in for that geom touching the stick)."""
    dx = mjx.put_data(env.mj_model, d)
    if relabel is not None:
        ids = env.scene._ids(env)
        c = dx._impl.contact
        geom = np.asarray(c.geom)
        is_rack = np.isin(geom, ids["rack"])
        assert is_rack.any()
        geom = np.where(is_rack, env.mj_model.geom(relabel).id, geom)
        dx = dx.replace(_impl=dx._impl.replace(contact=c.replace(geom=jnp.asarray(geom))))
    _, success, metrics = env.scene.evaluate(dx, {}, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def test_success_predicate_cases(env):
    for side in (1.0, -1.0):
        ok, t = _evaluate(env, _host(env, _hang_qpos(env, side)))
        assert ok and t["on_rack"] and t["rack_dist"] < 0 and t["off_table"] and t["released"], t
        assert abs(t["stick_height"] - env.scene.hang_height) < 1e-3
    ok, t = _evaluate(env, _host(env, _hang_qpos(env, dz=0.003)))  # held 3 mm above the pegs
    assert not ok and not t["on_rack"] and t["raised"]
    on_table = -env.scene.hang_height + env.scene.stick_radius - 2e-4
    ok, t = _evaluate(env, _host(env, _hang_qpos(env, dx=0.16, dz=on_table)))
    assert not ok and not t["on_rack"] and not t["off_table"] and not t["raised"]  # on the table
    ok, t = _evaluate(env, _host(env, _hang_qpos(env)), relabel="left_fixed_jaw")  # a jaw touches it
    assert not ok and not t["released"] and t["gripper_dist"] < 0
    ok, t = _evaluate(env, _host(env, _hang_qpos(env)), relabel="table")  # touching the table
    assert not ok and not t["off_table"]
    q = _hang_qpos(env)
    qvel = np.zeros(env.mj_model.nv)
    dof = env.scene._ids(env)["dofadr"]
    qvel[dof + 2] = -0.2  # grazing the rack while falling
    ok, t = _evaluate(env, _host(env, q, qvel))
    assert not ok and t["on_rack"] and not t["at_rest"]
    q0, _ = env.scene.init(jax.random.key(5), env)  # a start: on the table, far from the rack
    ok, t = _evaluate(env, _host(env, np.asarray(q0)))
    assert not ok and not t["off_table"] and t["rack_dist"] == 1.0


def test_rack_holds_a_stick_by_gravity_and_friction(env):
    """MuJoCo C: a stick dropped from 3 mm onto the pegs stays there (and its mirror image
    too); one dropped from ``short`` back along the arm's plane falls to the table."""
    m = env.mj_model
    body = env.scene._ids(env)["body"]
    for side in (1.0, -1.0):
        d = _host(env, _hang_qpos(env, side, dz=0.003))
        start = d.xipos[body].copy()
        for _ in range(int(1.5 / m.opt.timestep)):
            mujoco.mj_step(m, d)
        assert np.linalg.norm(d.xipos[body] - start) < 0.006, d.xipos[body] - start
        assert _evaluate(env, d)[0]
    d = _host(env, _hang_qpos(env, dz=0.003, dx=CFG.short))
    for _ in range(int(1.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    ok, t = _evaluate(env, d)
    assert not ok and not t["off_table"] and t["stick_height"] < 0.02


# ---------------------------------------------------------------------------- expert (slow)
episodes, test_expert_generic_checks = expert_fixtures(TASK)


@pytest.fixture(scope="module")
def rollouts(episodes):
    """(env, initial states, final states, traj): N seeds, their N mirror images, then
    N_PERTURBED right-side starts as ``side="right", asymmetric_quality=1.0`` draws them
    (every one perturbed), run through the shared episodes' compiled program. A right-side
    start is the default draw or its mirror image (``env.mirror_state`` in the program),
    whichever lies on the right, with its flag set."""
    env = episodes.env
    pert = make_scene(TASK, side="right", asymmetric_quality=1.0)
    keys = jax.random.split(jax.random.key(21), N_SEEDS + N_PERTURBED)
    q, info = episodes.draw(keys)
    n = N_SEEDS
    take = lambda t, *idx: jax.tree.map(lambda a: jnp.concatenate([a[i] for i in idx]), t)
    qpos, info = take((q, info), slice(None, n), slice(None, n), slice(n, None))
    info = {**info, "perturbed": info["perturbed"].at[2 * n :].set(True)}
    mirror = jnp.concatenate([jnp.zeros(n, bool), jnp.ones(n, bool), info["side"][2 * n :] > 0])
    s0, final, traj = run_starts(episodes, qpos, info, mirror)
    # the perturbed starts are what the asymmetric_quality=1.0, side="right" scene draws
    qp, ip = jax.jit(jax.vmap(lambda k: pert.init(k, env)))(keys[N_SEEDS:])
    assert np.all(np.asarray(ip["perturbed"])) and np.all(np.asarray(ip["side"]) == -1.0)
    np.testing.assert_allclose(np.asarray(s0.data.qpos)[2 * N_SEEDS :], np.asarray(qp), atol=1e-6)
    return env, s0, final, traj


@pytest.mark.slow
def test_expert_hangs_the_stick_on_both_sides(rollouts):
    env, s0, final, traj = rollouts
    n = 2 * N_SEEDS
    success, side = np.asarray(final.info["success"])[:n], np.asarray(s0.info["side"])[:n]
    assert set(side.tolist()) == {-1.0, 1.0}
    first = np.where(success, traj["success"][:n].argmax(axis=1), -1)
    print(f"\nexpert success {success.sum()}/{n}, sides {side}, first success step {first}")
    assert success.all()
    # hung, not balanced on the gripper: the stick still rests on the rack at the end with
    # the gripper gone, at the pegs' height
    m = np.asarray(final.metrics["stick_height"])[:n]
    np.testing.assert_allclose(m, env.scene.hang_height, atol=0.01)
    assert np.all(np.asarray(final.metrics["released"])[:n] > 0)
    assert np.all(np.asarray(final.metrics["on_rack"])[:n] > 0)
    # mirrored starts: mirrored actions (the script is open loop) and the same outcome
    a, am = traj["action"][:N_SEEDS], traj["action"][N_SEEDS:n]
    err = np.abs(np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(a))) - am).max()
    print(f"max |a_mirror - S a| = {err:.1e}")
    assert err < 1e-3 and np.abs(a - am).max() > 0.1


@pytest.mark.slow
def test_perturbed_expert_fails(rollouts):
    """``asymmetric_quality=1.0`` on the right: every episode there is perturbed, and the
    expert releases the stick short of the rack, so it falls to the table."""
    env, s0, final, traj = rollouts
    n = 2 * N_SEEDS
    perturbed = np.asarray(s0.info["perturbed"])
    assert np.all(perturbed[n:]) and not np.any(perturbed[:n])
    assert np.all(np.asarray(s0.info["side"])[n:] == -1.0)
    success = np.asarray(final.info["success"])[n:]
    height = np.asarray(final.metrics["stick_height"])[n:]
    print(f"\nperturbed expert success {success.sum()}/{success.size}; final stick heights "
          f"{height.round(3)}")
    assert success.sum() <= 1
    a = env.scene._ids(env)["qadr"]
    assert np.all(traj["qpos"][n:, :, a + 2].max(axis=1) > 0.1)  # it was carried before it fell
