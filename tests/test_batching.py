"""chunked_vmap equals vmap; batches of 64 and 256 envs run as one vmap (jaxlib 0.10.2's batched
LAPACK Cholesky deadlocked there on 2 cores; Env now traces MJX with sim/_linalg.py)."""

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
    """A plain vmap of mjx.forward over 64 envs hung forever on 2 cores with LAPACK's Cholesky."""
    from equibim_jax.sim.env import Env, EnvConfig, VmapEnv
    from equibim_jax.sim.scenes import BoxScene

    venv = VmapEnv(Env(EnvConfig(obs=("qpos",)), BoxScene()))
    s = jax.jit(venv.reset)(jax.random.split(jax.random.key(0), 64))
    assert s.data.qpos.shape[0] == 64 and np.all(np.isfinite(np.asarray(s.data.qpos)))


_BATCH_256 = """
import jax, numpy as np
from equibim_jax.sim.env import Env, EnvConfig, VmapEnv
from equibim_jax.sim.scenes import BoxScene
venv = VmapEnv(Env(EnvConfig(obs=("qpos",)), BoxScene()))
s = jax.jit(venv.reset)(jax.random.split(jax.random.key(0), 256))
step = jax.jit(venv.step)
for _ in range(3):
    s = step(s, s.obs["qpos"])
q = np.asarray(s.data.qpos)
assert q.shape[0] == 256 and np.all(np.isfinite(q))
print("ok", q.shape)
"""


@pytest.mark.slow
def test_vmapenv_steps_256_envs_without_deadlock():
    """Reset and three steps of 256 robot-A envs with contacts, in a subprocess under a
    timeout: a deadlock fails the test instead of hanging the suite."""
    import subprocess
    import sys

    try:
        r = subprocess.run([sys.executable, "-c", _BATCH_256], capture_output=True, text=True, timeout=900)
    except subprocess.TimeoutExpired:
        pytest.fail("256 envs did not finish reset + 3 steps in 900 s (deadlock?)")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "ok (256," in r.stdout
