"""Scripted experts: pure-JAX state machines that produce demonstrations.

An expert is an :class:`Expert`: ``init(env_state) -> expert_state`` and
``act(expert_state, env_state) -> (expert_state, action [A])``, pure functions of one
environment (``vmap`` them for batches). Each task's registry entry names its expert;
``equibim_jax.make_expert(env)`` builds it. :func:`make_rollout` runs an expert in its env
inside one ``lax.scan``.

Example::

    import equibim_jax as eb
    from equibim_jax.experts import make_rollout
    env = eb.make_env("place_empty_cup", side="both")
    roll = jax.jit(jax.vmap(make_rollout(env, eb.make_expert(env), length=250)))
    final, traj = roll(jax.random.split(jax.random.key(0), 64))
"""

from __future__ import annotations

from typing import Callable

import jax

from equibim_jax.experts._waypoints import Expert
from equibim_jax.sim.env import Env, State

__all__ = ["Expert", "make_expert", "make_rollout"]


def make_expert(env: Env, **kwargs) -> Expert:
    """The scripted expert of ``env``'s task (``equibim_jax.tasks.make_expert``)."""
    from equibim_jax.tasks import make_expert as _make

    return _make(env, **kwargs)


def make_rollout(env: Env, expert: Expert, length: int | None = None,
                 obs: bool = True) -> Callable[[jax.Array], tuple[State, dict]]:
    """A pure ``rollout(key) -> (final_state, traj)`` of the expert in ``env`` (one env).

    Args:
      env: the environment.
      expert: its :class:`Expert`.
      length: control steps (default: the env's ``episode_length``).
      obs: whether to record the observations (memory: ``[T, ...]`` per field).

    Returns:
      ``rollout(key)``: ``final_state`` after ``length`` steps and ``traj``, a dict of
      ``[T, ...]`` arrays: ``action`` [T, A], ``success`` [T] (latched), ``reward`` [T],
      ``qpos`` [T, nq] (after each step), ``obs`` (dict of [T, ...], the observation
      each action was chosen from) when ``obs`` is True. ``jit``/``vmap`` it.
      ``rollout.from_state(state)`` does the same from a given initial env state (e.g.
      ``env.mirror_state(s0)``).
    """
    n = int(length if length is not None else env.config.episode_length)

    def rollout(key: jax.Array):
        """Reset from ``key`` and run the expert for ``n`` steps."""
        s0 = env.reset(key)
        return run_from(s0)

    def run_from(s0: State):
        """Run the expert for ``n`` steps from the env state ``s0``."""
        e0 = expert.init(s0)

        def body(carry, _):
            s, e = carry
            e, a = expert.act(e, s)
            s2 = env.step(s, a)
            out = {"action": a, "success": s2.info["success"], "reward": s2.reward,
                   "qpos": s2.data.qpos}
            if obs:
                out["obs"] = s.obs
            return (s2, e), out

        (s, _), traj = jax.lax.scan(body, (s0, e0), None, length=n)
        return s, traj

    rollout.from_state = run_from  # type: ignore[attr-defined]
    return rollout
