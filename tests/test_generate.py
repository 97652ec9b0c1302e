"""Demo generation: expert rollouts kept on success, deterministic, saved and reloaded."""

import jax
import numpy as np

from equibim_jax.data.dataset import load, save
from equibim_jax.data.generate import generate_demos
from equibim_jax.tasks import make_env


def test_generate_left_demos_deterministic_and_round_trip(tmp_path):
    env = make_env("place_empty_cup", obs=("qpos", "point_cloud"), action="joint", side="left", n_points=32)
    d1, stats = generate_demos(env, jax.random.key(0), 2, chunk=2, progress=False)
    assert stats["kept"] == 2 and d1.success.all()
    # left side only (y > 0): the objects in the first point cloud sit on the left
    assert np.all(d1.obs["point_cloud"][:, 0, :, 1].mean(-1) > 0.05)
    assert d1.obs["point_cloud"].shape[2:] == (32, 3) and d1.action.shape[-1] == env.action_size
    assert np.all(d1.length < env.config.episode_length)  # cut shortly after success
    d2, _ = generate_demos(env, jax.random.key(0), 2, chunk=2, progress=False)
    np.testing.assert_array_equal(d1.action, d2.action)
    back = load(save(d1, tmp_path / "d.zarr"), expect={"task": "place_empty_cup"})
    np.testing.assert_array_equal(back.obs["qpos"], d1.obs["qpos"])
    # both action spaces are recorded and survive the round trip
    assert d1.action_spaces == ("joint", "ee") and d1.action_ee.shape == d1.action.shape[:2] + (20,)
    np.testing.assert_array_equal(back.action_ee, d1.action_ee)
    ee = back.in_action_space("ee")
    assert ee.action.shape[-1] == 20 and ee.meta["task_options"]["action"] == "ee"
    assert make_env(ee.meta["task"], **ee.meta["task_options"]).action_size == 20
    # the kept rollouts and the skipped ones are recorded
    assert len(back.meta["episode_indices"]) == 2 and back.meta["attempts"] >= 2
    assert back.meta["attempts"] == len(back.meta["episode_indices"]) + len(back.meta["skipped_indices"])
    # the ee action's gripper openings are the joint action's
    np.testing.assert_array_equal(d1.action_ee[..., [9, 19]], d1.action[..., [6, 13]])


def test_ee_action_symmetry_commutes_with_joint_to_ee():
    """S on the ee action of a joint action equals the ee action of the mirrored joint action."""
    env = make_env("place_empty_cup", obs=("qpos",), action="joint", side="both")
    rng = np.random.default_rng(0)
    home = env.home_qpos[env.arm_qadr]  # [2, n_arm]
    a = np.concatenate([home + rng.uniform(-0.6, 0.6, (64, 2, 6)), rng.uniform(0, 1, (64, 2, 1))], -1)
    a = jax.numpy.asarray(a.reshape(64, 14), jax.numpy.float32)
    lhs = env.ee_action_symmetry(env.ee_action_from_joint(a))
    rhs = env.ee_action_from_joint(env.joint_action_symmetry(a))
    np.testing.assert_allclose(np.asarray(lhs), np.asarray(rhs), atol=2e-5)
    assert float(np.abs(np.asarray(lhs) - np.asarray(env.ee_action_from_joint(a))).max()) > 0.05
    with np.testing.assert_raises(ValueError):
        env.ee_action_from_joint(a[:, :13])
