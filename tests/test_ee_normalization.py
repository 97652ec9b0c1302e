"""End-effector rotation entries are left unscaled by the data pipeline's normaliser.

A task that holds the gripper's orientation nearly fixed gives those entries a tiny demo
range; min-max scaling them turned small closed-loop orientation errors into inputs far
outside the training range. On test_extending's toy task with end-effector observations
and actions, built from jittered joint poses (no expert rollout to compile)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_extending import TOY_TASK, LinearConfig, make_linear

import equibim_jax as eb
from equibim_jax.data.dataset import Demos
from equibim_jax.data.normalizer import fit_normalizer
from equibim_jax.policies import register_policy
from equibim_jax.tasks import register_task
from equibim_jax.training.run import ee_rotation_mask, prepare_data, rotation_channels


@pytest.fixture(scope="module")
def ee_env_and_demos():
    register_policy("toy_linear", LinearConfig, make_linear)
    register_task(TOY_TASK)
    joint = eb.make_env("toy_close_gripper", side="left")
    env = eb.make_env("toy_close_gripper", side="left", action="ee", obs=("qpos", "ee"))
    q0 = np.asarray(jax.jit(joint.reset)(jax.random.key(0)).obs["qpos"])
    rng = np.random.default_rng(0)
    qpos = (q0 + rng.normal(0, 1e-3, (4, 12, 14))).astype(np.float32)  # orientation barely moves
    to_ee = jax.jit(jax.vmap(jax.vmap(joint.ee_action_from_joint)))
    ee = np.asarray(to_ee(qpos))
    act = np.asarray(to_ee(qpos + 0.01))
    demos = Demos(obs={"qpos": qpos, "ee": ee}, action=act, length=np.full(4, 12, np.int32),
                  success=np.ones(4, bool), meta={"task": env.task, "task_options": dict(env.task_options)})
    return env, demos


def test_rotation_mask_layout(ee_env_and_demos):
    env, _ = ee_env_and_demos
    mask = env.ee_rotation_mask()
    assert mask.shape == (env.action_size,) and mask.sum() == 2 * env.rot_dim
    one = np.r_[np.zeros(3, bool), np.ones(env.rot_dim, bool), False]
    np.testing.assert_array_equal(mask, np.r_[one, one])
    assert rotation_channels({"qpos": 14, "action": 14}, "action", "joint") == {}
    got = rotation_channels({"qpos": 14, "ee": 20, "act": 20}, "act", "ee")
    assert set(got) == {"ee", "act"}
    np.testing.assert_array_equal(got["ee"], mask)
    assert ee_rotation_mask(16).sum() == 8  # quaternion layout
    with pytest.raises(ValueError, match=r"2 \* \(3 \+ R \+ 1\) entries"):
        ee_rotation_mask(14)


def test_ee_rotation_entries_unscaled_and_mirror_consistent(ee_env_and_demos):
    env, demos = ee_env_and_demos
    cfg = LinearConfig(obs_horizon=1, pred_horizon=4, action_horizon=4, state_field="ee")
    data = prepare_data(demos, env, cfg)
    mask = env.ee_rotation_mask()
    ee = data.normalizer.fields["ee"]
    raw = demos.obs["ee"].reshape(-1, mask.size)
    for f in ("ee", "action"):
        n = data.normalizer.fields[f]
        np.testing.assert_array_equal(np.asarray(n.scale)[mask], 1.0)
        np.testing.assert_array_equal(np.asarray(n.offset)[mask], 0.0)
    plain = fit_normalizer({"ee": demos.obs["ee"]}, {"ee": env.obs_symmetry.ops["ee"]}).fields["ee"]
    assert np.asarray(plain.scale)[mask].max() > 20  # what min-max did to the rotation entries
    np.testing.assert_array_equal(np.asarray(ee.scale)[~mask], np.asarray(plain.scale)[~mask])
    # S commutes with the normaliser (the fit's mirror consistency holds with the mask)
    x = jnp.asarray(raw[:16])
    lhs = ee.normalize(env.obs_symmetry.ops["ee"](x))
    rhs = data.sym["ee"](ee.normalize(x))
    np.testing.assert_allclose(lhs, rhs, atol=1e-4)  # float32 round-off times the narrow position scales
