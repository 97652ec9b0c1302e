"""chunked_vmap equals vmap; batches of 64 envs run (jaxlib's batched Cholesky deadlock)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax._batching import chunked_vmap


def test_chunked_vmap_matches_vmap_with_broadcast_and_pytrees():
    def f(x, w):
        return {"y": jnp.tanh(x["a"] @ w), "z": x["b"] * 2.0, "empty": jnp.zeros((0, 3))}

    rng = np.random.default_rng(0)
    xs = {"a": jnp.asarray(rng.normal(size=(12, 4))), "b": jnp.arange(12.0)}
    w = jnp.asarray(rng.normal(size=(4, 5)))
    ref = jax.vmap(f, in_axes=(0, None))(xs, w)
    out = jax.jit(chunked_vmap(f, 4, in_axes=(0, None)))(xs, w)
    for k in ref:
        assert out[k].shape == ref[k].shape
        np.testing.assert_allclose(out[k], ref[k], rtol=1e-6)
    with pytest.raises(ValueError, match="multiple"):
        chunked_vmap(f, 5, in_axes=(0, None))(xs, w)


@pytest.mark.slow  # compiles a 64-env reset (the default suite keeps its budget)
def test_vmapenv_resets_64_envs():
    """Plain vmap of mjx.forward over 64 envs hangs forever on 2 cores with jaxlib 0.10.2."""
    from equibim_jax.sim.env import Env, EnvConfig, VmapEnv
    from equibim_jax.sim.scenes import BoxScene

    venv = VmapEnv(Env(EnvConfig(obs=("qpos",)), BoxScene()))
    s = jax.jit(venv.reset)(jax.random.split(jax.random.key(0), 64))
    assert s.data.qpos.shape[0] == 64 and np.all(np.isfinite(np.asarray(s.data.qpos)))
