"""handover_block: task registry and option errors (including ``robotwin_faithful``), model,
initial distribution (mirror-symmetric by default, always-left when faithful), success
predicate, scripted two-arm expert (handover on both sides, mirror equivariance, 50-start
success rate, the faithful variant).

The slow expert tests share one compiled rollout program per module, the task's
``task_rollouts.expert_episodes``: the expert from 50 seeded starts and from the mirror
images of the first 25 (so both sides are always covered), run 10 steps past the end of
its script. The same episodes serve the generic expert check (success rate, shapes, ``S`` on
the recorded demos) and this file's task-specific checks.
The faithful variant's starts run through the same program.
"""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts import make_expert
from equibim_jax.experts.handover_block import PHASES, HandoverExpertConfig
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.handover_block import HandoverBlock

from task_rollouts import N_PAIRS, assert_same_point_set, collides, expert_fixtures, run_starts

TASK = "handover_block"
N_SEEDS = N_PAIRS  # starts kept whole in the shared expert episodes, each with its mirror image
CFG = HandoverExpertConfig()
REFLECT = np.array([1.0, -1.0, 1.0])


def _phase_end(name):
    """Control step at which phase ``name`` of the script ends."""
    return int(sum(CFG.durations[: PHASES.index(name) + 1]))


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
    assert task_entry(TASK).expert is not None and task_entry(TASK).step_limit == 800
    with pytest.raises(ValueError, match="valid tasks: .*handover_block"):
        make_env("handover_blocks")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['colour'\].*valid options: .*pad_y_range"):
        make_env(TASK, colour="red")
    with pytest.raises(ValueError, match="side must be one of"):
        make_env(TASK, side="middle")
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, block_x_range=(0.3, 0.2))
    with pytest.raises(ValueError, match="wholly on its side"):
        make_scene(TASK, block_y_range=(0.01, 0.2))
    with pytest.raises(ValueError, match="wholly on its side"):
        make_scene(TASK, pad_y_range=(0.04, 0.2))
    with pytest.raises(ValueError, match="three positive half sizes"):
        make_scene(TASK, block_half=(0.02, 0.02))
    with pytest.raises(ValueError, match="block_mass must be positive"):
        make_scene(TASK, block_mass=0.0)
    with pytest.raises(ValueError, match="open_threshold"):
        make_scene(TASK, open_threshold=1.0)
    with pytest.raises(ValueError, match="not a valid"):
        make_scene(TASK, success_xy="near")
    with pytest.raises(ValueError, match="unknown option"):
        make_scene(TASK, episode_length=3)  # an env option, not a scene one
    # robotwin_faithful: always the block on the left; side="right" contradicts it
    with pytest.raises(ValueError, match="robotwin_faithful=True always starts the block on the left"):
        make_env(TASK, robotwin_faithful=True, side="right")
    with pytest.raises(ValueError, match="robotwin_faithful must be a bool"):
        make_scene(TASK, robotwin_faithful=1)
    faithful = make_scene(TASK, robotwin_faithful=True)  # side "both" (default) resolves to "left"
    assert faithful.side == "left" and faithful == make_scene(TASK, robotwin_faithful="true", side="left")
    assert make_env(TASK, robotwin_faithful=True, obs=("qpos",)).task_options["side"] == "left"
    # expert options
    with pytest.raises(ValueError, match="durations needs 15"):
        HandoverExpertConfig(durations=(10,) * 14)
    with pytest.raises(ValueError, match="grasp_below_top"):
        make_expert(env, config=HandoverExpertConfig(grasp_below_top=0.2))
    with pytest.raises(ValueError, match="must leave at least 1 cm"):
        make_expert(env, config=HandoverExpertConfig(receiver_grip_height=0.07))
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env(TASK, action="ee", obs=("qpos",)))
    assert {"obs", "action", "episode_length", "side", "robotwin_faithful", "pad_x_range"} <= set(task_options(TASK))
    assert env.config.episode_length == 800  # the task's step limit
    assert env.config.obs == ("qpos", "point_cloud") and env.config.n_points == 64
    assert env.scene == HandoverBlock(side="both") and not env.scene.robotwin_faithful
    assert make_scene(TASK, side="left", success_xy="0.025").success_xy == 0.025  # strings are parsed


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    # friction grasp only: no equality constraints (welds), no mocap bodies
    assert m.neq == 0 and m.nmocap == 0
    assert m.jnt_type[m.joint("block").id] == mujoco.mjtJoint.mjJNT_FREE
    assert abs(m.body_mass[m.body("block").id] - 0.06) < 1e-9
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    # the target pad's slide joints mirror as polar vectors: x keeps its sign, y flips
    for name, sign in (("target_x", 1.0), ("target_y", -1.0)):
        j = m.joint(name).id
        assert env.sym.joints[j] == j and env.sym.joint_signs[j] == sign
    # Few contact pairs: the block touches the grippers, the table and the target pad; the
    # target pad only the block.
    geom = lambda n: m.geom(n).id
    gripper = {geom(f"{s}_{g}") for s in ("left", "right") for g in ("pad_a", "pad_b", "palm")}
    partners = lambda g: {h for h in range(m.ngeom) if m.geom_bodyid[h] != m.geom_bodyid[g] and collides(m, g, h)}
    assert partners(geom("block")) == gripper | {geom("table"), geom("target")}
    assert partners(geom("target")) == {geom("block")}
    # The grasp holds by friction with a wide margin: at the 4 cm block a closing finger
    # pushes kp * its distance to the closed target, far more than the weight needs.
    finger = m.actuator("left_finger_a")
    push = finger.gainprm[0] * (2 * env.scene.block_half[0] - env.info.gripper_closed_gap) / 2
    mu = max(m.geom_friction[geom("block"), 0], m.geom_friction[geom("left_pad_a"), 0])
    assert 2 * mu * float(push) > 10 * m.body_mass[m.body("block").id] * 9.81


def _draw(env, scene, keys):
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    block, pad = jax.vmap(lambda q: env.scene.positions_from_qpos(q, env))(qpos)
    return np.asarray(qpos), np.asarray(block), np.asarray(pad), np.asarray(info["side"])


def _check_support(env, scene, qpos, block, pad, side):
    """Every start lies in the ranges, block on ``side``, pad on the other, arms at home."""
    np.testing.assert_array_equal(np.sign(block[:, 1]), side)
    np.testing.assert_array_equal(np.sign(pad[:, 1]), -side)
    for p, (xr, yr) in ((block, (scene.block_x_range, scene.block_y_range)),
                        (pad, (scene.pad_x_range, scene.pad_y_range))):
        assert np.all((p[:, 0] >= xr[0]) & (p[:, 0] <= xr[1]))
        assert np.all((np.abs(p[:, 1]) >= yr[0]) & (np.abs(p[:, 1]) <= yr[1]))
    np.testing.assert_allclose(block[:, 2], scene.block_half[2], atol=1e-6)  # resting on the table
    nq = env.info.nq_robot
    np.testing.assert_allclose(qpos[:, :nq], np.broadcast_to(env.home_qpos[:nq], (len(qpos), nq)))


def test_initial_distribution_is_mirror_symmetric(env):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, block, pad, side = _draw(env, scene, keys)
    assert 0.45 < (side > 0).mean() < 0.55
    _check_support(env, scene, qpos, block, pad, side)
    # The law is mirror-symmetric, exactly: from the same key, side="right" draws the mirror
    # image of what side="left" draws, and side="both" picks either with probability 1/2.
    _, block_l, pad_l, _ = _draw(env, dataclasses.replace(scene, side="left"), keys[:256])
    _, block_r, pad_r, side_r = _draw(env, dataclasses.replace(scene, side="right"), keys[:256])
    assert np.all(side_r == -1.0)
    np.testing.assert_array_equal(block_r, block_l * REFLECT)
    np.testing.assert_array_equal(pad_r, pad_l * REFLECT)
    # the point-cloud crop holds every block and pad the distribution can place, and the
    # block held at the handover
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    for centre, half in ((block, np.asarray(scene.block_half)), (pad, np.asarray(scene.pad_half))):
        assert np.all(centre[:, :2] - half[:2] >= lo[:2]) and np.all(centre[:, :2] + half[:2] <= hi[:2])
    assert CFG.handover_bottom + 2 * scene.block_half[2] <= hi[2]


def test_initial_distribution_faithful_is_always_left(env):
    """robotwin_faithful=True: block always on the left, pad on the right (asymmetric on
    purpose), otherwise the same ranges."""
    scene = make_scene(TASK, robotwin_faithful=True)
    keys = jax.random.split(jax.random.key(1), 500)
    qpos, block, pad, side = _draw(env, scene, keys)
    assert np.all(side == 1.0) and np.all(block[:, 1] > 0) and np.all(pad[:, 1] < 0)
    _check_support(env, scene, qpos, block, pad, side)
    # the same draws as side="left" without the option
    _, block_l, pad_l, _ = _draw(env, dataclasses.replace(env.scene, side="left"), keys[:64])
    np.testing.assert_array_equal(block[:64], block_l)
    np.testing.assert_array_equal(pad[:64], pad_l)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_mirror_of_a_start_is_a_start(env, rollouts):
    """``env.mirror_state`` of sampled starts: objects reflected, side flipped, arms at home,
    every constraint of the distribution still met, and the point cloud reflected."""
    s0, _, _ = rollouts
    scene, n = env.scene, N_SEEDS
    block, pad = jax.vmap(lambda q: scene.positions_from_qpos(q, env))(s0.data.qpos)
    block, pad, side = np.asarray(block), np.asarray(pad), np.asarray(s0.info["side"])
    np.testing.assert_allclose(block[n:], block[:n] * REFLECT, atol=1e-6)
    np.testing.assert_allclose(pad[n:], pad[:n] * REFLECT, atol=1e-6)
    np.testing.assert_array_equal(side[n:], -side[:n])
    _check_support(env, scene, np.asarray(s0.data.qpos), block, pad, side)
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
def _evaluate(env, qpos, opening=None):
    """(success, terms) of a state built by hand on the host (no stepping)."""
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(qpos)
    if opening is not None:
        for side, o in enumerate(opening):
            d.qpos[env.grip_qadr[side]] = np.asarray(env.info.gripper_ctrl(o))
    mujoco.mj_forward(m, d)
    _, success, metrics = env.scene.evaluate(mjx.put_data(m, d), {}, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def _placed_qpos(env, dx=0.0, dz=0.0, tilt_deg=0.0, pad_side=-1.0):
    """The block standing on the pad (pad on ``pad_side``), shifted and tilted about x."""
    scene = env.scene
    pad = (0.28, pad_side * 0.15)
    top = env.info.table_height + 2 * scene.pad_half[2]
    t = np.deg2rad(tilt_deg)
    quat = (np.cos(t / 2), np.sin(t / 2), 0.0, 0.0)  # about x
    # the lowest point of the tilted box is this far below its centre
    below = scene.block_half[1] * abs(np.sin(t)) + scene.block_half[2] * abs(np.cos(t))
    block = (pad[0] + dx, pad[1], top + below + dz)
    return np.asarray(scene.placed_qpos(jnp.asarray(env.home_qpos), env, block, quat, pad_xy=pad))


def test_success_predicate_cases(env):
    assert _evaluate(env, _placed_qpos(env))[0]  # on the pad, both grippers at home (open)
    assert _evaluate(env, _placed_qpos(env, pad_side=1.0))[0]
    ok, t = _evaluate(env, _placed_qpos(env, dx=0.025, dz=0.008))  # inside both tolerances
    assert ok and abs(t["block_pad_dz"] - 0.008) < 1e-5
    ok, t = _evaluate(env, _placed_qpos(env, dx=0.035))
    assert not ok and abs(t["block_pad_xy"] - 0.035) < 1e-5  # 3.5 cm off: outside 3 cm
    assert not _evaluate(env, _placed_qpos(env, dz=0.015))[0]  # held 1.5 cm above it
    # the bottom is the block's lowest point: a tilted block resting on a corner counts
    ok, t = _evaluate(env, _placed_qpos(env, tilt_deg=10.0))
    assert ok and abs(t["block_pad_dz"]) < 1e-5 and abs(t["block_tilt_deg"] - 10.0) < 1e-3
    # Only the receiving gripper (the arm on the pad's side) must be open. A gripper
    # squeezing the 4 cm block (opening ~0.40) or closed is not open.
    held = float(env.info.opening_for_gap(2 * env.scene.block_half[0]))
    assert 0.3 < held < 0.5
    for pad_side, recv in ((-1.0, 1), (1.0, 0)):
        q = _placed_qpos(env, pad_side=pad_side)
        for o_recv, o_other, expect in ((held, 1.0, False), (0.0, 1.0, False), (1.0, 0.0, True),
                                        (0.7, held, True)):
            opening = [o_other, o_other]
            opening[recv] = o_recv
            ok, t = _evaluate(env, q, opening=opening)
            assert ok == expect, (pad_side, opening)
            assert abs(t["receiver_opening"] - o_recv) < 1e-3
    q0, _ = env.scene.init(jax.random.key(5), env)  # where it starts: on the table, off the pad
    assert not _evaluate(env, q0)[0]


# ---------------------------------------------------------------------------- expert
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_hands_over_on_both_sides(env, rollouts):
    """Success on both sides, and the handover was physical: the giver lifted the block to
    the handover, both grippers were closed on it, then the receiver alone held it at the
    handover height (the giver open) until it carried it away."""
    s0, final, traj = rollouts
    success, side = np.asarray(final.info["success"]), np.asarray(s0.info["side"])
    assert set(side.tolist()) == {-1.0, 1.0}
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    print(f"\nexpert success {success.sum()}/{success.size}, sides {side}, first success step {first}")
    assert success.all()
    a = env.scene._ids(env)["block_qadr"]
    bottom = traj["qpos"][:, :, a + 2] - env.scene.block_half[2]  # the block stays upright
    opening = np.asarray(jax.vmap(jax.vmap(env.gripper_opening))(jnp.asarray(traj["qpos"])))  # [B, T, 2]
    giver = np.where(side > 0, 0, 1)
    rows = np.arange(len(side))
    held = float(env.info.opening_for_gap(2 * env.scene.block_half[0]))
    t_both = _phase_end("settle2") - 1  # both closed on the block
    t_solo = _phase_end("withdraw") - 1  # the giver open and away, the receiver holding
    assert np.all(np.abs(opening[:, t_both] - held) < 0.05), opening[:, t_both]
    assert np.all(opening[rows, t_solo, giver] > 0.95)
    assert np.all(np.abs(opening[rows, t_solo, 1 - giver] - held) < 0.05)
    assert np.all(np.abs(bottom[:, t_solo] - CFG.handover_bottom) < 0.015), bottom[:, t_solo]
    xy = traj["qpos"][:, t_solo, a : a + 2]
    assert np.all(np.abs(xy - np.array([CFG.handover_x, 0.0])) < 0.01), xy


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(env, rollouts):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored block trajectory."""
    _, _, traj = rollouts
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    a = env.scene._ids(env)["block_qadr"]
    block, block_m = traj["qpos"][:n, :, a : a + 3], traj["qpos"][n:, :, a : a + 3]
    block_err = np.abs(block_m - block * REFLECT).max()
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; "
          f"max block position error = {block_err * 1000:.3f} mm over {acts.shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the arms' roles swapped: the check is not vacuous
    assert act_err < 1e-3
    assert block_err < 5e-3


@pytest.mark.slow
def test_faithful_variant_expert_succeeds(episodes):
    """robotwin_faithful=True: 50 always-left starts, run by the same expert in the same
    model through the shared episodes' compiled program (the faithful scene differs from the
    default one only in how it draws starts)."""
    env = episodes.env
    env_f = make_env(TASK, robotwin_faithful=True, obs=env.config.obs)
    assert dataclasses.replace(env_f.scene, side="both", robotwin_faithful=False) == env.scene
    keys = jax.random.split(jax.random.key(3), 50)
    qpos, info = jax.jit(jax.vmap(lambda k: env_f.scene.init(k, env_f)))(keys)
    _, final, _ = run_starts(episodes, qpos, info)  # asserts that the program did not recompile
    success, side = np.asarray(final.info["success"]), np.asarray(final.info["side"])
    print(f"\nfaithful variant: success {success.sum()}/{success.size}")
    assert np.all(side == 1.0)
    assert success.mean() >= 0.95
