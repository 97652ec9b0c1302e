"""Batched closed-loop evaluation of a diffusion policy in MJX, with action chunking.

Every ``Ta`` control steps the policy samples a ``[Tp, A]`` chunk from the last ``To``
observations (DDIM in ``lax.scan``) and the env executes ``Ta`` of them; the whole episode
is one ``lax.scan`` and episodes are ``vmap``-ed, so a batch of evaluations is one
compiled call.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax.evaluation.stats import wilson_interval
from equibim_jax.policies.diffusion import predict_action
from equibim_jax.sim.env import Env


def make_policy_rollout(env: Env, model, normalizer, length: int | None = None) -> Callable:
    """A pure ``rollout(params, key) -> dict`` of one closed-loop episode.

    Args:
      env: the task env (its observation fields must include the policy's inputs).
      model: the ``NoisePredictor`` (its ``config`` is a ``PolicyConfig``).
      normalizer: the policy's ``Normalizer``.
      length: control steps (default: the env's ``episode_length``).
    Returns:
      ``rollout(params, key)`` -> ``{"success": [] bool (latched), "side": [], "success_t":
      [n_chunks * Ta] bool, "final_qpos": [nq]}``. ``vmap`` over keys for a batch.
    """
    cfg = model.config
    fields = tuple(cfg.encoder.keys)
    missing = [f for f in fields if f not in env.config.obs]
    if missing:
        raise ValueError(f"the policy reads {missing}, which the env does not observe ({env.config.obs})")
    to, ta = cfg.obs_horizon, cfg.action_horizon
    n_chunks = math.ceil(int(length or env.config.episode_length) / ta)

    def rollout(params, key):
        k_reset, k_pol = jax.random.split(key)
        s = env.reset(k_reset)
        hist = {f: jnp.repeat(s.obs[f][None], to, axis=0) for f in fields}  # [To, ...]

        def chunk(carry, i):
            s, hist = carry
            obs = {f: v[None] for f, v in hist.items()}
            acts = predict_action(model, params, obs, jax.random.fold_in(k_pol, i), normalizer)["action"][0]

            def step(carry, a):
                s, hist = carry
                s = env.step(s, a)
                hist = {f: jnp.concatenate([hist[f][1:], s.obs[f][None]], 0) for f in fields}
                return (s, hist), s.info["success"]

            (s, hist), succ = jax.lax.scan(step, (s, hist), acts)
            return (s, hist), succ

        (s, _), succ = jax.lax.scan(chunk, (s, hist), jnp.arange(n_chunks))
        return {"success": s.info["success"], "side": s.info.get("side", jnp.zeros(())),
                "success_t": succ.reshape(-1), "final_qpos": s.data.qpos}

    return rollout


def evaluate(rollout: Callable, params: Any, key: jax.Array, n_episodes: int,
             chunk: int = 32) -> dict:
    """Run ``n_episodes`` closed-loop episodes in chunks and summarise them.

    Returns:
      ``{"success": rate, "ci95": [lo, hi], "episodes": n, "successes": k, "wall_s": ...,
      "per_episode": [bool, ...]}`` with the Wilson 95% interval.
    """
    run = jax.jit(jax.vmap(rollout, in_axes=(None, 0)))
    keys = jax.random.split(key, n_episodes)
    t0 = time.perf_counter()
    outs = []
    for i in range(0, n_episodes, chunk):
        outs.append(np.asarray(jax.device_get(run(params, keys[i : i + chunk])["success"])))
    succ = np.concatenate(outs)
    k = int(succ.sum())
    lo, hi = wilson_interval(k, n_episodes)
    return {"success": k / n_episodes, "ci95": [lo, hi], "episodes": n_episodes, "successes": k,
            "wall_s": time.perf_counter() - t0, "per_episode": succ.astype(bool).tolist()}
