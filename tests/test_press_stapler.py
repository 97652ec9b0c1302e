"""press_stapler: task registry and options, the sprung hinged plate and its mirror
symmetry, initial distribution, success predicate, scripted expert (success on both sides
and mirror equivariance).

The slow expert tests share one compiled rollout program per module, the task's
``task_rollouts.expert_episodes``: the expert from 50 seeded starts and from the mirror
images of the first 25 (so both sides are always covered), run 10 steps past the end of
its script. The same episodes serve the generic expert check (success rate, shapes, ``S`` on
the recorded demos) and this file's task-specific checks.
"""

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts import make_expert
from equibim_jax.experts.press_stapler import StaplerExpertConfig
from equibim_jax.sim import robots
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.press_stapler import PressStapler

from task_rollouts import N_PAIRS, expert_fixtures

N_SEEDS = N_PAIRS  # starts kept whole in the shared expert episodes, each with its mirror image
MIRROR_POSE = np.array([1.0, -1.0, -1.0])  # (x, y, yaw) under the mirror


@pytest.fixture(scope="module")
def env():
    return make_env("press_stapler", side="both", obs=("qpos", "ee"))


episodes, test_expert_generic_checks = expert_fixtures("press_stapler")


@pytest.fixture(scope="module")
def rollouts(episodes):
    """(initial states [2N], final states [2N], traj) for N starts then their N mirror images."""
    return episodes.s0, episodes.final, episodes.traj


def _valid_start(env, qpos, side):
    """Whether each qpos [B, nq] (with side [B]) lies in the support of the initial
    distribution: stapler inside the ranges on its side, yaw in range, plate open, arms
    at home."""
    scene = env.scene
    pose = np.asarray(jax.vmap(lambda q: scene.pose_from_qpos(q, env))(qpos))
    angle = np.asarray(jax.vmap(lambda q: scene.hinge_angle(q, env))(qpos))
    q = np.asarray(qpos)
    (xlo, xhi), (ylo, yhi) = scene.stapler_x_range, scene.stapler_y_range
    nq = env.info.nq_robot
    side_ok = (np.sign(pose[:, 1]) == np.asarray(side)) | (pose[:, 1] == 0)
    return ((pose[:, 0] >= xlo - 1e-6) & (pose[:, 0] <= xhi + 1e-6)
            & (np.abs(pose[:, 1]) >= ylo - 1e-6) & (np.abs(pose[:, 1]) <= yhi + 1e-6) & side_ok
            & (np.abs(pose[:, 2]) <= scene.max_yaw + 1e-6)
            & (np.abs(angle - scene.open_angle) < 1e-6)
            & np.all(np.abs(q[:, :nq] - env.home_qpos[:nq]) < 1e-5, axis=1))


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors(env):
    assert "press_stapler" in task_names()
    entry = task_entry("press_stapler")
    assert entry.expert is not None and entry.step_limit == 400 and entry.robot == "robot_a"
    assert {"side", "stapler_x_range", "max_yaw", "closed_angle"} <= set(task_options("press_stapler"))
    with pytest.raises(ValueError, match="valid tasks: .*press_stapler"):
        make_env("press_staple")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['yaw'\].*valid options: .*max_yaw"):
        make_env("press_stapler", yaw=0.3)
    with pytest.raises(ValueError, match="side must be one of"):
        make_scene("press_stapler", side="centre")
    with pytest.raises(ValueError, match="stapler_x_range must be"):
        make_scene("press_stapler", stapler_x_range=(0.3, 0.2))
    with pytest.raises(ValueError, match=r"\|y\| values"):
        make_scene("press_stapler", stapler_y_range=(-0.2, 0.2))
    with pytest.raises(ValueError, match="max_yaw must be in"):
        make_scene("press_stapler", max_yaw=4.0)
    with pytest.raises(ValueError, match="closed_angle .* < open_angle"):
        make_scene("press_stapler", closed_angle=0.4)
    with pytest.raises(ValueError, match="press_offset .* must lie on the plate"):
        make_scene("press_stapler", press_offset=0.2)
    with pytest.raises(ValueError, match="not a valid"):
        make_scene("press_stapler", max_yaw="half")
    assert make_scene("press_stapler", max_yaw="1.5", stapler_y_range="0.05,0.15") == PressStapler(
        max_yaw=1.5, stapler_y_range=(0.05, 0.15))
    assert env.config.episode_length == 400  # the task's step limit
    assert env.scene == PressStapler(side="both")
    assert env.task == "press_stapler" and env.task_options["max_yaw"] == math.pi
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env("press_stapler", action="ee", obs=("qpos",)))


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    assert m.neq == 0 and m.nmocap == 0  # no welds, no teleporting
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    sym = env.sym
    for name, sign in (("stapler_x", 1.0), ("stapler_y", -1.0), ("stapler_yaw", -1.0),
                       ("stapler_hinge", 1.0)):
        j = m.joint(name).id
        assert sym.joints[j] == j and sym.joint_signs[j] == sign, name
    # the plate is on a real sprung hinge with stops, its spring holding it open
    scene = env.scene
    j = m.joint("stapler_hinge").id
    assert m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and m.jnt_limited[j]
    np.testing.assert_allclose(m.jnt_range[j], [0.0, scene.open_angle], atol=1e-7)
    assert m.jnt_stiffness[j] == scene.spring_stiffness
    assert m.qpos_spring[m.jnt_qposadr[j]] > scene.open_angle
    # only the plate collides, and only with the finger pads
    geoms = [g for g in range(m.ngeom)
             if m.body(m.geom_bodyid[g]).name in ("stapler", "stapler_plate")]
    colliding = [m.geom(g).name for g in geoms if m.geom_contype[g] or m.geom_conaffinity[g]]
    assert colliding == ["stapler_plate"]
    g = m.geom("stapler_plate").id
    assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == robots.PAD_BIT


def test_spring_holds_the_plate_open_and_reopens_it():
    """Passive physics on the host (MuJoCo C, same model): the plate rests at its open stop,
    and released shut, the spring opens it again."""
    env = make_env("press_stapler", obs=("qpos",))
    m = env.mj_model
    d = mujoco.MjData(m)
    q0, _ = env.scene.init(jax.random.key(0), env)
    adr = env.scene._ids(env)["hinge_qadr"]
    for start in (env.scene.open_angle, 0.0):
        d.qpos[:] = np.asarray(q0)
        d.qpos[adr] = start
        d.qvel[:] = 0
        d.ctrl[:] = env.home_ctrl
        for _ in range(250):  # 1 s
            mujoco.mj_step(m, d)
        assert abs(d.qpos[adr] - env.scene.open_angle) < 5e-3, (start, d.qpos[adr])


# ---------------------------------------------------------------------------- distribution
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_initial_distribution_is_mirror_symmetric(env, rollouts):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    side = np.asarray(info["side"])
    assert 0.4 < (side > 0).mean() < 0.6
    assert np.all(_valid_start(env, qpos, side))
    qpos_m = jax.vmap(env.sym.qpos)(qpos)
    assert np.all(_valid_start(env, qpos_m, -side))
    pose = np.asarray(jax.vmap(lambda q: scene.pose_from_qpos(q, env))(qpos))
    pose_m = np.asarray(jax.vmap(lambda q: scene.pose_from_qpos(q, env))(qpos_m))
    np.testing.assert_allclose(pose_m, pose * MIRROR_POSE, atol=1e-6)
    # the two sides' distributions are mirror images: quantiles of x, |y| and of the yaw
    # on one side against the mirrored yaw on the other
    qs = np.linspace(0.05, 0.95, 7)
    for col, sgn in ((0, 1.0), (1, 1.0), (2, -1.0)):
        a = pose[side > 0, col] * (np.sign(pose[side > 0, 1]) if col == 1 else 1.0)
        b = pose[side < 0, col] * (np.sign(pose[side < 0, 1]) if col == 1 else sgn)
        tol = 0.02 if col < 2 else 0.5
        np.testing.assert_allclose(np.quantile(a, qs), np.quantile(b, qs), atol=tol)
    s0, _, _ = rollouts
    n = N_SEEDS
    side0 = np.asarray(s0.info["side"])
    np.testing.assert_array_equal(side0[n:], -side0[:n])
    assert np.all(_valid_start(env, s0.data.qpos, side0))
    # the point-cloud crop holds every stapler the distribution can place (any yaw)
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    reach = math.hypot(scene.base_half[0], scene.base_half[1])
    assert np.all(pose[:, :2] - reach >= lo[:2]) and np.all(pose[:, :2] + reach <= hi[:2])
    for side_opt, sgn in (("left", 1.0), ("right", -1.0)):
        e = make_env("press_stapler", side=side_opt, obs=("qpos",))
        _, inf = jax.vmap(lambda k: e.scene.init(k, e))(keys[:16])
        assert np.all(np.asarray(inf["side"]) == sgn)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_reset_and_step_shapes_no_nan_success_false_at_reset(env, rollouts):
    s0, final, traj = rollouts
    b = 2 * N_SEEDS
    assert s0.obs["qpos"].shape == (b, 14) and s0.obs["ee"].shape == (b, 2 * (3 + 6 + 1))
    assert final.obs["qpos"].shape == (b, 14) and final.reward.shape == (b,)
    assert traj["action"].shape[::2] == (b, env.action_size)
    assert traj["qpos"].shape == (*traj["action"].shape[:2], env.mj_model.nq)
    for tree in (s0, final):
        for leaf in jax.tree.leaves((tree.obs, tree.metrics, tree.data.qpos, tree.data.qvel)):
            assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.all(np.isfinite(traj["qpos"])) and np.all(np.isfinite(traj["action"]))
    assert not np.any(np.asarray(s0.info["success"]))
    assert not np.any(np.asarray(s0.metrics["shut"]))
    assert np.all(np.asarray(final.info["step"]) == traj["action"].shape[1])
    assert np.all(np.asarray(final.metrics["nan_action"]) == 0)


# ---------------------------------------------------------------------------- predicate
def _evaluate(env, qpos):
    """(success, terms) of a state built by hand on the host (no stepping)."""
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(qpos)
    mujoco.mj_forward(m, d)
    _, success, metrics = env.scene.evaluate(mjx.put_data(m, d), {}, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def test_success_predicate_cases(env):
    scene = env.scene
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = env.home_qpos
    mujoco.mj_forward(m, d)
    ee = d.site_xpos[env.ee_site]  # [2, 3] home ee positions
    q0, _ = scene.init(jax.random.key(1), env)
    hinge = scene.hinge_pos[0]
    for side in (0, 1):
        for yaw in (0.0, 2.0, -2.5):
            # the stapler placed so that its shut press point lies under the ee site (+ dx)
            def at(angle, dx=0.0, yaw=yaw):
                off = (hinge + scene.press_offset) * np.array([np.cos(yaw), np.sin(yaw)])
                xy = ee[side, :2] - off + [dx, 0.0]
                return scene.placed_qpos(q0, env, xy[0], xy[1], yaw, angle)
            ok, t = _evaluate(env, at(0.0))
            assert ok and t["ee_press_xy"] < 1e-5, t
            assert _evaluate(env, at(scene.closed_angle - 0.01))[0]
            ok, t = _evaluate(env, at(scene.closed_angle + 0.01))
            assert not ok and abs(t["hinge_angle"] - scene.closed_angle - 0.01) < 1e-6  # not shut
            assert not _evaluate(env, at(scene.open_angle))[0]
            ok, t = _evaluate(env, at(0.0, dx=0.035))  # shut, but no gripper near the press point
            assert not ok and abs(t["ee_press_xy"] - 0.035) < 1e-4


# ---------------------------------------------------------------------------- expert
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_presses_the_plate_shut_on_both_sides(env, rollouts):
    s0, final, traj = rollouts
    side = np.asarray(s0.info["side"])
    assert set(side.tolist()) == {-1.0, 1.0}
    success = np.asarray(final.info["success"])
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    ids = env.scene._ids(env)
    angle = traj["qpos"][:, :, ids["hinge_qadr"]]
    pose0 = np.asarray(jax.vmap(lambda q: env.scene.pose_from_qpos(q, env))(s0.data.qpos))
    pose = traj["qpos"][:, :, [ids["x_qadr"], ids["y_qadr"], ids["yaw_qadr"]]]
    drift = np.abs(pose - pose0[:, None]).max(axis=1)  # [B, 3]
    print(f"\nexpert success {success.sum()}/{success.size}, sides {side}, yaw "
          f"{np.round(pose0[:, 2], 2)}, first success step {first}, min hinge angle "
          f"{np.round(angle.min(axis=1), 3)}, stapler drift (mm, mm, rad) {np.round(drift * [1e3, 1e3, 1], 2)}")
    assert success.all()
    # the plate physically closed past the threshold, then the spring reopened it
    assert np.all(angle.min(axis=1) < env.scene.closed_angle)
    assert np.all(np.abs(angle[:, -1] - env.scene.open_angle) < 0.02)
    # the stapler was pressed, not shoved: its base moved little
    assert np.all(drift[:, :2] < 0.01) and np.all(drift[:, 2] < 0.1)
    acts = traj["action"].reshape(2 * N_SEEDS, traj["action"].shape[1], 2, -1)
    moved = np.abs(acts[..., :-1] - acts[:, :1, :, :-1]).max(axis=(1, 3))  # [B, 2]
    active = np.where(side > 0, 0, 1)
    assert np.all(moved[np.arange(len(side)), active] > 0.1)
    assert np.all(moved[np.arange(len(side)), 1 - active] < 1e-3)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(env, rollouts):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored stapler motion."""
    _, _, traj = rollouts
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    ids = env.scene._ids(env)
    pose = traj["qpos"][:, :, [ids["x_qadr"], ids["y_qadr"], ids["yaw_qadr"]]]
    pose_err = np.abs(pose[n:] - pose[:n] * MIRROR_POSE).max(axis=(0, 1))
    angle = traj["qpos"][:, :, ids["hinge_qadr"]]
    angle_err = np.abs(angle[n:] - angle[:n]).max(axis=0)  # [T]
    # Until the retreat begins the hinge is either at rest or pushed slowly by the pads.
    # During the retreat the spring snaps the plate open at up to ~0.05 rad per control
    # step, so the two simulations' float32 contact round-off shows up as a small timing
    # difference; the tolerance there is 0.02 rad (2 mm at the press point). Before the
    # retreat the median pair must agree to 1e-4 rad (an asymmetry in the model or the
    # expert would shift every pair); over N pairs the round-off of the pads sliding on
    # the plate grows in a few, so the worst pair is held to 2e-3 rad (0.2 mm).
    t_retreat = sum(StaplerExpertConfig().durations[:-1])
    err_press, err_all = angle_err[:t_retreat].max(), angle_err.max()
    per_pair = np.abs(angle[n:] - angle[:n])[:, :t_retreat].max(axis=1)  # [N]
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; stapler (x, y, yaw) error "
          f"{pose_err}; hinge angle error {err_press:.2e} rad before the retreat (median pair "
          f"{np.median(per_pair):.2e}), {err_all:.2e} "
          f"rad over all {traj['action'].shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the other arm acted: the check is not vacuous
    assert act_err < 1e-3
    assert np.all(pose_err < 1e-3)
    assert np.median(per_pair) < 1e-4 and err_press < 2e-3 and err_all < 0.02
