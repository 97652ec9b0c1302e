"""Shared by the task test files: expert episodes from N seeded starts and their mirror images."""

import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax.experts import make_expert, make_rollout


def expert_rollouts(env, n_seeds: int, length: int, seed: int):
    """Run the task's expert for ``length`` steps from ``n_seeds`` starts, then from their
    mirror images, in one jitted batch.

    Returns:
      (initial states [2N], final states [2N], traj as numpy arrays [2N, length, ...]):
      index i < N is seed i, index N + i its mirror image.
    """
    expert = make_expert(env)
    roll = make_rollout(env, expert, length=length, obs=False)

    @jax.jit
    def starts(keys):
        s = jax.vmap(env.reset)(keys)
        sm = jax.vmap(env.mirror_state)(s)
        return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), s, sm)

    s0 = starts(jax.random.split(jax.random.key(seed), n_seeds))
    final, traj = jax.jit(jax.vmap(roll.from_state))(s0)
    return s0, final, jax.tree.map(np.asarray, traj)


def collides(m, g1: int, g2: int) -> bool:
    """Whether MuJoCo's contype/conaffinity filter lets geoms g1 and g2 collide."""
    return bool((m.geom_contype[g1] & m.geom_conaffinity[g2]) or (m.geom_contype[g2] & m.geom_conaffinity[g1]))
