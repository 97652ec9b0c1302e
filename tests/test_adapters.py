"""Adapters: MuJoCo Playground's MjxEnv interface and the Gymnasium wrapper (equibim_jax.adapters).

MuJoCo Playground is not installed here (its package would add warp-lang, brax and an env
zoo to the environment; docs/data.md): the first test is a check of the ``MjxEnv``
interface written from Playground's public ``mujoco_playground/_src/mjx_env.py`` (abstract
members, properties, the ``State`` fields and their types, jit). The Gymnasium wrapper is
checked with Gymnasium's own ``gymnasium.utils.env_checker.check_env``.

One small env (click_bell, joint-state observations, a 5-step limit) is compiled once and
shared by both adapters.
"""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.adapters import playground

STEP_LIMIT = 5

# What MjxEnv declares (abstract: reset, step, xml_path, action_size, mj_model, mjx_model;
# concrete: dt, sim_dt, n_substeps, observation_size, model_assets, render, unwrapped) and
# State's fields.
MJX_ENV_METHODS = ("reset", "step", "render")
MJX_ENV_PROPERTIES = ("xml_path", "action_size", "mj_model", "mjx_model", "dt", "sim_dt", "n_substeps",
                      "observation_size", "model_assets", "unwrapped")
STATE_FIELDS = ("data", "obs", "reward", "done", "metrics", "info")


@pytest.fixture(scope="module")
def env():
    return playground.make("click_bell", step_limit=STEP_LIMIT, obs=("qpos",))


def test_playground_mjx_env_interface(env):
    for m in MJX_ENV_METHODS:
        assert callable(getattr(env, m)), m
    for p in MJX_ENV_PROPERTIES:
        assert isinstance(getattr(type(env), p, None), property), p
    assert [f.name for f in dataclasses.fields(playground.State)] == list(STATE_FIELDS)
    assert isinstance(env.mj_model, mujoco.MjModel) and isinstance(env.mjx_model, mjx.Model)
    assert isinstance(env.xml_path, str) and env.unwrapped is env
    assert env.n_substeps * env.sim_dt == pytest.approx(env.dt)
    assert env.action_size == 14 and env.observation_size == 14  # flat qpos of robot_a

    s = env.jit_reset(jax.random.PRNGKey(0))
    assert s.obs.shape == (env.observation_size,) and s.obs.dtype == jnp.float32
    for x in (s.reward, s.done):
        assert x.shape == () and x.dtype == jnp.float32
    assert float(s.reward) == 0.0 and float(s.done) == 0.0
    assert all(jnp.shape(v) == () for v in s.metrics.values()) and "success" in s.metrics
    other = env.jit_reset(jax.random.PRNGKey(1))
    assert not np.allclose(s.data.qpos, other.data.qpos)  # the key draws the episode (bell position)
    np.testing.assert_array_equal(env.jit_reset(jax.random.PRNGKey(0)).data.qpos, s.data.qpos)

    a = s.obs  # hold the current joints
    t0 = float(s.data.time)
    for i in range(STEP_LIMIT):
        assert float(s.done) == 0.0
        s = env.jit_step(s, a)
        assert int(s.info["step"]) == i + 1
    assert float(s.data.time) == pytest.approx(t0 + STEP_LIMIT * env.dt, rel=1e-4)
    assert float(s.done) == 1.0 and float(s.reward) == 0.0  # the step limit, no success
    # reward is the (latched) task success, and success ends the episode
    won = env.jit_step(env.jit_reset(jax.random.PRNGKey(0)).tree_replace({"info.success": jnp.array(True)}), a)
    assert float(won.reward) == 1.0 and float(won.done) == 1.0 and int(won.info["step"]) == 1
    assert won.tree_replace({"info.step": jnp.int32(7)}).info["step"] == 7


def test_gymnasium_wrapper_passes_check_env(env):
    gymnasium = pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import check_env

    from equibim_jax.adapters.gym import EquibimGymEnv

    g = EquibimGymEnv(env)
    check_env(g, skip_render_check=True)
    assert g.observation_space.shape == (14,) and g.action_space.shape == (14,)
    assert np.all(g.action_space.low[[6, 13]] == 0) and np.all(g.action_space.high[[6, 13]] == 1)
    o1, info = g.reset(seed=3)
    o2, _ = g.reset(seed=3)
    np.testing.assert_array_equal(o1, o2)
    assert info == {"is_success": False, "step": 0} and g.observation_space.contains(o1)
    for i in range(STEP_LIMIT):
        obs, reward, terminated, truncated, info = g.step(o1)
        assert isinstance(reward, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
        assert truncated == (i == STEP_LIMIT - 1) and not terminated
    assert isinstance(g, gymnasium.Env) and g.render() is None


@pytest.mark.slow
def test_playground_vmap_and_render(env):
    """Playground's training wrappers vmap reset and step; render ray-casts in JAX."""
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    s = jax.jit(jax.vmap(env.reset))(keys)
    s = jax.jit(jax.vmap(env.step))(s, s.obs)
    assert s.reward.shape == (3,) and s.obs.shape == (3, env.observation_size)
    img = env.render(jax.tree.map(lambda x: x[0], s), height=24, width=32)
    assert img.shape == (24, 32, 3) and img.dtype == np.uint8 and img.std() > 0
