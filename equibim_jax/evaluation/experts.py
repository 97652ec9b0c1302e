"""Scripted-expert success rates: every task's expert over seeded initial states.

:func:`expert_success` runs one task's expert for a whole episode (the task's step limit)
from ``episodes`` starts, in batched MJX, and reports the latched success rate with its
95 % Wilson interval. :func:`expert_table` does it for several tasks and writes the
results to a JSON file as each task finishes, skipping the tasks the file already holds
with the same settings, so an interrupted run resumes.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from equibim_jax._io import atomic_write_json
from equibim_jax.evaluation.stats import wilson_interval

__all__ = ["expert_success", "expert_table", "markdown_table", "parse_task_spec", "default_specs"]


def parse_task_spec(spec: str) -> tuple[str, dict[str, str]]:
    """``"task"`` or ``"task:option=value,option=value"`` -> (task, options).

    Raises:
      ValueError: a malformed option (no ``=``).
    """
    task, _, rest = spec.partition(":")
    options = {}
    for item in filter(None, (x.strip() for x in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"task spec {spec!r}: options must be option=value, got {item!r}")
        options[key.strip()] = value.strip()
    return task.strip(), options


def default_specs() -> list[str]:
    """Every registered task with an expert, then the ``robotwin_faithful=True`` variant of
    each task that has that option."""
    from equibim_jax.tasks import task_entry, task_names

    names = [n for n in task_names() if task_entry(n).expert is not None]
    return names + [f"{n}:robotwin_faithful=True" for n in names
                    if "robotwin_faithful" in task_entry(n).scene_fields]


def expert_success(task: str, episodes: int = 200, seed: int = 2024, batch: int = 25,
                   options: Mapping[str, Any] | None = None, progress: bool = True) -> dict:
    """Success rate of ``task``'s scripted expert over ``episodes`` seeded starts.

    Episode ``i`` starts from ``env.reset(keys[i])`` with
    ``keys = jax.random.split(jax.random.key(seed), episodes)`` and runs for the env's
    ``episode_length`` (the task's step limit unless ``options`` set it). Observations are
    not rendered (success does not depend on them).

    Args:
      task: a registered task with an expert.
      episodes: number of starts (>= 1).
      seed: PRNG seed of the starts.
      batch: episodes per compiled call.
      options: task options (``make_env``), e.g. ``{"side": "left"}``.
      progress: show a progress bar.

    Returns:
      ``{"success": float, "ci95": [lo, hi], "episodes": int, "successes": int,
      "seed": int, "length": int, "options": {...}, "failed": [indices],
      "side_success": {"left": float, "right": float} (when the task records a side),
      "compile_s": float, "run_s": float}``.
    """
    from equibim_jax.experts import make_rollout
    from equibim_jax.tasks import make_env, make_expert

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    opts = {"obs": ("qpos",), **dict(options or {})}
    env = make_env(task, **opts)
    expert = make_expert(env)
    length = int(env.config.episode_length)
    roll = make_rollout(env, expert, length=length, obs=False)
    batch = min(batch, episodes)

    @jax.jit
    def run(keys):
        final, _ = jax.vmap(roll)(keys)
        side = final.info.get("side", jnp.zeros(keys.shape[:1]))
        return final.info["success"], side

    keys = jax.random.split(jax.random.key(seed), episodes)
    n_pad = (-episodes) % batch
    padded = jnp.concatenate([keys, keys[:n_pad]]) if n_pad else keys
    success, side = [], []
    compile_s = None
    t0 = time.perf_counter()
    bar = tqdm(total=episodes, desc=f"expert {task}", unit="ep", disable=not progress)
    for i in range(0, padded.shape[0], batch):
        tc = time.perf_counter()
        s, sd = jax.device_get(run(padded[i : i + batch]))
        if compile_s is None:
            compile_s = time.perf_counter() - tc
            t0 = time.perf_counter()
        success.append(np.asarray(s))
        side.append(np.asarray(sd))
        bar.update(min(batch, episodes - i))
        bar.set_postfix(success=f"{np.concatenate(success)[:episodes].mean():.3f}")
    bar.close()
    run_s = time.perf_counter() - t0
    success = np.concatenate(success)[:episodes].astype(bool)
    side = np.concatenate(side)[:episodes]
    k = int(success.sum())
    lo, hi = wilson_interval(k, episodes)
    out = {
        "success": k / episodes, "ci95": [lo, hi], "episodes": int(episodes), "successes": k,
        "seed": int(seed), "length": length, "options": {k2: _jsonable(v) for k2, v in (options or {}).items()},
        "failed": np.flatnonzero(~success).tolist(),
        "compile_s": float(compile_s), "run_s": float(run_s),
    }
    if np.any(side != 0):
        out["side_success"] = {
            name: float(success[m].mean()) if m.any() else None
            for name, m in (("left", side > 0), ("right", side < 0))
        }
    return out


def _jsonable(v):
    return list(v) if isinstance(v, tuple) else v


def expert_table(tasks: Iterable[str], out: str | Path | None, episodes: int = 200, seed: int = 2024,
                 batch: int = 25, progress: bool = True) -> dict:
    """:func:`expert_success` for each of ``tasks``; results saved to ``out`` as they finish.

    Args:
      tasks: task specs, ``"task"`` or ``"task:option=value,..."`` (:func:`parse_task_spec`);
        results are keyed by the spec.
      out: JSON file ``{spec: result}``, or None. Tasks it already holds with the same
        ``episodes``, ``seed`` and options are skipped (an interrupted run resumes); the
        file is rewritten atomically after each task.
      episodes, seed, batch, progress: as :func:`expert_success`.

    Returns:
      ``{task: result}`` for every task asked for.

    Raises:
      ValueError: ``out`` exists but is not such a JSON file.
    """
    results: dict = {}
    if out is not None and Path(out).exists():
        try:
            results = json.loads(Path(out).read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{out} is not a JSON file of expert results ({e}); move it away") from None
        if not isinstance(results, dict):
            raise ValueError(f"{out} is not a JSON object of expert results; move it away")
    want: dict = {}
    for spec in tasks:
        task, opts = parse_task_spec(spec)
        old = results.get(spec)
        same = (isinstance(old, dict) and old.get("episodes") == episodes and old.get("seed") == seed
                and old.get("options", {}) == {k: _jsonable(v) for k, v in opts.items()})
        if not same:
            results[spec] = expert_success(task, episodes, seed, batch, opts, progress)
            if out is not None:
                atomic_write_json(out, results)
        want[spec] = results[spec]
    return want


def markdown_table(results: Mapping[str, Mapping]) -> str:
    """A Markdown table of :func:`expert_table` results: task, success, 95 % CI, episodes."""
    lines = ["| task | expert success | 95 % CI | steps per episode |", "|---|---|---|---|"]
    for spec, r in results.items():
        lo, hi = r["ci95"]
        task, opts = parse_task_spec(spec)
        name = f"`{task}`" + "".join(f", `{k}={v}`" for k, v in opts.items())
        lines.append(f"| {name} | {r['successes']}/{r['episodes']} ({100 * r['success']:.1f} %) "
                     f"| {100 * lo:.1f} to {100 * hi:.1f} % | {r.get('length', '')} |")
    return "\n".join(lines)
