"""EnvConfig.max_contacts: the K deepest contacts are kept (MJX's max_contact_points)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.sim.env import Env, EnvConfig
from equibim_jax.sim.scenes import BoxScene

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)


@pytest.mark.parametrize("bad", [0, -3, 2.5])
def test_max_contacts_must_be_a_positive_int(bad):
    with pytest.raises(ValueError, match="max_contacts"):
        EnvConfig(max_contacts=bad)


def _rest(env):
    """One program: reset from key 3, then 10 steps holding the arms' start targets. Returns
    (initial state, final state, touching contacts [10] after each step)."""

    @jax.jit
    def run(key):
        s0 = env.reset(key)
        action = s0.obs["qpos"] if s0.obs["qpos"].shape == (env.action_size,) else jnp.zeros(env.action_size)

        def body(s, _):
            s = env.step(s, action)
            return s, jnp.sum(s.data._impl.contact.dist < 0)

        s, touch = jax.lax.scan(body, s0, None, length=10)
        return s0, s, touch

    return run(jax.random.key(3))


@pytest.mark.slow  # compiles two envs' reset and step
def test_max_contacts_shrinks_the_solve_and_keeps_the_physics_while_few_touch():
    full = Env(EnvConfig(obs=("qpos",)), BoxScene())
    cut = Env(EnvConfig(obs=("qpos",), max_contacts=12), BoxScene())
    (sf0, sf, touch), (sc0, sc, _) = _rest(full), _rest(cut)
    assert sf0.data._impl.contact.dist.shape[0] > 12 and sc0.data._impl.contact.dist.shape[0] == 12
    assert sc0.data._impl.efc_J.shape[0] < sf0.data._impl.efc_J.shape[0]
    assert np.all(np.asarray(touch) <= 12)  # the box rests on the table: 4 touching contacts, fewer than 12
    np.testing.assert_allclose(np.asarray(sc.data.qpos), np.asarray(sf.data.qpos), atol=1e-4)
