"""Batched closed-loop evaluation of any policy in MJX, with action chunking.

Every ``Ta`` control steps the policy samples a ``[Tp, A]`` chunk from the last ``To``
observations and the env executes ``Ta`` of them; the whole episode is one ``lax.scan``
and episodes are ``vmap``-ed, so a batch of evaluations is one compiled call. The mirrored
side of an evaluation starts each episode from the mirror image (``env.mirror_state``) of
the trained side's initial state, whatever the task. ACT's temporal ensembling (query
every step, average the overlapping chunks' actions) is the ``temporal_ensemble`` option
of :func:`make_policy_rollout` (:func:`ensemble_step`).

Evaluation is data-parallel: each batch of episodes is split over every visible device
(``equibim_jax._sharding``), the parameters replicated, and the batch size rounded up to a
multiple of the device count (the extra episodes are padding, dropped from the results).
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from equibim_jax._sharding import data_mesh, replicate, round_up, shard_batch, to_host
from equibim_jax.evaluation.stats import wilson_interval
from equibim_jax.policies.base import Policy, predict_action
from equibim_jax.sim.env import Env

Array = Any


def init_ensemble_buffer(n_exec: int, action_dim: int) -> tuple[Array, Array]:
    """An empty temporal-ensembling buffer for chunks of ``n_exec`` executed actions:
    ``(actions [n_exec, n_exec, A] zeros, valid [n_exec, n_exec] False)``.

    Row ``n`` holds the prediction made ``n + 1`` control steps before the next
    :func:`ensemble_step`, column ``i`` its action for that step ``+ i``.
    """
    return (jnp.zeros((n_exec, n_exec, action_dim), jnp.float32),
            jnp.zeros((n_exec, n_exec), bool))


def ensemble_step(buffer: tuple[Array, Array], new_chunk: Array, k: float | Array
                  ) -> tuple[Array, tuple[Array, Array]]:
    """One control step of ACT's temporal ensembling (pure ``jnp``, jit/vmap-able).

    Inserts ``new_chunk`` (the newest prediction, its actions for this step and the
    ``n_exec - 1`` next ones) as row 0, averages every buffered prediction for this step
    with weights ``exp(-k * i) / sum_j exp(-k * j)``, ``i = 0`` for the *oldest* of them
    (ACT's scheme: with ``k > 0`` older predictions weigh more), then shifts the buffer
    one step on (column 0 dropped, the oldest row falls out at the next insertion).

    Args:
      buffer: ``(actions [n_exec, n_exec, A], valid [n_exec, n_exec] bool)`` from
        :func:`init_ensemble_buffer` or the previous call.
      new_chunk: ``[n_exec, A]``.
      k: the weight constant (ACT uses 0.01; 0 gives the plain mean).
    Returns:
      ``(action [A], buffer)``.
    """
    acts, valid = buffer
    acts = jnp.concatenate([new_chunk[None].astype(acts.dtype), acts[:-1]], axis=0)
    valid = jnp.concatenate([jnp.ones_like(valid[:1]), valid[:-1]], axis=0)
    now, ok = acts[:, 0], valid[:, 0]  # [N, A], [N]: row n was predicted n steps ago
    # i = how many valid predictions are older than row n (0 for the oldest).
    okf = ok.astype(acts.dtype)
    i = jnp.cumsum(okf[::-1])[::-1] - okf
    logw = jnp.where(ok, -k * i, -jnp.inf)
    w = jnp.exp(logw - jnp.max(logw))  # row 0 is always valid: the max is finite
    action = jnp.sum(w[:, None] * now, axis=0) / jnp.sum(w)
    acts = jnp.concatenate([acts[:, 1:], jnp.zeros_like(acts[:, :1])], axis=1)
    valid = jnp.concatenate([valid[:, 1:], jnp.zeros_like(valid[:, :1])], axis=1)
    return action, (acts, valid)


def make_policy_rollout(env: Env, policy: Policy, normalizer, length: int | None = None,
                        mirror_noise: bool = False, record_qpos: bool = False,
                        observe_every_step: bool = False,
                        temporal_ensemble: float | None = None) -> Callable:
    """A pure ``rollout(params, key) -> dict`` of one closed-loop episode.

    Args:
      env: the task env (its observation fields must include the policy's inputs).
      policy: the :class:`~equibim_jax.policies.Policy`.
      normalizer: the policy's ``Normalizer`` (mirror-consistent: fitted with ``S``).
      length: control steps (default: the env's ``episode_length``).
      mirror_noise: on the mirrored side, draw each chunk's sampler noise ``z`` as on the
        trained side and use ``S_a z`` (a signed permutation of ``N(0, I)`` noise, so the
        same distribution). Episode ``i`` of the mirrored side is then the mirror image of
        episode ``i`` in all its randomness, and an exactly equivariant policy in
        mirror-symmetric physics repeats it move for move. ``False`` (the default) gives
        the mirrored side ``z`` itself.
      record_qpos: also return ``"qpos_t"``, ``[n_chunks * Ta, nq]`` after every step.
      observe_every_step: render the observations after every control step. By default
        only the last ``To`` steps of each chunk are observed (the policy reads nothing
        else; ``Env.step(observe=False)`` for the others): the same episode, cheaper with a
        rendered observation (``benchmarks/rollout.py`` measures it).
      temporal_ensemble: ``None`` (the default): action chunking as above. A float ``k``
        (ACT uses 0.01): ACT's temporal ensembling. The policy is queried at *every*
        control step (and every step is observed); each prediction's executed part,
        ``chunk[To - 1:]`` (``Tp - To + 1`` actions, for this step and the next ones), is
        kept in a buffer, and the action executed at step ``t`` is the weighted mean of
        all buffered predictions for step ``t``, weights ``exp(-k i)`` normalised, ``i = 0``
        the oldest prediction (:func:`ensemble_step`). The episode has the same
        ``n_chunks * Ta`` control steps; ``mirror_noise`` applies to every query.
    Returns:
      ``rollout(params, key, mirrored=False)`` -> ``{"success": [] bool (latched),
      "success_t": [n_chunks * Ta] bool, "nan_actions": [] int32 (steps whose action was
      NaN or infinite, refused by the env), "final_qpos": [nq]}``. ``vmap`` over keys for a
      batch. ``mirrored`` (a bool, may be traced) starts the episode from
      ``env.mirror_state`` of the reset state instead: the same key then gives the exact
      mirror image of the initial state, so trained-side and mirrored-side evaluations can
      share one compiled function and be paired episode by episode.
    """
    cfg = policy.config
    fields = tuple(cfg.obs_keys)
    missing = [f for f in fields if f not in env.config.obs]
    if missing:
        raise ValueError(f"the policy reads {missing}, which the env does not observe ({env.config.obs})")
    to, ta = cfg.obs_horizon, cfg.action_horizon
    n_chunks = math.ceil(int(env.config.episode_length if length is None else length) / ta)
    n_blind = 0 if observe_every_step else max(0, ta - to)
    if mirror_noise:
        from equibim_jax.data.normalizer import normalized_symmetry

        s_a = normalized_symmetry({cfg.action_key: env.action_symmetry}, normalizer,
                                  names=(cfg.action_key,))[cfg.action_key]

    if temporal_ensemble is not None:
        k_te = float(temporal_ensemble)
        if not math.isfinite(k_te):
            raise ValueError(f"temporal_ensemble must be a finite float or None, got {temporal_ensemble}")
        n_exec = cfg.pred_horizon - to + 1

        def rollout_te(params, key, mirrored=False):
            s, k_pol = episode_start(env, key, mirrored)
            hist = {f: jnp.repeat(s.obs[f][None], to, axis=0) for f in fields}  # [To, ...]
            buf = init_ensemble_buffer(n_exec, cfg.action_dim)

            def step(carry, t):
                s, hist, buf = carry
                obs = {f: v[None] for f, v in hist.items()}
                noise_op = (lambda z: jnp.where(mirrored, s_a(z), z)) if mirror_noise else None
                pred = predict_action(policy, params, obs, jax.random.fold_in(k_pol, t), normalizer,
                                      noise_op=noise_op)["action_pred"][0]
                a, buf = ensemble_step(buf, pred[to - 1 :], k_te)
                s = env.step(s, a)
                hist = {f: jnp.concatenate([hist[f][1:], s.obs[f][None]], 0) for f in fields}
                return (s, hist, buf), (s.info["success"], s.metrics["nan_action"],
                                        s.data.qpos if record_qpos else None)

            (s, _, _), (succ, nan, qpos_t) = jax.lax.scan(step, (s, hist, buf),
                                                          jnp.arange(n_chunks * ta))
            out = {"success": s.info["success"], "success_t": succ,
                   "nan_actions": jnp.sum(nan).astype(jnp.int32), "final_qpos": s.data.qpos}
            if record_qpos:
                out["qpos_t"] = qpos_t
            return out

        return rollout_te

    def rollout(params, key, mirrored=False):
        s, k_pol = episode_start(env, key, mirrored)
        hist = {f: jnp.repeat(s.obs[f][None], to, axis=0) for f in fields}  # [To, ...]

        def chunk(carry, i):
            s, hist = carry
            obs = {f: v[None] for f, v in hist.items()}
            noise_op = (lambda z: jnp.where(mirrored, s_a(z), z)) if mirror_noise else None
            acts = predict_action(policy, params, obs, jax.random.fold_in(k_pol, i), normalizer,
                                  noise_op=noise_op)["action"][0]

            def step(carry, xs):
                s, hist = carry
                a, j = xs
                s = env.step(s, a, observe=False)

                def observe(s, hist):
                    s = s.replace(obs=env.observe(s.data))
                    return s, {f: jnp.concatenate([hist[f][1:], s.obs[f][None]], 0) for f in fields}

                # Only the last To steps of a chunk are read by the next one. ``j`` is not
                # batched, so under vmap this stays a real branch: one copy of the renderer
                # in the program, run on the steps that need it.
                s, hist = jax.lax.cond(j >= n_blind, observe, lambda s, h: (s, h), s, hist)
                return (s, hist), (s.info["success"], s.metrics["nan_action"],
                                   s.data.qpos if record_qpos else None)

            (s, hist), out = jax.lax.scan(step, (s, hist), (acts, jnp.arange(ta)))
            return (s, hist), out

        (s, _), (succ, nan, qpos_t) = jax.lax.scan(chunk, (s, hist), jnp.arange(n_chunks))
        out = {"success": s.info["success"], "success_t": succ.reshape(-1),
               "nan_actions": jnp.sum(nan).astype(jnp.int32), "final_qpos": s.data.qpos}
        if record_qpos:
            out["qpos_t"] = qpos_t.reshape(-1, qpos_t.shape[-1])
        return out

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


def episode_keys(key: jax.Array, n_episodes: int) -> jax.Array:
    """The key of each evaluation episode, ``[n_episodes]``: episode ``i`` of every side
    (trained and mirrored) uses ``episode_keys(key, n)[i]``."""
    return jax.random.split(key, n_episodes)


def episode_start(env: Any, key: jax.Array, mirrored: Any = False) -> tuple[Any, jax.Array]:
    """The start of the evaluation episode with key ``key`` (one of :func:`episode_keys`) and
    its policy key: ``(state, k_policy)``. ``key`` splits into the reset key and the policy
    key; with ``mirrored`` (a bool, traced or not) the state is the mirror image of the
    trained side's start (``env.mirror_state``). Every rollout and every analysis of an
    evaluation's starts derives them here, so they cannot drift apart."""
    k_reset, k_pol = jax.random.split(key)
    s = env.reset(k_reset)
    s_m = env.mirror_state(s)
    s = jax.tree.map(lambda a, b: jnp.where(mirrored, b, a), s, s_m)
    return s, k_pol


def evaluate_sides(rollout: Callable, params: Any, key: jax.Array, n_episodes: int,
                   chunk: int = 32, sides: tuple[str, ...] = ("trained", "mirrored"),
                   progress: bool = False, desc: str = "eval") -> dict:
    """Evaluate on the trained side and/or its mirror image with one compiled function.

    Episode ``i`` of every side uses the same key, so the mirrored episode starts from the
    exact mirror image of the trained-side episode's initial state (paired evaluation).
    Batches of at most ``chunk`` episodes (<= 32 on the CPU: see ``equibim_jax._batching``).

    Returns:
      ``{side: {"success", "ci95", "episodes", "successes", "wall_s", "batch_s",
      "per_episode", "first_success_step", "nan_actions", "episodes_with_nan",
      "nan_per_episode"}}``;
      ``wall_s`` is the call's wall time split evenly over the sides, ``batch_s`` the wall
      time of each batch of the call (the first includes tracing and compiling);
      ``first_success_step`` is
      -1 for failures; ``nan_actions`` counts the steps whose action was not finite (the env
      refuses them), summed over episodes, ``nan_per_episode`` the same count per episode.
    """
    outs, wall, batch_s = _run_paired(_runner(rollout), params, key, n_episodes, chunk, sides,
                                      ("success", "success_t", "nan_actions"), progress, desc)
    res = {}
    for side in sides:
        succ, st = outs[side]["success"].astype(bool), outs[side]["success_t"]
        nan = outs[side]["nan_actions"]
        res[side] = {**summarize(succ), "wall_s": wall / len(sides), "batch_s": batch_s,
                     "per_episode": succ.tolist(),
                     "first_success_step": np.where(st.any(-1), st.argmax(-1), -1).astype(int).tolist(),
                     "nan_actions": int(nan.sum()), "episodes_with_nan": int((nan > 0).sum()),
                     "nan_per_episode": nan.astype(int).tolist()}
    return res


def _run_paired(run: Callable, params: Any, key: jax.Array, n_episodes: int, chunk: int,
                sides: tuple[str, ...], fields: tuple[str, ...], progress: bool,
                desc: str) -> tuple[dict, float, list[float]]:
    """Run ``run(params, keys [c], mirrored [c])`` (a ``jit(vmap(rollout))``) over
    ``n_episodes`` keys for each side, in padded batches of ``chunk`` (one shape, one
    compile), each split over the data mesh (``chunk`` rounded up to a multiple of the
    device count). Returns ``({side: {field: np [n_episodes, ...]}}, wall seconds, [seconds
    per batch])``."""
    bad = [s for s in sides if s not in ("trained", "mirrored")]
    if bad or not sides:
        raise ValueError(f"sides must be a non-empty subset of ('trained', 'mirrored'), got {sides}")
    if n_episodes < 1 or chunk < 1:
        raise ValueError(f"n_episodes and chunk must be >= 1, got {n_episodes}, {chunk}")
    keys = episode_keys(key, n_episodes)
    all_keys = jnp.concatenate([keys] * len(sides))
    flags = jnp.concatenate([jnp.full((n_episodes,), s == "mirrored") for s in sides])
    total = all_keys.shape[0]
    mesh = data_mesh()
    chunk = round_up(min(chunk, total), mesh)
    pad = (-total) % chunk  # pad the last batch (same shape -> no second compile)
    fill = np.arange(pad) % total  # repeats the first episodes (pad may exceed total)
    all_keys = jnp.concatenate([all_keys, all_keys[fill]])
    flags = jnp.concatenate([flags, flags[fill]])
    params = replicate(params, mesh)
    t0 = time.perf_counter()
    got = {f: [] for f in fields}
    batch_s = []
    with tqdm(total=total, desc=desc, unit="ep", disable=not progress) as bar:
        for i in range(0, total + pad, chunk):
            tb = time.perf_counter()
            batch = shard_batch((all_keys[i : i + chunk], flags[i : i + chunk]), mesh)
            out = to_host(run(params, *batch))
            batch_s.append(time.perf_counter() - tb)
            for f in fields:
                got[f].append(np.asarray(out[f]))
            bar.update(min(chunk, total - i))
    wall = time.perf_counter() - t0
    got = {f: np.concatenate(v)[:total] for f, v in got.items()}
    return {side: {f: v[j * n_episodes : (j + 1) * n_episodes] for f, v in got.items()}
            for j, side in enumerate(sides)}, wall, batch_s


def mirror_pair_gap(env: Env, policy: Policy, normalizer, params: Any, key: jax.Array, n_episodes: int,
                    chunk: int = 32, at_steps=(1, 8, 32, 128), progress: bool = False) -> dict:
    """How long the mirrored episodes stay the mirror images of the trained-side ones.

    Runs ``n_episodes`` pairs with ``mirror_noise=True`` (the mirrored episode starts from
    the mirror image of the initial state and samples with the mirrored DDIM noise), and
    compares the mirrored trajectory, mapped back by ``S``, with the trained-side one:
    ``gap(t) = max_j |S(q_mirrored(t))_j - q_trained(t)_j|`` over all ``qpos`` entries (rad
    and m). An exactly equivariant policy in mirror-symmetric physics gives ``gap = 0``
    throughout (with the test's equivariant-by-construction policy the physics keeps it
    below 1e-4 over 8 steps); a policy that breaks the symmetry drifts from the first chunk.

    Returns:
      ``{"trained", "mirrored"}`` summaries (as :func:`evaluate_sides`, with this pairing),
      ``"gap_median_at": {step: median gap over pairs}`` for ``at_steps`` (and the last
      step), ``"gap_final": [per pair]``, and ``"both", "trained_only", "mirrored_only",
      "neither"`` pair counts.
    """
    roll = make_policy_rollout(env, policy, normalizer, mirror_noise=True, record_qpos=True)
    outs, _, _ = _run_paired(jax.jit(jax.vmap(roll, in_axes=(None, 0, 0))), params, key, n_episodes,
                          chunk, ("trained", "mirrored"), ("success", "qpos_t"), progress, "mirror pairs")
    q_back = np.asarray(jax.jit(jax.vmap(jax.vmap(env.sym.qpos)))(outs["mirrored"]["qpos_t"]))
    gap = np.max(np.abs(q_back - outs["trained"]["qpos_t"]), axis=-1)  # [n_episodes, T]
    s_t = outs["trained"]["success"].astype(bool)
    s_m = outs["mirrored"]["success"].astype(bool)
    last = gap.shape[1]
    steps = sorted({int(t) for t in at_steps if 1 <= t <= last} | {last})
    return {
        "trained": {**summarize(s_t), "per_episode": s_t.tolist()},
        "mirrored": {**summarize(s_m), "per_episode": s_m.tolist()},
        "gap_median_at": {t: float(np.median(gap[:, t - 1])) for t in steps},
        "gap_final": gap[:, -1].tolist(),
        "both": int(np.sum(s_t & s_m)), "trained_only": int(np.sum(s_t & ~s_m)),
        "mirrored_only": int(np.sum(~s_t & s_m)), "neither": int(np.sum(~s_t & ~s_m)),
    }
