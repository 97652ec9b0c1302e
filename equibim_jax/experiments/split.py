"""An experiment cell's closed-loop outcomes split by a property of each episode's start.

The runner's evaluations keep per-episode success for every arm and side, and episode
``i`` of a side starts from ``env.reset(k_i)`` (trained side) or its mirror image
(mirrored side), with ``k_i`` derived from the evaluation seed. This module rebuilds those
starts (resets only, no policy) and groups the recorded outcomes by one entry of the
start's ``info`` (for example the drumstick's ``side``: which side of the table the stick
lies on), so a result can be read per start condition, e.g. the side whose demos failed.
For each value it reports every arm's successes and, for each non-baseline arm, the paired
sign test against the baseline on the episodes with that value. Run::

    python -m equibim_jax.experiments.split docs/results/experiments/table3/results.json \\
        drumstick_hook/act_image_joint side --out docs/results/experiments/table3/drumstick_by_side.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np

from equibim_jax._io import atomic_write_json
from equibim_jax.config import ConfigError
from equibim_jax.evaluation.stats import paired_sign_test, wilson_interval


def start_info(task: str, options: dict, seed: int, episodes: int, key: str) -> dict[str, np.ndarray]:
    """``info[key]`` of the evaluation's starts, per side.

    The starts are those the evaluation ran: ``evaluation.rollout.episode_start`` of
    ``episode_keys(jax.random.key(seed), episodes)[i]``, unmirrored and mirrored.

    Returns:
      ``{"trained": [episodes, ...], "mirrored": [episodes, ...]}`` numpy arrays.
    Raises:
      ConfigError: the start's ``info`` has no entry ``key`` (the message lists those it has).
    """
    from equibim_jax.evaluation.rollout import episode_keys, episode_start
    from equibim_jax.tasks import make_env

    env = make_env(task, **options)
    # the start's info is the scene's draw plus the env's step and success: check the key
    # on its shapes alone, before tracing any physics
    drawn = jax.eval_shape(lambda k: env.scene.init(k, env)[1], jax.random.key(0))
    has = sorted({"step", "success", *drawn})
    if key not in has:
        raise ConfigError(f"task {task!r}: the start's info has no {key!r}; it has {has}")

    def one(k):
        s, _ = episode_start(env, k, False)
        s_m, _ = episode_start(env, k, True)
        return s.info[key], s_m.info[key]

    keys = episode_keys(jax.random.key(seed), episodes)
    tr, mi = jax.jit(jax.vmap(one))(keys)
    return {"trained": np.asarray(tr), "mirrored": np.asarray(mi)}


def split_outcomes(results: dict, cell: str, key: str, evaluation: str | None = None) -> dict:
    """Per-episode outcomes of ``cell`` grouped by ``info[key]`` of each episode's start.

    Args:
      results: a runner ``results.json`` as a dict.
      cell: the cell's name, e.g. ``"drumstick_hook/act_image_joint"``.
      key: an entry of the task's start ``info`` with one scalar per episode.
      evaluation: the evaluation distribution (default: the cell's first).
    Returns:
      ``{"cell", "evaluation", "key", "groups": {value: {"episodes": {side: n},
      "arms": {arm: {"successes", "episodes", "success", "ci95"}},
      "sign_tests": {arm: paired_sign_test(baseline, arm)}}}}``; episodes of both sides
      are pooled per value (value as a string, e.g. ``"-1.0"``).
    Raises:
      ConfigError: unknown cell or evaluation, no baseline arm, or outcomes whose count
        differs from the evaluation config's episodes.
    """
    cells, configs = results.get("cells", {}), results.get("configs", {})
    if cell not in cells or cell not in configs:
        raise ConfigError(f"no cell {cell!r} in the results; cells: {sorted(cells)}")
    cfg, res = configs[cell], cells[cell]
    evals = dict((name, opts) for name, opts in cfg["evals"])
    evaluation = evaluation or cfg["evals"][0][0]
    if evaluation not in evals or evaluation not in res["evals"]:
        raise ConfigError(f"cell {cell!r} has no evaluation {evaluation!r}; it has {sorted(evals)}")
    outcomes = res["evals"][evaluation]
    if "baseline" not in outcomes:
        raise ConfigError(f"cell {cell!r}: no baseline arm to compare against; arms {sorted(outcomes)}")
    n = int(cfg["eval"]["episodes"])
    task = cfg["task"]["name"] if isinstance(cfg["task"], dict) else cfg["task"]
    sides = [s for s in ("trained", "mirrored") if s in outcomes["baseline"]]
    per = {arm: {s: np.asarray(outcomes[arm][s]["per_episode"], bool) for s in sides} for arm in outcomes}
    for arm, d in per.items():
        for s, v in d.items():
            if v.shape != (n,):
                raise ConfigError(f"cell {cell!r}, arm {arm}, side {s}: {v.shape[0]} outcomes, "
                                  f"the evaluation config says {n} episodes")
    info = start_info(task, evals[evaluation], int(cfg["eval"]["seed"]), n, key)
    vals = {s: info[s].reshape(n, -1)[:, 0] for s in sides}
    groups = {}
    for v in np.unique(np.concatenate(list(vals.values()))):
        masks = {s: vals[s] == v for s in sides}
        succ = {arm: np.concatenate([d[s][masks[s]] for s in sides]) for arm, d in per.items()}
        arms = {}
        for arm, x in succ.items():
            k, m = int(x.sum()), int(x.size)
            arms[arm] = {"successes": k, "episodes": m, "success": k / m if m else float("nan"),
                         "ci95": list(wilson_interval(k, m)) if m else None}
        tests = {arm: paired_sign_test(succ["baseline"], x)
                 for arm, x in succ.items() if arm != "baseline" and x.size}
        groups[str(float(v))] = {"episodes": {s: int(masks[s].sum()) for s in sides},
                                 "arms": arms, "sign_tests": tests}
    return {"cell": cell, "evaluation": evaluation, "key": key, "groups": groups}


def markdown(split: dict) -> str:
    """A Markdown table of :func:`split_outcomes`: one row per value, successes per arm."""
    arms = list(next(iter(split["groups"].values()))["arms"])
    head = [f"start `{split['key']}`", "episodes (trained + mirrored)"] + arms + [
        f"{a} vs baseline: pairs won, p (one-sided)" for a in arms if a != "baseline"]
    rows = []
    for v, g in split["groups"].items():
        row = [v, " + ".join(str(x) for x in g["episodes"].values())]
        row += [f"{g['arms'][a]['successes']}/{g['arms'][a]['episodes']}" for a in arms]
        row += [f"{t['b_only']}:{t['a_only']}, {t['p_b_better']:.2g}" for t in g["sign_tests"].values()]
        rows.append(row)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path, help="an experiment's results.json")
    ap.add_argument("cell", help="cell name, e.g. drumstick_hook/act_image_joint")
    ap.add_argument("key", help="entry of the start's info, e.g. side")
    ap.add_argument("--evaluation", default=None, help="evaluation distribution (default: the cell's first)")
    ap.add_argument("--out", type=Path, default=None, help="JSON file to write (atomically)")
    args = ap.parse_args(argv)
    try:
        results = json.loads(args.results.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"cannot read {args.results}: {e}") from None
    try:
        split = split_outcomes(results, args.cell, args.key, args.evaluation)
    except ConfigError as e:
        raise SystemExit(str(e)) from None
    if args.out is not None:
        args_given = sys.argv[1:] if argv is None else argv
        atomic_write_json(args.out, {**split, "command": "python -m equibim_jax.experiments.split "
                                     + " ".join(str(a) for a in args_given)})
    print(markdown(split), end="")


if __name__ == "__main__":
    main()
