"""stamp_seal: task registry and option errors, model, initial distribution and its mirror
symmetry, jitted reset/step, success predicate, scripted expert (success on both sides
and mirror equivariance).

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
from equibim_jax.experts.stamp_seal import SealExpertConfig
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.stamp_seal import StampSeal

from task_rollouts import N_PAIRS, assert_same_point_set, collides, expert_fixtures

TASK = "stamp_seal"
N_SEEDS = N_PAIRS  # starts kept whole in the shared expert episodes, each with its mirror image


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
    with pytest.raises(ValueError, match="valid tasks: .*stamp_seal"):
        make_env("stamp_seals")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['ink'\].*valid options: .*seal_y_range"):
        make_env(TASK, ink="red")
    with pytest.raises(ValueError, match="side must be one of"):
        make_env(TASK, side="middle")
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, seal_x_range=(0.3, 0.2))
    with pytest.raises(ValueError, match="wholly on its side"):
        make_scene(TASK, seal_y_range=(0.0, 0.2))
    with pytest.raises(ValueError, match="min_dist must exceed"):
        make_scene(TASK, min_dist=0.05)
    with pytest.raises(ValueError, match="never put the seal and the mat"):
        make_scene(TASK, seal_x_range=(0.3, 0.3), mat_x_range=(0.3, 0.3), seal_y_range=(0.1, 0.1),
                   mat_y_range=(0.1, 0.15))
    with pytest.raises(ValueError, match="n_candidates"):
        make_scene(TASK, n_candidates=0)
    with pytest.raises(ValueError, match="not a valid"):
        make_scene(TASK, min_dist="far")
    with pytest.raises(ValueError, match="unknown option"):
        make_scene(TASK, episode_length=3)  # an env option, not a scene one
    with pytest.raises(ValueError, match="grasp_below_top"):
        make_expert(env, config=SealExpertConfig(grasp_below_top=0.2))
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env(TASK, action="ee", obs=("qpos",)))
    assert {"obs", "action", "episode_length", "side", "mat_x_range", "min_dist"} <= set(task_options(TASK))
    assert env.config.episode_length == 400  # the task's step limit
    assert env.config.obs == ("qpos", "point_cloud") and env.config.n_points == 64
    assert env.scene == StampSeal(side="both")
    assert make_scene(TASK, side="left", min_dist="0.12").min_dist == 0.12  # strings are parsed


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    # friction grasp only: no equality constraints (welds), no mocap bodies
    assert m.neq == 0 and m.nmocap == 0
    assert m.jnt_type[m.joint("seal").id] == mujoco.mjtJoint.mjJNT_FREE
    assert abs(m.body_mass[m.body("seal").id] - 0.06) < 1e-9
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    # the mat's slide joints mirror as polar vectors: x keeps its sign, y flips
    for name, sign in (("mat_x", 1.0), ("mat_y", -1.0)):
        j = m.joint(name).id
        assert env.sym.joints[j] == j and env.sym.joint_signs[j] == sign
    # Few contact pairs: the handle touches only the grippers, the base also the table and
    # the mat, the mat only the base.
    geom = lambda n: m.geom(n).id
    gripper = {geom(f"{s}_{g}") for s in ("left", "right") for g in ("pad_a", "pad_b", "palm")}
    partners = lambda g: {h for h in range(m.ngeom) if m.geom_bodyid[h] != m.geom_bodyid[g] and collides(m, g, h)}
    assert partners(geom("seal_handle")) == gripper
    assert partners(geom("seal_base")) == gripper | {geom("table"), geom("mat")}
    assert partners(geom("mat")) == {geom("seal_base")}


def test_initial_distribution(env):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    seal, mat = jax.vmap(lambda q: scene.positions_from_qpos(q, env))(qpos)
    seal, mat, side = np.asarray(seal), np.asarray(mat), np.asarray(info["side"])
    assert 0.45 < (side > 0).mean() < 0.55
    np.testing.assert_array_equal(np.sign(seal[:, 1]), side)
    np.testing.assert_array_equal(np.sign(mat[:, 1]), side)
    for p, (xr, yr) in ((seal, (scene.seal_x_range, scene.seal_y_range)),
                        (mat, (scene.mat_x_range, scene.mat_y_range))):
        assert np.all((p[:, 0] >= xr[0]) & (p[:, 0] <= xr[1]))
        assert np.all((np.abs(p[:, 1]) >= yr[0]) & (np.abs(p[:, 1]) <= yr[1]))
    assert np.all(np.linalg.norm(seal[:, :2] - mat[:, :2], axis=1) >= scene.min_dist - 1e-6)
    np.testing.assert_allclose(seal[:, 2], scene.base_half[2], atol=1e-6)  # resting on the table
    # The law is mirror-symmetric, exactly: from the same key, side="right" draws the mirror
    # image of what side="left" draws, and side="both" picks either with probability 1/2.
    draw = lambda side_opt: jax.vmap(lambda q: scene.positions_from_qpos(q, env))(jax.jit(jax.vmap(
        lambda k: dataclasses.replace(scene, side=side_opt).init(k, env)[0]))(keys[:256]))
    (seal_l, mat_l), (seal_r, mat_r) = draw("left"), draw("right")
    reflect = np.array([1.0, -1.0, 1.0])
    np.testing.assert_array_equal(np.asarray(seal_r), np.asarray(seal_l) * reflect)
    np.testing.assert_array_equal(np.asarray(mat_r), np.asarray(mat_l) * reflect)
    # the point-cloud crop holds every seal and mat the distribution can place
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    for centre, half in ((seal, np.asarray(scene.base_half)), (mat, np.asarray(scene.mat_half))):
        assert np.all(centre[:, :2] - half[:2] >= lo[:2]) and np.all(centre[:, :2] + half[:2] <= hi[:2])
    assert np.all(seal[:, 2] - scene.base_half[2] + scene.seal_height <= hi[2])
    np.testing.assert_allclose(np.asarray(qpos)[:, : env.info.nq_robot],
                               np.broadcast_to(env.home_qpos[: env.info.nq_robot], (len(keys), env.info.nq_robot)))
    for side_opt, sgn in (("left", 1.0), ("right", -1.0)):
        e = make_env(TASK, side=side_opt, obs=("qpos",))
        _, inf = jax.vmap(lambda k: e.scene.init(k, e))(keys[:16])
        assert np.all(np.asarray(inf["side"]) == sgn)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_mirror_of_a_start_is_a_start(env, rollouts):
    """``env.mirror_state`` of sampled starts: objects reflected, side flipped, arms at home,
    every constraint of the distribution still met, and the point cloud reflected."""
    s0, _, _ = rollouts
    scene, n = env.scene, N_SEEDS
    seal, mat = jax.vmap(lambda q: scene.positions_from_qpos(q, env))(s0.data.qpos)
    seal, mat, side = np.asarray(seal), np.asarray(mat), np.asarray(s0.info["side"])
    reflect = np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(seal[n:], seal[:n] * reflect, atol=1e-6)
    np.testing.assert_allclose(mat[n:], mat[:n] * reflect, atol=1e-6)
    np.testing.assert_array_equal(side[n:], -side[:n])
    np.testing.assert_array_equal(np.sign(seal[:, 1]), side)
    np.testing.assert_array_equal(np.sign(mat[:, 1]), side)
    assert np.all((np.abs(seal[:, 1]) >= scene.seal_y_range[0]) & (np.abs(seal[:, 1]) <= scene.seal_y_range[1]))
    assert np.all((np.abs(mat[:, 1]) >= scene.mat_y_range[0]) & (np.abs(mat[:, 1]) <= scene.mat_y_range[1]))
    assert np.all(np.linalg.norm(seal[:, :2] - mat[:, :2], axis=1) >= scene.min_dist - 1e-6)
    q = np.asarray(s0.data.qpos)[:, : env.info.nq_robot]
    np.testing.assert_allclose(q, np.broadcast_to(env.home_qpos[: env.info.nq_robot], q.shape), atol=1e-6)
    pts = np.asarray(s0.obs["point_cloud"])
    for i in range(n):
        assert_same_point_set(pts[i] * reflect, pts[n + i], atol=1e-5)


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


def _placed_qpos(env, dx=0.0, dz=0.0, tilt_deg=0.0, side=1.0):
    scene = env.scene
    mat = (0.28, side * 0.12)
    top = env.info.table_height + 2 * scene.mat_half[2]
    half = np.deg2rad(tilt_deg) / 2
    quat = (np.cos(half), np.sin(half), 0.0, 0.0)  # about x
    seal = (mat[0] + dx, mat[1], top + scene.base_half[2] + dz)
    return np.asarray(scene.placed_qpos(jnp.asarray(env.home_qpos), env, seal, quat, mat_xy=mat))


def test_success_predicate_cases(env):
    assert _evaluate(env, _placed_qpos(env))[0]  # on the mat, upright, both grippers at home (open)
    assert _evaluate(env, _placed_qpos(env, side=-1.0))[0]
    assert _evaluate(env, _placed_qpos(env, dx=0.015, dz=0.005, tilt_deg=10.0))[0]  # inside every tolerance
    ok, t = _evaluate(env, _placed_qpos(env, dx=0.025))
    assert not ok and abs(t["seal_mat_xy"] - 0.025) < 1e-5  # 2.5 cm off: outside the 2 cm tolerance
    assert not _evaluate(env, _placed_qpos(env, dz=0.02))[0]  # held 2 cm above it
    ok, t = _evaluate(env, _placed_qpos(env, tilt_deg=20.0))
    assert not ok and abs(t["seal_tilt_deg"] - 20.0) < 1e-3
    # a gripper squeezing the 2.4 cm handle (opening ~0.22) or closed is not released
    held = float(env.info.opening_for_gap(2 * env.scene.handle_half[1]))
    assert 0.15 < held < 0.3
    assert not _evaluate(env, _placed_qpos(env), opening=(held, 1.0))[0]
    assert not _evaluate(env, _placed_qpos(env), opening=(1.0, 0.0))[0]
    assert _evaluate(env, _placed_qpos(env), opening=(1.0, 0.6))[0]
    q0, _ = env.scene.init(jax.random.key(5), env)  # where it starts: on the table, off the mat
    assert not _evaluate(env, q0)[0]


# ---------------------------------------------------------------------------- expert
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_success_both_sides(env, rollouts):
    s0, final, traj = rollouts
    success, side = np.asarray(final.info["success"]), np.asarray(s0.info["side"])
    assert set(side.tolist()) == {-1.0, 1.0}
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    print(f"\nexpert success {success.sum()}/{success.size}, sides {side}, first success step {first}")
    assert success.sum() >= success.size - 1
    # the grasp held by friction: the seal rose by about the carry lift
    a = env.scene._ids(env)["seal_qadr"]
    lift = traj["qpos"][:, :, a + 2].max(axis=1) - np.asarray(s0.data.qpos)[:, a + 2]
    assert np.all(lift > 0.04), lift


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(env, rollouts):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored seal trajectory."""
    _, _, traj = rollouts
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    a = env.scene._ids(env)["seal_qadr"]
    seal, seal_m = traj["qpos"][:n, :, a : a + 3], traj["qpos"][n:, :, a : a + 3]
    seal_err = np.abs(seal_m - seal * np.array([1.0, -1.0, 1.0])).max()
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; "
          f"max seal position error = {seal_err * 1000:.3f} mm over {acts.shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the other arm acted: the check is not vacuous
    assert act_err < 1e-3
    assert seal_err < 5e-3
