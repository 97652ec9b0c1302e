"""Demonstration generation: the scripted expert in batched MJX, successful episodes kept.

One compiled ``jit(vmap(rollout))`` runs a chunk of episodes; Python only loops over chunks
(with a progress bar) and copies each finished chunk to the host once. Each chunk is split
over every visible device (``equibim_jax._sharding``); on several devices ``chunk`` is
rounded up to a multiple of the device count.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from equibim_jax._sharding import data_mesh, is_main_process, round_up, shard_batch, to_host
from equibim_jax.config import config_to_dict
from equibim_jax.data.dataset import Demos, save
from equibim_jax.experts import make_rollout
from equibim_jax.sim.env import Env
from equibim_jax.tasks import make_expert


def make_demo_rollout(env: Env, length: int) -> Callable:
    """The compiled batch rollout that :func:`generate_demos` runs.

    Returns:
      ``roll(keys [B]) -> (final_state, traj)``, ``jit(vmap(...))`` of the task's expert in
      ``env`` for ``length`` steps; ``traj`` holds ``obs`` (dict of [B, T, ...]),
      ``action`` [B, T, A], ``success`` [B, T] (latched), ``perturbed`` [B] (the task's
      ``info["perturbed"]``: the expert was corrupted on purpose; False for tasks without
      it) and, for a joint-action env, ``action_ee`` [B, T, A_ee]. Build it once and pass it to :func:`generate_demos` to
      reuse the compiled program.
    """
    expert = make_expert(env)
    base = make_rollout(env, expert, length=int(length), obs=True)
    record_ee = env.config.action == "joint"

    def rollout(k):
        final, traj = base(k)
        traj = {**traj, "perturbed": jnp.asarray(final.info.get("perturbed", False), bool)}
        if record_ee:  # the same actions in the end-effector space
            traj = {**traj, "action_ee": env.ee_action_from_joint(traj["action"])}
        return final, traj

    roll = jax.jit(jax.vmap(rollout))
    roll.length = int(length)  # type: ignore[attr-defined]
    return roll


def default_length(env: Env, tail: int = 10) -> int:
    """Rollout length of demo generation: the expert's script plus ``2 * tail`` steps,
    capped at the env's ``episode_length``. Episodes are cut ``tail`` steps after their
    first success, so simulating the rest of the step limit would be wasted."""
    return int(min(env.config.episode_length, make_expert(env).horizon + 2 * tail))


def generate_demos(
    env: Env,
    key: jax.Array,
    n_episodes: int,
    length: int | None = None,
    chunk: int = 32,
    keep_failures: bool = False,
    max_attempts: int | None = None,
    tail: int = 10,
    progress: bool = True,
    meta: dict | None = None,
    rollout: Callable | None = None,
) -> tuple[Demos, dict]:
    """Roll out the task's scripted expert until ``n_episodes`` successes are collected.

    Episodes whose expert was perturbed on purpose (the ``asymmetric_quality`` shift of the
    robot-B tasks, ``info["perturbed"]``) are kept whether or not they succeed, as the bad
    demonstrations of that shift, and count towards ``n_episodes``.

    Args:
      env: the task environment, built by ``equibim_jax.make_env`` (its ``obs`` fields
        are recorded; its task name and options go into the metadata).
      key: PRNG key; episode ``i`` uses ``fold_in(key, i)``, so the result is a pure
        function of the key and the arguments.
      n_episodes: successful episodes to keep.
      length: control steps per rollout (default: :func:`default_length`).
      chunk: episodes per compiled batch (at most ``n_episodes``), split over the devices;
        rounded up to a multiple of the device count (the extra rollouts are real attempts,
        recorded as such). The kept episodes do not depend on it: rollout ``i`` always
        starts from ``fold_in(key, i)`` and the first ``n_episodes`` successes are kept.
      keep_failures: keep failed episodes too (marked ``success=False``).
      max_attempts: stop after this many rollouts (default ``4 * n_episodes``).
      tail: steps kept after the first success (the expert's release and retreat).
      progress: show a progress bar (in process 0 only).
      meta: extra metadata stored with the dataset.
      rollout: a :func:`make_demo_rollout` of ``env`` to reuse (its length wins).
    Returns:
      ``(demos, stats)``: :class:`Demos` with ``obs`` [E, T, ...], ``action`` [E, T, A]
      and, for a joint-action env, ``action_ee`` [E, T, A_ee] (the same actions in the
      end-effector space); and stats (attempts, successes, wall/compile times). The
      metadata record which rollout indices were kept (``episode_indices``, the ``i`` of
      ``fold_in(key, i)``), which failed and were skipped (``skipped_indices``), and per
      kept episode whether it was perturbed (``perturbed``; ``Demos.success`` says whether
      it succeeded).
    Raises:
      RuntimeError: fewer than ``n_episodes`` successes within ``max_attempts``.
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    if rollout is None:
        rollout = make_demo_rollout(env, int(length or default_length(env, tail)))
    roll = rollout
    t_len = int(roll.length)
    record_ee = env.config.action == "joint"
    max_attempts = max_attempts or 4 * n_episodes
    mesh = data_mesh()
    chunk = round_up(min(chunk, n_episodes), mesh)
    kept: list[dict] = []
    skipped: list[int] = []
    attempts = successes = 0
    t0 = time.perf_counter()
    compile_s = None
    bar = tqdm(total=n_episodes, desc="demos", unit="ep", disable=not (progress and is_main_process()))
    while len(kept) < n_episodes and attempts < max_attempts:
        idx = jnp.arange(attempts, attempts + chunk)
        keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)
        tc = time.perf_counter()
        _, traj = roll(shard_batch(keys, mesh))
        traj = to_host(traj)
        if compile_s is None:
            compile_s = time.perf_counter() - tc
        attempts += chunk
        succ = np.asarray(traj["success"])  # [B, T] latched
        pert = np.asarray(traj["perturbed"])  # [B]
        for b in range(chunk):
            ok = bool(succ[b, -1])
            successes += ok
            if len(kept) >= n_episodes:
                continue
            if not (ok or keep_failures or pert[b]):
                skipped.append(attempts - chunk + b)
                continue
            first = int(np.argmax(succ[b])) if ok else t_len - 1
            n = min(t_len, first + 1 + tail)
            kept.append({
                "obs": {k: v[b] for k, v in traj["obs"].items()}, "action": traj["action"][b],
                "action_ee": traj["action_ee"][b] if record_ee else None,
                "length": n, "success": ok, "index": attempts - chunk + b,
                "perturbed": bool(pert[b]),
            })
            bar.update(1)
        bar.set_postfix(success_rate=f"{successes / attempts:.2f}")
    bar.close()
    if len(kept) < n_episodes:
        raise RuntimeError(
            f"only {len(kept)} successful episodes in {attempts} attempts "
            f"(expert success rate {successes / max(attempts, 1):.2f}); raise max_attempts"
        )
    horizon = max(k["length"] for k in kept)
    obs = {f: np.stack([k["obs"][f][:horizon] for k in kept]) for f in kept[0]["obs"]}
    demos = Demos(
        obs=obs,
        action=np.stack([k["action"][:horizon] for k in kept]).astype(np.float32),
        length=np.array([k["length"] for k in kept], np.int32),
        success=np.array([k["success"] for k in kept]),
        meta={"task": env.task, "task_options": config_to_dict(env.task_options),
              "episode_indices": [k["index"] for k in kept], "skipped_indices": skipped,
              "attempts": attempts, "action_space": env.config.action,
              "perturbed": [k["perturbed"] for k in kept], **(meta or {})},
        action_ee=(np.stack([k["action_ee"][:horizon] for k in kept]).astype(np.float32)
                   if record_ee else None),
    )
    wall = time.perf_counter() - t0
    stats = {"attempts": attempts, "successes": successes, "success_rate": successes / attempts,
             "wall_s": wall, "first_chunk_s_incl_compile": compile_s, "chunks": attempts // chunk,
             "kept": len(kept),
             "skipped": len(skipped), "perturbed": sum(k["perturbed"] for k in kept)}
    return demos, stats


def generate_dataset(env: Env, out: str | Path, n_episodes: int, seed: int = 0, chunk: int = 32,
                     overwrite: bool = False, progress: bool = True) -> tuple[Demos, dict]:
    """Generate ``n_episodes`` successful expert demos in ``env`` and save them (zarr).

    Episodes run in equal batches of at most ``chunk`` that cover ``n_episodes`` (48 -> 2 x 24, not 2 x 32, since
    the expert rarely fails and a padded last batch would mostly simulate spares). The
    dataset at ``out`` is written atomically; an existing one is only replaced with
    ``overwrite=True``. The metadata records the task, its resolved options and ``seed``,
    so training and evaluation rebuild the same env.

    Returns:
      ``(demos, stats)`` as :func:`generate_demos`.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite=True (--overwrite) to replace it")
    chunk = max(1, min(int(chunk), int(n_episodes)))
    chunk = math.ceil(int(n_episodes) / math.ceil(int(n_episodes) / chunk))
    demos, stats = generate_demos(env, jax.random.key(seed), n_episodes, chunk=chunk,
                                  progress=progress, meta={"seed": int(seed)})
    save(demos, out, overwrite=overwrite)
    return demos, stats


def env_from_meta(meta: dict) -> Env:
    """Rebuild the env a dataset was generated in, from its metadata (task and options).

    Raises:
      DatasetError: the metadata lack the task or its options.
    """
    from equibim_jax.data.dataset import DatasetError
    from equibim_jax.tasks import make_env

    if "task" not in meta or not isinstance(meta.get("task_options"), dict):
        raise DatasetError("dataset metadata has no 'task' and 'task_options' (not written by "
                           "equibim generate?)")
    try:
        return make_env(meta["task"], **meta["task_options"])
    except ValueError as e:
        raise DatasetError(f"dataset metadata do not describe a valid env: {e}") from None
