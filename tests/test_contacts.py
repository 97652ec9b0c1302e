"""EnvConfig.max_contacts: the K deepest contacts are kept (MJX's max_contact_points)."""

import jax
import numpy as np
import pytest

from equibim_jax.sim.env import Env, EnvConfig
from equibim_jax.sim.scenes import BoxScene


@pytest.mark.parametrize("bad", [0, -3, 2.5])
def test_max_contacts_must_be_a_positive_int(bad):
    with pytest.raises(ValueError, match="max_contacts"):
        EnvConfig(max_contacts=bad)


@pytest.mark.slow  # compiles two envs' reset and step
def test_max_contacts_shrinks_the_solve_and_keeps_the_physics_while_few_touch():
    full = Env(EnvConfig(obs=("qpos",)), BoxScene())
    cut = Env(EnvConfig(obs=("qpos",), max_contacts=12), BoxScene())
    sf, sc = full.reset(jax.random.key(3)), cut.reset(jax.random.key(3))
    assert sf.data._impl.contact.dist.shape[0] > 12 and sc.data._impl.contact.dist.shape[0] == 12
    assert sc.data._impl.efc_J.shape[0] < sf.data._impl.efc_J.shape[0]
    step_f, step_c = jax.jit(full.step), jax.jit(cut.step)
    a = sf.obs["qpos"][: full.action_size] if full.action_size <= sf.obs["qpos"].shape[0] else None
    action = np.zeros(full.action_size, np.float32) if a is None else a
    for _ in range(10):  # the box rests on the table: 4 touching contacts, fewer than 12
        sf, sc = step_f(sf, action), step_c(sc, action)
        n_touch = int(np.sum(np.asarray(sf.data._impl.contact.dist) < 0))
        assert n_touch <= 12
    np.testing.assert_allclose(np.asarray(sc.data.qpos), np.asarray(sf.data.qpos), atol=1e-4)
