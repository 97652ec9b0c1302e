"""place_empty_cup: task registry, initial distribution, success predicate, scripted expert
(success and mirror equivariance).

The slow expert tests share one compiled rollout program, the task's
``task_rollouts.expert_episodes``: the expert from 50 seeded starts and from the mirror
images of the first 25 (so both sides are always covered), run 10 steps past the end of
its script. The same episodes serve the generic expert check (success rate, shapes, ``S`` on
the recorded demos), the point-cloud check and this file's expert checks.
"""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.place_empty_cup import PlaceEmptyCup, held_opening

from task_rollouts import N_PAIRS, assert_same_point_set, expert_fixtures

N_SEEDS = N_PAIRS  # starts kept whole in the shared expert episodes, each with its mirror image


@functools.lru_cache(maxsize=None)
def _env(side="both"):
    return make_env("place_empty_cup", side=side, obs=("qpos",))


episodes, test_expert_generic_checks = expert_fixtures("place_empty_cup")


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors():
    assert "place_empty_cup" in task_names()
    assert task_entry("place_empty_cup").expert is not None
    with pytest.raises(ValueError, match="valid tasks: .*place_empty_cup"):
        make_env("place_full_cup")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['colour'\].*valid options: .*side"):
        make_env("place_empty_cup", colour="red")
    with pytest.raises(ValueError, match="side must be one of"):
        make_env("place_empty_cup", side="middle")
    with pytest.raises(ValueError, match="unknown observation field"):
        make_env("place_empty_cup", obs=("qpos", "smell"))
    with pytest.raises(ValueError, match="unknown option"):
        make_scene("place_empty_cup", episode_length=3)  # an env option, not a scene one
    opts = task_options("place_empty_cup")
    assert {"obs", "action", "episode_length", "side", "cup_y_range"} <= set(opts)
    env = _env()
    assert env.config.episode_length == 500  # the task's step limit
    assert env.scene == PlaceEmptyCup(side="both")
    env2 = make_env("place_empty_cup", side="left", episode_length=7, obs=("qpos", "ee"))
    assert env2.config.episode_length == 7 and env2.scene.side == "left"


def test_model_is_physical_and_mirror_symmetric():
    m = _env().mj_model
    # friction grasp only: no equality constraints (welds), no mocap bodies
    assert m.neq == 0 and m.nmocap == 0
    assert m.jnt_type[m.joint("cup").id] == mujoco.mjtJoint.mjJNT_FREE
    assert abs(m.body_mass[m.body("cup").id] - 0.05) < 1e-9
    assert _env().sym.residual < 1e-6
    # the coaster's slide joints mirror as polar vectors: x keeps its sign, y flips
    sym = _env().sym
    for name, sign in (("coaster_x", 1.0), ("coaster_y", -1.0)):
        j = m.joint(name).id
        assert sym.joints[j] == j and sym.joint_signs[j] == sign


def test_initial_distribution():
    env = _env()
    scene = env.scene
    keys = jax.random.split(jax.random.key(0), 2000)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    cup, coaster = jax.vmap(lambda q: scene.positions_from_qpos(q, env))(qpos)
    cup, coaster, side = np.asarray(cup), np.asarray(coaster), np.asarray(info["side"])
    assert 0.4 < (side > 0).mean() < 0.6
    np.testing.assert_array_equal(np.sign(cup[:, 1]), side)
    np.testing.assert_array_equal(np.sign(coaster[:, 1]), side)
    assert np.all((np.abs(cup[:, 1]) >= 0.15) & (np.abs(cup[:, 1]) <= 0.30))
    assert np.all(np.abs(coaster[:, 1]) <= np.abs(cup[:, 1]) - scene.min_gap + 1e-6)  # nearer the centre
    assert np.all(np.abs(coaster[:, 1]) >= scene.coaster_y_min - 1e-6)
    np.testing.assert_allclose(cup[:, 2], scene.cup_half[2], atol=1e-6)  # resting on the table
    # The point-cloud crop holds every cup and coaster the distribution can place.
    lo, hi = (np.asarray(c) for c in scene.point_cloud_crop)
    for centre, half in ((cup, np.asarray(scene.cup_half)), (coaster, np.asarray(scene.coaster_half))):
        assert np.all(centre[:, :2] - half[:2] >= lo[:2]) and np.all(centre[:, :2] + half[:2] <= hi[:2])
        assert np.all(centre[:, 2] + half[2] <= hi[2])
    # the arms start at home
    np.testing.assert_allclose(np.asarray(qpos)[:, : env.info.nq_robot],
                               np.broadcast_to(env.home_qpos[: env.info.nq_robot], (len(keys), env.info.nq_robot)))
    # side="left" / "right" restrict the side
    for side_opt, sgn in (("left", 1.0), ("right", -1.0)):
        e = _env(side_opt)
        _, inf = jax.vmap(lambda k: e.scene.init(k, e))(keys[:16])
        assert np.all(np.asarray(inf["side"]) == sgn)


@pytest.mark.slow  # needs the shared expert episodes' compile; CI runs it with the slow suite
def test_point_cloud_sees_cup_and_coaster_and_mirrors(episodes):
    """A start's 64-point cloud (the shared episodes' first start) and its mirror image's."""
    env, s0 = episodes.env, episodes.s0
    assert env.config.n_points == 64
    pts, pts_m = np.asarray(s0.obs["point_cloud"][0]), np.asarray(s0.obs["point_cloud"][N_SEEDS])
    cup, coaster = (np.asarray(v) for v in env.scene.positions_from_qpos(s0.data.qpos[0], env))
    lo, hi = (np.asarray(c) for c in env.crop)
    assert np.all((pts >= lo - 1e-6) & (pts <= hi + 1e-6))
    near = lambda c, r: np.linalg.norm(pts[:, :2] - c[:2], axis=1) < r
    assert near(cup, 0.05).sum() >= 8 and near(coaster, 0.06).sum() >= 8
    assert np.all(near(cup, 0.05) | near(coaster, 0.06))  # nothing else at the arms' rest pose
    # The mirrored state's cloud is the reflected cloud (as a set of points; the mirror plane is y = 0).
    assert_same_point_set(pts * np.array([1.0, -1.0, 1.0]), pts_m, atol=1e-5)


# ---------------------------------------------------------------------------- predicate
def _evaluate(qpos, opening=None):
    """(success, terms) of a state built by hand on the host (no stepping)."""
    env = _env()
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(qpos)
    if opening is not None:
        for side, o in enumerate(opening):
            d.qpos[env.grip_qadr[side]] = np.asarray(env.info.gripper_ctrl(o))
    mujoco.mj_forward(m, d)
    data = mjx.put_data(m, d)
    _, success, metrics = env.scene.evaluate(data, {}, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def _placed_qpos(dx=0.0, dz=0.0, tilt_deg=0.0, side=1.0):
    env = _env()
    scene = env.scene
    q, _ = scene.init(jax.random.key(3), env)
    q = np.asarray(q).copy()
    ids = scene._ids(env)
    q[ids["coaster_qadr"]] = 0.28
    q[ids["coaster_y_qadr"]] = side * 0.08
    coaster_top = env.info.table_height + 2 * scene.coaster_half[2]
    half = np.deg2rad(tilt_deg) / 2
    quat = (np.cos(half), np.sin(half), 0.0, 0.0)  # about x
    cup = (0.28 + dx, side * 0.08, coaster_top + scene.cup_half[2] + dz)
    return np.asarray(scene.placed_qpos(jnp.asarray(q), env, cup, quat))


def test_success_predicate_cases():
    assert _evaluate(_placed_qpos())[0]  # on the coaster, upright, both grippers at home (open)
    assert _evaluate(_placed_qpos(side=-1.0))[0]
    assert _evaluate(_placed_qpos(dx=0.03, dz=0.01, tilt_deg=10.0))[0]  # inside every tolerance
    assert _evaluate(_placed_qpos(), opening=(1.0, 0.7))[0]
    ok, t = _evaluate(_placed_qpos(dx=0.04))
    assert not ok and abs(t["cup_coaster_xy"] - 0.04) < 1e-5  # beside the coaster
    assert not _evaluate(_placed_qpos(dz=0.03))[0]  # held 3 cm above it
    ok, t = _evaluate(_placed_qpos(tilt_deg=20.0))
    assert not ok and abs(t["cup_tilt_deg"] - 20.0) < 1e-3  # tipped
    # a gripper that still squeezes the cup (opening ~0.51) or is closed is not released
    held = held_opening(_env().info, 2 * _env().scene.cup_half[1])
    assert 0.45 < held < 0.6
    assert not _evaluate(_placed_qpos(), opening=(held, 1.0))[0]
    assert not _evaluate(_placed_qpos(), opening=(1.0, 0.0))[0]
    # the cup on the table where it starts
    q0, _ = _env().scene.init(jax.random.key(5), _env())
    assert not _evaluate(q0)[0]


# ---------------------------------------------------------------------------- expert
@pytest.mark.slow  # needs the shared expert episodes' compile; CI runs it with the slow suite
def test_expert_success_both_sides(episodes):
    s0, traj = episodes.s0, episodes.traj
    success = np.asarray(episodes.final.info["success"])
    side = np.asarray(s0.info["side"])
    assert set(side.tolist()) == {-1.0, 1.0}
    first = np.where(success, traj["success"].argmax(axis=1), -1)
    print(f"\nexpert success {success.sum()}/{success.size}, sides {side}, first success step {first}")
    assert success.sum() >= success.size - 1
    # the grasp held by friction: the cup rose by ~the carry lift during the transfer
    env = episodes.env
    a = env.scene._ids(env)["cup_qadr"]
    lift = traj["qpos"][:, :, a + 2].max(axis=1) - np.asarray(s0.data.qpos)[:, a + 2]
    assert np.all(lift > 0.04), lift
    # no NaN actions, nothing outside the actuator ranges
    assert np.all(np.isfinite(traj["action"]))


@pytest.mark.slow  # needs the shared expert episodes' compile; CI runs it with the slow suite
def test_expert_mirror_equivariance(episodes):
    """Mirrored start -> mirrored actions (to IK round-off) and mirrored cup trajectory."""
    env, traj = episodes.env, episodes.traj
    n = N_SEEDS
    acts, acts_m = traj["action"][:n], traj["action"][n:]
    expect = np.asarray(jax.vmap(jax.vmap(env.action_symmetry))(jnp.asarray(acts)))
    act_err = np.abs(acts_m - expect).max()
    a = env.scene._ids(env)["cup_qadr"]
    cup, cup_m = traj["qpos"][:n, :, a : a + 3], traj["qpos"][n:, :, a : a + 3]
    cup_err = np.abs(cup_m - cup * np.array([1.0, -1.0, 1.0])).max()
    print(f"\nequivariance: max |a_mirror - S a| = {act_err:.2e} rad; "
          f"max cup position error = {cup_err * 1000:.3f} mm over {acts.shape[1]} steps")
    assert np.abs(acts_m - acts).max() > 0.1  # the other arm acted: the check is not vacuous
    assert act_err < 1e-3
    assert cup_err < 5e-3
