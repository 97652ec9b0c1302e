"""pick_dual_bottles: task registry and option errors (``robotwin_faithful`` included),
model (mirror-symmetric by default, two different bottles with ``robotwin_faithful``),
initial distribution and its mirror symmetry, success predicate, jitted reset/step, the
two-arm scripted expert (success, mirror equivariance, arms apart), 50-start success rate
and the faithful variant's expert.

The default tests compile no MJX rollout. The slow expert tests share one compiled rollout
program per module, the task's ``task_rollouts.expert_episodes``: the expert from 50 seeded
starts and from the mirror images of the first 25, run 10 steps past the end of its script.
The same episodes serve the generic expert check (success rate, shapes, ``S`` on the
recorded demos) and this file's task-specific checks. The faithful variant (a different
model) compiles its own.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts import make_expert, make_rollout
from equibim_jax.experts.pick_dual_bottles import DualBottlesExpertConfig
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.pick_dual_bottles import PickDualBottles

from task_rollouts import N_PAIRS, collides, expert_fixtures

TASK = "pick_dual_bottles"
N_SEEDS = N_PAIRS  # starts kept whole in the shared expert episodes, each with its mirror image
REFLECT = np.array([1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def env():
    return make_env(TASK, obs=("qpos",))


@pytest.fixture(scope="module")
def env_faithful():
    return make_env(TASK, robotwin_faithful=True, obs=("qpos",))


episodes, test_expert_generic_checks = expert_fixtures(TASK)


@pytest.fixture(scope="module")
def rollouts(episodes):
    """(initial states [2N], final states [2N], traj) for N starts then their N mirror images."""
    return episodes.s0, episodes.final, episodes.traj


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors():
    assert TASK in task_names()
    assert task_entry(TASK).expert is not None and task_entry(TASK).step_limit == 400
    with pytest.raises(ValueError, match="valid tasks: .*pick_dual_bottles"):
        make_env("pick_dual_bottle")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['side'\].*valid options: .*y_range"):
        make_env(TASK, side="left")  # both arms act: the task has no side option
    with pytest.raises(ValueError, match="robotwin_faithful must be a bool"):
        make_scene(TASK, robotwin_faithful=1)
    with pytest.raises(ValueError, match="not a valid"):
        make_scene(TASK, robotwin_faithful="yes")
    assert make_scene(TASK, robotwin_faithful="true").robotwin_faithful is True  # parsed
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, x_range=(0.3, 0.2))
    with pytest.raises(ValueError, match="wholly on its side"):
        make_scene(TASK, y_range=(0.03, 0.2))
    with pytest.raises(ValueError, match="wholly on its side"):  # the faithful right bottle is wider
        make_scene(TASK, y_range=(0.04, 0.2), robotwin_faithful=True)
    with pytest.raises(ValueError, match="three positive half sizes"):
        make_scene(TASK, body_half=(0.02, 0.02))
    with pytest.raises(ValueError, match="must not overhang"):
        make_scene(TASK, neck_radius=0.03)
    with pytest.raises(ValueError, match="must not overhang"):
        make_scene(TASK, right_neck_radius=0.031, robotwin_faithful=True)
    with pytest.raises(ValueError, match="capsule"):
        make_scene(TASK, neck_length=0.02)
    with pytest.raises(ValueError, match="body_mass must be positive"):
        make_scene(TASK, body_mass=0.0)
    with pytest.raises(ValueError, match="must exceed success_dist"):
        make_scene(TASK, lift_target=(0.3, 0.08, 0.2))
    with pytest.raises(ValueError, match="at least min_lift"):
        make_scene(TASK, lift_target=(0.3, 0.15, 0.12))
    with pytest.raises(ValueError, match=r"\(x_t, y_t, z_t\)"):
        make_scene(TASK, lift_target=(0.3, 0.15))
    with pytest.raises(ValueError, match="unknown option"):
        make_scene(TASK, episode_length=3)  # an env option, not a scene one
    assert {"obs", "action", "episode_length", "robotwin_faithful", "lift_target"} <= set(task_options(TASK))
    e = make_env(TASK)
    assert e.config.episode_length == 400  # the task's step limit
    assert e.config.obs == ("qpos", "point_cloud") and e.config.n_points == 64
    assert e.scene == PickDualBottles()
    with pytest.raises(ValueError, match="grasp_below_top"):
        make_expert(e, config=DualBottlesExpertConfig(grasp_below_top=0.09))
    with pytest.raises(ValueError, match="durations needs 6"):
        DualBottlesExpertConfig(durations=(10, 10))
    with pytest.raises(ValueError, match="pregrasp_height"):
        DualBottlesExpertConfig(pregrasp_height=0.0)
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env(TASK, action="ee", obs=("qpos",)))


def _partners(m, name):
    g = m.geom(name).id
    return {m.geom(h).name for h in range(m.ngeom)
            if m.geom_bodyid[h] != m.geom_bodyid[g] and collides(m, g, h)}


GRIPPERS = {f"{s}_{g}" for s in ("left", "right") for g in ("pad_a", "pad_b", "palm")}


def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    # friction grasp only: no equality constraints (welds), no mocap bodies
    assert m.neq == 0 and m.nmocap == 0
    for name in ("bottle_a", "bottle_b"):
        assert m.jnt_type[m.joint(name).id] == mujoco.mjtJoint.mjJNT_FREE
        assert abs(m.body_mass[m.body(name).id] - 0.1) < 1e-9
        # each free bottle maps to itself (reflected in place)
        assert env.sym.bodies[m.body(name).id] == m.body(name).id
    # the two bottles are identical
    for part in ("body", "neck"):
        ga, gb = m.geom(f"bottle_a_{part}").id, m.geom(f"bottle_b_{part}").id
        assert m.geom_type[ga] == m.geom_type[gb]
        np.testing.assert_array_equal(m.geom_size[ga], m.geom_size[gb])
        np.testing.assert_array_equal(m.geom_pos[ga], m.geom_pos[gb])
        np.testing.assert_array_equal(m.geom_rgba[ga], m.geom_rgba[gb])
    assert m.geom_type[m.geom("bottle_a_neck").id] == mujoco.mjtGeom.mjGEOM_CAPSULE
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    # Few contact pairs: the neck touches only the grippers; the body also the table, but
    # not the other bottle.
    assert _partners(m, "bottle_a_neck") == GRIPPERS
    assert _partners(m, "bottle_a_body") == GRIPPERS | {"table"}
    assert _partners(m, "bottle_b_body") == GRIPPERS | {"table"}


def test_faithful_model_is_not_symmetric(env, env_faithful):
    m = env_faithful.mj_model
    assert m.neq == 0 and m.nmocap == 0
    ma, mb = (m.body_mass[m.body(n).id] for n in ("bottle_a", "bottle_b"))
    assert abs(ma - 0.1) < 1e-9 and abs(mb - 0.15) < 1e-9  # different masses
    for part in ("body", "neck"):
        ga, gb = m.geom(f"bottle_a_{part}").id, m.geom(f"bottle_b_{part}").id
        assert np.abs(m.geom_size[ga] - m.geom_size[gb]).max() > 1e-3  # different shapes
    # The default bottle is bottle_a in both variants; only the right one differs.
    np.testing.assert_array_equal(m.geom_size[m.geom("bottle_a_body").id],
                                  env.mj_model.geom_size[env.mj_model.geom("bottle_a_body").id])
    # bottle_a (the default bottle) always starts on the left, bottle_b on the right, so the
    # mirror image of a start (bottle_a on the right) is never a start: not mirror-symmetric.
    scene = env_faithful.scene
    keys = jax.random.split(jax.random.key(1), 256)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env_faithful)))(keys)
    pos = np.asarray(jax.vmap(lambda q: scene.positions_from_qpos(q, env_faithful))(qpos))
    assert np.all(np.asarray(info["a_side"]) == 1.0)
    assert np.all(pos[:, 0, 1] > 0) and np.all(pos[:, 1, 1] < 0)
    mirrored = np.asarray(jax.vmap(env_faithful.sym.qpos)(qpos))
    pos_m = np.asarray(jax.vmap(lambda q: scene.positions_from_qpos(q, env_faithful))(mirrored))
    assert np.all(pos_m[:, 0, 1] < 0)  # bottle_a on the right: outside the faithful support
    # each bottle rests on the table at its own height
    np.testing.assert_allclose(pos[:, 0, 2], 0.05, atol=1e-6)
    np.testing.assert_allclose(pos[:, 1, 2], 0.04, atol=1e-6)


def _canonical(env, qpos):
    """``qpos`` as numpy with each bottle's quaternion sign fixed (w >= 0): q and -q are
    the same orientation."""
    q = np.array(qpos, np.float64)
    for a in env.scene._ids(env)["qadr"]:
        q[a + 3 : a + 7] *= 1.0 if q[a + 3] >= 0 else -1.0
    return q


def test_initial_distribution(env):
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    pos = np.asarray(jax.vmap(lambda q: scene.positions_from_qpos(q, env))(qpos))  # [n, 2, 3]
    a_side = np.asarray(info["a_side"])
    assert 0.45 < (a_side > 0).mean() < 0.55
    np.testing.assert_array_equal(np.sign(pos[:, 0, 1]), a_side)  # bottle_a on side a_side
    np.testing.assert_array_equal(np.sign(pos[:, 1, 1]), -a_side)  # bottle_b on the other
    for p in (pos[:, 0], pos[:, 1]):
        assert np.all((p[:, 0] >= scene.x_range[0]) & (p[:, 0] <= scene.x_range[1]))
        assert np.all((np.abs(p[:, 1]) >= scene.y_range[0]) & (np.abs(p[:, 1]) <= scene.y_range[1]))
        np.testing.assert_allclose(p[:, 2], scene.body_half[2], atol=1e-6)  # resting on the table
    # The law is mirror-symmetric, exactly: the mirror of layout(s, l, r) is
    # layout(-s, M r, M l), and (s, l, M r) are independent with s a fair coin and l, M r
    # identically distributed.
    rng = np.random.default_rng(0)
    for s in (1.0, -1.0):
        left = np.array([rng.uniform(*scene.x_range), rng.uniform(*scene.y_range)], np.float32)
        right = np.array([rng.uniform(*scene.x_range), -rng.uniform(*scene.y_range)], np.float32)
        q = scene.layout(env, jnp.asarray(s), left, right)
        expect = scene.layout(env, jnp.asarray(-s), right * REFLECT[:2], left * REFLECT[:2])
        np.testing.assert_allclose(_canonical(env, env.sym.qpos(q)), _canonical(env, expect), atol=1e-7)
    left_slot = np.where(a_side[:, None] > 0, pos[:, 0], pos[:, 1])
    right_slot = np.where(a_side[:, None] > 0, pos[:, 1], pos[:, 0]) * REFLECT
    for c in (0, 1):  # same marginals on both sides (sampling check of the construction)
        q = np.linspace(0.05, 0.95, 10)
        np.testing.assert_allclose(np.quantile(left_slot[:, c], q), np.quantile(right_slot[:, c], q),
                                   atol=0.012)
    # the point-cloud crop holds every bottle the distribution can place, and the targets
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    half = np.asarray(scene.body_half)
    for p in (pos[:, 0], pos[:, 1]):
        assert np.all(p[:, :2] - half[:2] >= lo[:2]) and np.all(p[:, :2] + half[:2] <= hi[:2])
    tgt = np.asarray(scene.targets())
    assert np.all(tgt + scene.bottles()[0].top_above_centre * np.array([0, 0, 1]) <= hi)
    np.testing.assert_allclose(np.asarray(qpos)[:, : env.info.nq_robot],
                               np.broadcast_to(env.home_qpos[: env.info.nq_robot], (len(keys), env.info.nq_robot)))


# ---------------------------------------------------------------------------- predicate
def _evaluate(env, qpos):
    """(success, terms) of a state built by hand on the host (no stepping)."""
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(qpos)
    mujoco.mj_forward(m, d)
    _, success, metrics = env.scene.evaluate(mjx.put_data(m, d), {}, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def _at(env, a, b):
    return np.asarray(env.scene.placed_qpos(jnp.asarray(env.home_qpos), env, a, b))


def test_success_predicate_cases(env, env_faithful):
    tl, tr = (np.asarray(t, np.float64) for t in env.scene.targets())
    dz = np.array([0.0, 0.0, 1.0])
    assert _evaluate(env, _at(env, tl, tr))[0]  # both bottles at their lift targets
    assert _evaluate(env, _at(env, tr, tl))[0]  # which bottle is where does not matter
    ok, t = _evaluate(env, _at(env, tl + [0.06, 0.0, -0.04], tr + [0.0, -0.05, 0.03]))
    assert ok and abs(t["left_lift"] - 0.11) < 1e-5  # inside every tolerance
    ok, t = _evaluate(env, _at(env, tl + [0.105, 0.0, 0.0], tr))
    assert not ok and abs(t["left_target_dist"] - 0.105) < 1e-5 and t["right_done"] == 1.0
    ok, t = _evaluate(env, _at(env, tl, tr - 0.06 * dz))  # near its target, lifted only 9 cm
    assert not ok and abs(t["right_lift"] - 0.09) < 1e-5 and t["right_target_dist"] < 0.1
    assert not _evaluate(env, _at(env, tl, tr * REFLECT + [0.0, 0.05, 0.0]))[0]  # both on the left
    q0, _ = env.scene.init(jax.random.key(5), env)  # where they start: on the table
    ok, t = _evaluate(env, q0)
    assert not ok and abs(t["left_lift"]) < 1e-6 and abs(t["right_lift"]) < 1e-6
    # one bottle lifted to its target, the other still on the table
    pos = np.asarray(env.scene.positions_from_qpos(q0, env))
    left = int(np.argmax(pos[:, 1]))
    a, b = (tl, pos[1]) if left == 0 else (pos[0], tl)
    ok, t = _evaluate(env, _at(env, a, b))
    assert not ok and t["left_done"] == 1.0 and t["right_done"] == 0.0
    # the faithful right bottle rests 1 cm lower: its lift counts from its own rest height
    ok, t = _evaluate(env_faithful, _at(env_faithful, tl, tr))
    assert ok and abs(t["right_lift"] - (tr[2] - 0.04)) < 1e-5


# ---------------------------------------------------------------------------- rollouts
@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_mirror_of_a_start_is_a_start(env, rollouts):
    """``env.mirror_state`` of sampled starts: bottles reflected in place, ``a_side``
    flipped, arms at home, every constraint of the distribution still met. (The point
    cloud's mirror is the env's, tested in test_env.py; rendering it here would add a
    compile of its own.)"""
    s0, _, _ = rollouts
    scene, n = env.scene, N_SEEDS
    pos = np.asarray(jax.vmap(lambda q: scene.positions_from_qpos(q, env))(s0.data.qpos))
    a_side = np.asarray(s0.info["a_side"])
    np.testing.assert_allclose(pos[n:], pos[:n] * REFLECT, atol=1e-6)
    np.testing.assert_array_equal(a_side[n:], -a_side[:n])
    np.testing.assert_array_equal(np.sign(pos[:, 0, 1]), a_side)
    np.testing.assert_array_equal(np.sign(pos[:, 1, 1]), -a_side)
    y = np.abs(pos[..., 1])
    assert np.all((y >= scene.y_range[0]) & (y <= scene.y_range[1]))
    q = np.asarray(s0.data.qpos)[:, : env.info.nq_robot]
    np.testing.assert_allclose(q, np.broadcast_to(env.home_qpos[: env.info.nq_robot], q.shape), atol=1e-6)


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_jit_reset_step_shapes_no_nan(env, rollouts):
    """Reset and step (inside the jitted rollout) give the documented shapes, finite values,
    and no success at reset."""
    s0, final, traj = rollouts
    b = 2 * N_SEEDS
    for s in (s0, final):
        assert s.obs["qpos"].shape == (b, 14)
        assert s.reward.shape == (b,) and s.done.shape == (b,)
        assert all(np.all(np.isfinite(np.asarray(v))) for v in s.obs.values())
        assert np.all(np.isfinite(np.asarray(s.data.qpos)))
    assert not np.any(np.asarray(s0.info["success"])) and not np.any(np.asarray(s0.reward))
    assert traj["action"].shape[::2] == (b, 14) and traj["success"].shape == traj["action"].shape[:2]
    assert np.all(np.isfinite(traj["action"])) and np.all(np.isfinite(traj["qpos"]))
    assert np.all(np.asarray(final.info["step"]) == traj["action"].shape[1])
    assert not np.any(np.asarray(final.metrics["nan_action"]))


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_success_and_grasp(env, rollouts):
    s0, final, traj = rollouts
    success = np.asarray(final.info["success"])
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    print(f"\nexpert success {success.sum()}/{success.size}, a_side {np.asarray(s0.info['a_side'])}, "
          f"first success step {first}")
    assert success.sum() >= success.size - 1
    # both grasps held by friction: each bottle rose by more than 10 cm and stayed upright
    qadr = env.scene._ids(env)["qadr"]
    for a in qadr:
        lift = traj["qpos"][:, :, a + 2].max(axis=1) - np.asarray(s0.data.qpos)[:, a + 2]
        assert np.all(lift > 0.1), lift
    assert np.all(np.asarray(final.metrics["min_upright"]) > np.cos(np.radians(15)))


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(env, rollouts):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored bottle trajectories."""
    _, _, traj = rollouts
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    qadr = env.scene._ids(env)["qadr"]
    pos = np.stack([traj["qpos"][..., a : a + 3] for a in qadr], axis=2)  # [2N, T, 2, 3]
    pos_err = np.abs(pos[n:] - pos[:n] * REFLECT).max()
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; "
          f"max bottle position error = {pos_err * 1000:.3f} mm over {acts.shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the arms' roles swapped: the check is not vacuous
    assert act_err < 1e-3
    assert pos_err < 5e-3


@pytest.mark.slow  # needs the module's expert-rollout compile; CI runs it with the slow suite
def test_arms_stay_on_their_own_sides(env, rollouts):
    """The arms never collide: at every 3rd step every geom of the left arm (links, palm,
    pads; by its bounding sphere) lies wholly in y > 0 and every right-arm geom in y < 0."""
    _, _, traj = rollouts
    m = env.mj_model
    d = mujoco.MjData(m)
    arm_geoms = []
    for side in ("left", "right"):
        root = m.body(f"{side}_base").id
        bodies = {b for b in range(m.nbody) if _has_ancestor(m, b, root)}
        arm_geoms.append([g for g in range(m.ngeom) if m.geom_bodyid[g] in bodies])
    gap = np.inf
    for qpos in traj["qpos"][:, ::3].reshape(-1, m.nq):
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        left = min(d.geom_xpos[g, 1] - m.geom_rbound[g] for g in arm_geoms[0])
        right = max(d.geom_xpos[g, 1] + m.geom_rbound[g] for g in arm_geoms[1])
        gap = min(gap, left, -right)
    print(f"\nsmallest clearance of an arm geom's bounding sphere from the mirror plane: {gap * 100:.1f} cm")
    assert gap > 0.0


def _has_ancestor(m, b, root):
    while b > 0:
        if b == root:
            return True
        b = m.body_parentid[b]
    return False


@pytest.mark.slow
def test_faithful_expert_succeeds(env_faithful):
    """With two different bottles (not mirror-symmetric) the expert, which reads each
    bottle's size from the scene, still lifts both."""
    expert = make_expert(env_faithful)
    roll = jax.jit(jax.vmap(make_rollout(env_faithful, expert, length=expert.horizon, obs=False)))
    final, traj = roll(jax.random.split(jax.random.key(7), 3))
    success = np.asarray(final.info["success"])
    print(f"\nfaithful variant: expert success {success.sum()}/{success.size}; right lift "
          f"{np.round(np.asarray(final.metrics['right_lift']), 3)}")
    assert np.all(success)
