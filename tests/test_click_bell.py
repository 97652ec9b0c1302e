"""click_bell: task registry and options, the sprung-button model and its mirror symmetry,
initial distribution, success predicate, scripted expert (success on both sides and
mirror equivariance).

The slow expert tests share one compiled rollout program per module, the task's
``task_rollouts.expert_episodes``: the expert from 50 seeded starts and from the mirror
images of the first 25 (so both sides are always covered), run 10 steps past the end of
its script. The same episodes serve the generic expert check (success rate, shapes, ``S`` on
the recorded demos) and this file's task-specific checks.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts import make_expert
from equibim_jax.sim import robots
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.click_bell import ClickBell

from task_rollouts import N_PAIRS, expert_fixtures

N_SEEDS = N_PAIRS  # starts kept whole in the shared expert episodes, each with its mirror image
MIRROR_Y = np.array([1.0, -1.0])


@pytest.fixture(scope="module")
def env():
    return make_env("click_bell", side="both", obs=("qpos", "ee"))


episodes, test_expert_generic_checks = expert_fixtures("click_bell")


@pytest.fixture(scope="module")
def rollouts(episodes):
    """(initial states [2N], final states [2N], traj) for N starts then their N mirror images."""
    return episodes.s0, episodes.final, episodes.traj


def _valid_start(env, qpos, side):
    """Whether each qpos [B, nq] (with side [B]) lies in the support of the initial
    distribution: bell inside the ranges on its side, button up, arms at home."""
    scene = env.scene
    xy = np.asarray(jax.vmap(lambda q: scene.bell_xy(q, env))(qpos))
    depth = np.asarray(jax.vmap(lambda q: scene.button_depth(q, env))(qpos))
    q = np.asarray(qpos)
    (xlo, xhi), (ylo, yhi) = scene.bell_x_range, scene.bell_y_range
    nq = env.info.nq_robot
    return ((xy[:, 0] >= xlo - 1e-6) & (xy[:, 0] <= xhi + 1e-6)
            & (np.abs(xy[:, 1]) >= ylo - 1e-6) & (np.abs(xy[:, 1]) <= yhi + 1e-6)
            & (np.sign(xy[:, 1]) == np.asarray(side)) & (np.abs(depth) < 1e-6)
            & np.all(np.abs(q[:, :nq] - env.home_qpos[:nq]) < 1e-5, axis=1))


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors(env):
    assert "click_bell" in task_names()
    entry = task_entry("click_bell")
    assert entry.expert is not None and entry.step_limit == 400 and entry.robot == "robot_a"
    assert {"side", "bell_x_range", "bell_y_range", "press_depth"} <= set(task_options("click_bell"))
    with pytest.raises(ValueError, match="valid tasks: .*click_bell"):
        make_env("click_bells")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['colour'\].*valid options: .*bell_y_range"):
        make_env("click_bell", colour="gold")
    with pytest.raises(ValueError, match="side must be one of"):
        make_scene("click_bell", side="middle")
    with pytest.raises(ValueError, match="bell_x_range must be"):
        make_scene("click_bell", bell_x_range=(0.4, 0.2))
    with pytest.raises(ValueError, match=r"\|y\| values"):
        make_scene("click_bell", bell_y_range=(-0.1, 0.2))
    with pytest.raises(ValueError, match="press_depth .* must be below button_travel"):
        make_scene("click_bell", press_depth=0.02)
    with pytest.raises(ValueError, match="spring_stiffness must be positive"):
        make_scene("click_bell", spring_stiffness=0.0)
    with pytest.raises(ValueError, match="closed_threshold"):
        make_scene("click_bell", closed_threshold=1.5)
    with pytest.raises(ValueError, match="not a valid"):
        make_scene("click_bell", press_depth="deep")
    # strings (from a command line) are parsed into the fields' types
    assert make_scene("click_bell", bell_y_range="0.1,0.2", press_depth="0.005") == ClickBell(
        bell_y_range=(0.1, 0.2), press_depth=0.005)
    assert env.config.episode_length == 400  # the task's step limit
    assert env.scene == ClickBell(side="both")
    assert env.task == "click_bell" and env.task_options["side"] == "both"
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env("click_bell", action="ee", obs=("qpos",)))


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    assert m.neq == 0 and m.nmocap == 0  # no welds, no teleporting
    # derive_symmetry (run by the env) matched the whole model, dynamics included
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    sym = env.sym
    for name, sign in (("bell_x", 1.0), ("bell_y", -1.0), ("bell_button", 1.0)):
        j = m.joint(name).id
        assert sym.joints[j] == j and sym.joint_signs[j] == sign, name
    # the button is a real sprung slide with stops
    j = m.joint("bell_button").id
    assert m.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE and m.jnt_limited[j]
    np.testing.assert_allclose(m.jnt_range[j], [-env.scene.button_travel, 0.0])
    assert m.jnt_stiffness[j] == env.scene.spring_stiffness
    assert m.qpos_spring[m.jnt_qposadr[j]] > 0  # preloaded against the upper stop
    np.testing.assert_allclose(m.jnt_axis[j], [0.0, 0.0, 1.0])
    # only the button collides, and only with the finger pads
    bell_geoms = [g for g in range(m.ngeom)
                  if m.body(m.geom_bodyid[g]).name in ("bell", "bell_button")]
    colliding = [m.geom(g).name for g in bell_geoms if m.geom_contype[g] or m.geom_conaffinity[g]]
    assert colliding == ["bell_button"]
    g = m.geom("bell_button").id
    assert m.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE
    assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == robots.PAD_BIT


def test_spring_holds_the_button_up_and_returns_it():
    """Passive physics on the host (MuJoCo C, same model): the button rests at its upper
    stop, and released from its lower stop the spring pushes it back up."""
    env = make_env("click_bell", obs=("qpos",))
    m = env.mj_model
    d = mujoco.MjData(m)
    q0, _ = env.scene.init(jax.random.key(0), env)
    adr = env.scene._ids(env)["button_qadr"]
    for start in (0.0, -env.scene.button_travel):
        d.qpos[:] = np.asarray(q0)
        d.qpos[adr] = start
        d.qvel[:] = 0
        d.ctrl[:] = env.home_ctrl
        for _ in range(250):  # 1 s
            mujoco.mj_step(m, d)
        assert abs(d.qpos[adr]) < 5e-4, (start, d.qpos[adr])


# ---------------------------------------------------------------------------- distribution
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_initial_distribution_is_mirror_symmetric(env, rollouts):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    side = np.asarray(info["side"])
    assert 0.4 < (side > 0).mean() < 0.6
    assert np.all(_valid_start(env, qpos, side))
    # the mirror image of every sampled start is a valid start on the other side
    qpos_m = jax.vmap(env.sym.qpos)(qpos)
    assert np.all(_valid_start(env, qpos_m, -side))
    # and the ranges on the two sides are mirror images: compare the two empirical
    # distributions of (x, |y|) by their quantiles
    xy = np.asarray(jax.vmap(lambda q: scene.bell_xy(q, env))(qpos))
    for col in (0, 1):
        a, b = np.abs(xy[side > 0, col]), np.abs(xy[side < 0, col])
        qs = np.linspace(0.05, 0.95, 7)
        np.testing.assert_allclose(np.quantile(a, qs), np.quantile(b, qs), atol=0.02)
    # env.mirror_state of reset states (the rollout fixture's second half) are valid starts
    s0, _, _ = rollouts
    n = N_SEEDS
    side0 = np.asarray(s0.info["side"])
    np.testing.assert_array_equal(side0[n:], -side0[:n])
    assert np.all(_valid_start(env, s0.data.qpos, side0))
    # the point-cloud crop holds every bell the distribution can place
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    half = np.asarray(scene.base_half[:2])
    assert np.all(xy - half >= lo[:2]) and np.all(xy + half <= hi[:2])
    for side_opt, sgn in (("left", 1.0), ("right", -1.0)):
        e = make_env("click_bell", side=side_opt, obs=("qpos",))
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
    assert not np.any(np.asarray(s0.metrics["pressed"]))
    assert np.all(np.asarray(final.info["step"]) == traj["action"].shape[1])
    assert np.all(np.asarray(final.metrics["nan_action"]) == 0)


# ---------------------------------------------------------------------------- predicate
def _evaluate(env, qpos, opening):
    """(success, terms) of a state built by hand on the host (no stepping)."""
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(qpos)
    for side, o in enumerate(opening):
        d.qpos[env.grip_qadr[side]] = np.asarray(env.info.gripper_ctrl(o))
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
    for side in (0, 1):
        under = lambda dx=0.0, depth=0.0: scene.placed_qpos(q0, env, ee[side, :2] + [dx, 0.0], depth)
        closed = (1.0, 0.0) if side else (0.0, 1.0)
        ok, t = _evaluate(env, under(depth=0.01), closed)
        assert ok and abs(t["button_depth"] - 0.01) < 1e-6, t
        assert _evaluate(env, under(dx=0.02, depth=scene.press_depth + 1e-4), closed)[0]
        assert not _evaluate(env, under(depth=0.0), closed)[0]  # not pressed
        assert not _evaluate(env, under(depth=scene.press_depth - 1e-3), closed)[0]  # not far enough
        assert not _evaluate(env, under(depth=0.01), (1.0, 1.0))[0]  # gripper open
        ok, t = _evaluate(env, under(dx=0.03, depth=0.01), closed)  # beside the button
        assert not ok and abs(t["ee_button_xy"] - 0.03) < 1e-5


# ---------------------------------------------------------------------------- expert
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_presses_the_button_on_both_sides(env, rollouts):
    s0, final, traj = rollouts
    side = np.asarray(s0.info["side"])
    assert set(side.tolist()) == {-1.0, 1.0}
    success = np.asarray(final.info["success"])
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    adr = env.scene._ids(env)["button_qadr"]
    depth = -traj["qpos"][:, :, adr]
    print(f"\nexpert success {success.sum()}/{success.size}, sides {side}, first success step "
          f"{first}, max button depth (mm) {np.round(depth.max(axis=1) * 1000, 1)}")
    assert success.all()
    # the button physically went down past the threshold, then the spring brought it back
    assert np.all(depth.max(axis=1) >= env.scene.press_depth)
    assert np.all(np.abs(depth[:, -1]) < 1e-3)
    # the arm on the bell's side acted: the other arm's joints stayed near home
    acts = traj["action"].reshape(2 * N_SEEDS, traj["action"].shape[1], 2, -1)
    moved = np.abs(acts[..., :-1] - acts[:, :1, :, :-1]).max(axis=(1, 3))  # [B, 2]
    active = np.where(side > 0, 0, 1)
    assert np.all(moved[np.arange(len(side)), active] > 0.1)
    assert np.all(moved[np.arange(len(side)), 1 - active] < 1e-3)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(env, rollouts):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored bell/button motion."""
    _, _, traj = rollouts
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    ids = env.scene._ids(env)
    xy = traj["qpos"][:, :, [ids["x_qadr"], ids["y_qadr"]]]
    xy_err = np.abs(xy[n:] - xy[:n] * MIRROR_Y).max()
    depth_err = np.abs(traj["qpos"][n:, :, ids["button_qadr"]] - traj["qpos"][:n, :, ids["button_qadr"]]).max()
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; bell xy error "
          f"{xy_err * 1000:.4f} mm; button depth error {depth_err * 1000:.4f} mm over {traj['action'].shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the other arm acted: the check is not vacuous
    assert act_err < 1e-3
    assert xy_err < 1e-3 and depth_err < 1e-3
