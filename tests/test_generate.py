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
