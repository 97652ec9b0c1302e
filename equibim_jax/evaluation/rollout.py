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
from tqdm.auto import tqdm

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
      ``rollout(params, key, mirrored=False)`` -> ``{"success": [] bool (latched), "side": [],
      "success_t": [n_chunks * Ta] bool, "final_qpos": [nq]}``. ``vmap`` over keys for a
      batch. ``mirrored`` (a bool, may be traced) starts the episode from
      ``env.mirror_state`` of the reset state instead: the same key then gives the exact
      mirror image of the initial state, so trained-side and mirrored-side evaluations can
      share one compiled function and be paired episode by episode.
    """
    cfg = model.config
    fields = tuple(cfg.encoder.keys)
    missing = [f for f in fields if f not in env.config.obs]
    if missing:
        raise ValueError(f"the policy reads {missing}, which the env does not observe ({env.config.obs})")
    to, ta = cfg.obs_horizon, cfg.action_horizon
    n_chunks = math.ceil(int(env.config.episode_length if length is None else length) / ta)

    def rollout(params, key, mirrored=False):
        k_reset, k_pol = jax.random.split(key)
        s = env.reset(k_reset)
        s_m = env.mirror_state(s)
        s = jax.tree.map(lambda a, b: jnp.where(mirrored, b, a), s, s_m)
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
             chunk: int = 32, mirrored: bool = False) -> dict:
    """Run ``n_episodes`` closed-loop episodes in chunks and summarise them.

    Returns:
      ``{"success": rate, "ci95": [lo, hi], "episodes": n, "successes": k, "wall_s": ...,
      "per_episode": [bool, ...]}`` with the Wilson 95% interval.
    """
    return evaluate_sides(rollout, params, key, n_episodes, chunk=chunk,
                          sides=("mirrored",) if mirrored else ("trained",))[
        "mirrored" if mirrored else "trained"]


_RUNNERS: dict = {}


def _runner(rollout: Callable) -> Callable:
    """One ``jit(vmap(rollout))`` per rollout function, so repeated calls reuse the compile."""
    if rollout not in _RUNNERS:
        _RUNNERS[rollout] = jax.jit(jax.vmap(rollout, in_axes=(None, 0, 0)))
    return _RUNNERS[rollout]


def summarize(successes) -> dict:
    """``{"success", "ci95", "episodes", "successes"}`` of a boolean vector (Wilson 95%)."""
    succ = np.asarray(successes, bool)
    n, k = int(succ.size), int(succ.sum())
    if n == 0:
        raise ValueError("no episodes to summarise")
    lo, hi = wilson_interval(k, n)
    return {"success": k / n, "ci95": [lo, hi], "episodes": n, "successes": k}


def evaluate_sides(rollout: Callable, params: Any, key: jax.Array, n_episodes: int,
                   chunk: int = 32, sides: tuple[str, ...] = ("trained", "mirrored"),
                   progress: bool = False, desc: str = "eval") -> dict:
    """Evaluate on the trained side and/or its mirror image with one compiled function.

    Episode ``i`` of every side uses the same key, so the mirrored episode starts from the
    exact mirror image of the trained-side episode's initial state (paired evaluation).
    Batches of at most ``chunk`` episodes (<= 32 on the CPU: see ``equibim_jax._batching``).

    Returns:
      ``{side: {"success", "ci95", "episodes", "successes", "wall_s", "per_episode",
      "first_success_step"}}``; ``first_success_step`` is -1 for failures.
    """
    bad = [s for s in sides if s not in ("trained", "mirrored")]
    if bad or not sides:
        raise ValueError(f"sides must be a non-empty subset of ('trained', 'mirrored'), got {sides}")
    if n_episodes < 1 or chunk < 1:
        raise ValueError(f"n_episodes and chunk must be >= 1, got {n_episodes}, {chunk}")
    run = _runner(rollout)
    keys = jax.random.split(key, n_episodes)
    all_keys = jnp.concatenate([keys] * len(sides))
    flags = jnp.concatenate([jnp.full((n_episodes,), s == "mirrored") for s in sides])
    total = all_keys.shape[0]
    chunk = min(chunk, total)
    pad = (-total) % chunk  # pad the last batch (same shape -> no second compile)
    all_keys = jnp.concatenate([all_keys, all_keys[:pad]])
    flags = jnp.concatenate([flags, flags[:pad]])
    t0 = time.perf_counter()
    succ, first = [], []
    with tqdm(total=total, desc=desc, unit="ep", disable=not progress) as bar:
        for i in range(0, total + pad, chunk):
            out = jax.device_get(run(params, all_keys[i : i + chunk], flags[i : i + chunk]))
            succ.append(np.asarray(out["success"]))
            st = np.asarray(out["success_t"])
            first.append(np.where(st.any(-1), st.argmax(-1), -1))
            bar.update(min(chunk, total - i))
    wall = time.perf_counter() - t0
    succ, first = np.concatenate(succ)[:total], np.concatenate(first)[:total]
    res = {}
    for j, side in enumerate(sides):
        sl = slice(j * n_episodes, (j + 1) * n_episodes)
        res[side] = {**summarize(succ[sl]), "wall_s": wall / len(sides),
                     "per_episode": succ[sl].astype(bool).tolist(),
                     "first_success_step": first[sl].astype(int).tolist()}
    return res
