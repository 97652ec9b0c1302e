"""Tables and plots of an experiment's results (:func:`equibim_jax.experiments.runner.run_experiment`).

Every success rate is printed as ``k/n`` with its Wilson 95% interval; every arm other than
the baseline gets the exact paired sign test against the baseline on the same episodes
(one-sided p that the arm is better). The paper's numbers, where the experiment file gives
them, are printed beside ours for comparison, never mixed into them.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from equibim_jax._io import atomic_write_bytes
from equibim_jax.evaluation.stats import wilson_interval

__all__ = ["summarize", "markdown", "plot"]

SIDES = ("trained", "mirrored")


def _rows(results: dict):
    """``(cell, label, side, {arm: summary})`` for every evaluation of every cell."""
    for cname, cell in results["cells"].items():
        for label, ev in cell["evals"].items():
            for side in SIDES:
                if all(side in ev.get(a, {}) for a in results["arms"]):
                    yield cname, label, side, {a: ev[a][side] for a in results["arms"]}


def summarize(results: dict) -> dict:
    """The view's aggregate: for ``view == "average"``, per policy preset, arm, evaluation
    label and side, the mean success rate over the preset's cells (tasks) and the pooled
    ``k/n``; otherwise per cell. ``{group: {arm: {"label/side": {"mean", "successes",
    "episodes", "cells"}}}}``."""
    out: dict = {}
    for cname, label, side, by_arm in _rows(results):
        group = results["cells"][cname]["preset"] if results.get("view") == "average" else cname
        for arm, s in by_arm.items():
            d = out.setdefault(group, {}).setdefault(arm, {}).setdefault(
                f"{label}/{side}", {"rates": [], "successes": 0, "episodes": 0})
            d["rates"].append(s["success"])
            d["successes"] += s["successes"]
            d["episodes"] += s["episodes"]
    for group in out.values():
        for arm in group.values():
            for d in arm.values():
                d["mean"] = float(np.mean(d.pop("rates")))
                d["cells"] = None
    for group, arms in out.items():
        for arm, cols in arms.items():
            for col, d in cols.items():
                d["cells"] = sum(1 for cn, c in results["cells"].items()
                                 if (c["preset"] if results.get("view") == "average" else cn) == group)
    return out


def _fmt(s: dict) -> str:
    lo, hi = s["ci95"]
    return f"{s['successes']}/{s['episodes']} ({100 * s['success']:.0f}%, {100 * lo:.0f}-{100 * hi:.0f})"


def markdown(results: dict) -> str:
    """The experiment's Markdown: the aggregate table of its view, the per-cell table with
    Wilson intervals and sign tests, and the paper's numbers."""
    arms = results["arms"]
    lines = [f"# Experiment `{results['experiment']}`" + (" (quick size)" if results.get("quick") else ""), ""]
    if results.get("description"):
        lines += [results["description"], ""]
    if results.get("quick"):
        lines += ["**Quick size: tiny models, few demos and episodes. These numbers check the "
                  "pipeline, not the method.**", ""]
    summ = results.get("summary", {})
    if results.get("view") == "average":
        lines += ["## Mean success over tasks, per policy (pooled k/n in brackets)", "",
                  "| policy | evaluation | " + " | ".join(arms) + " |", "|---|---|" + "---|" * len(arms)]
        for group, by_arm in summ.items():
            for col in by_arm[arms[0]]:
                cells = [f"{100 * by_arm[a][col]['mean']:.1f}% ({by_arm[a][col]['successes']}/"
                         f"{by_arm[a][col]['episodes']})" for a in arms]
                lines.append(f"| {group} | {col} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["## Per cell: k/n (success, Wilson 95% interval in %), paired sign test against the baseline", "",
              "| cell | evaluation | side | " + " | ".join(arms) + " | "
              + " | ".join(f"p({a} better)" for a in arms if a != "baseline") + " |",
              "|---|---|---|" + "---|" * (2 * len(arms) - 1)]
    for cname, label, side, by_arm in _rows(results):
        tests = results["cells"][cname]["sign_tests"][label]
        ps = [f"{tests[a][side]['p_b_better']:.3g} ({tests[a][side]['b_only']}:{tests[a][side]['a_only']})"
              for a in arms if a != "baseline"]
        lines.append(f"| {cname} | {label} | {side} | " + " | ".join(_fmt(by_arm[a]) for a in arms)
                     + " | " + " | ".join(ps) + " |")
    lines += ["", "p: exact one-sided sign test over the discordant paired episodes "
              "(in brackets: pairs won by the arm : pairs won by the baseline).", ""]
    paper = results.get("paper") or {}
    if paper:
        lines += [f"## The paper's numbers ({paper.get('source', 'paper')})", ""]
        if paper.get("note"):
            lines += [paper["note"], ""]
        rows = paper.get("rows", {})
        cols = sorted({k for r in rows.values() for k in r})
        lines += ["| row | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
        for name, r in rows.items():
            lines.append(f"| {name} | " + " | ".join(str(r.get(c, "")) for c in cols) + " |")
        lines.append("")
    est = results.get("full_size_estimate") or {}
    if est:
        lines += [f"Full size: about {est.get('hours_on_2_cores')} h on 2 cores ({est.get('computed_from', '')}).", ""]
    lines.append(f"Wall time of this invocation: {results.get('wall_time_s', 0):.0f} s "
                 "(finished units are skipped on a rerun; see manifest.json for each unit's own time).")
    return "\n".join(lines) + "\n"


def plot(results: dict, path: str | Path) -> None:
    """Horizontal bars of success per (cell, evaluation, side) and arm, with Wilson 95%
    intervals, written atomically as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = results["arms"]
    rows = list(_rows(results))
    n = max(len(rows), 1)
    fig, ax = plt.subplots(figsize=(7.5, 1.0 + 0.22 * n * len(arms)))
    h = 0.8 / len(arms)
    colours = plt.get_cmap("tab10")
    for j, arm in enumerate(arms):
        rate = np.array([r[3][arm]["success"] for r in rows])
        ci = np.array([r[3][arm]["ci95"] for r in rows]).reshape(-1, 2)
        y = np.arange(len(rows)) + (j - (len(arms) - 1) / 2) * h
        # Clipped at 0: intervals stored by older versions could end a rounding error inside the rate.
        err = np.clip([rate - ci[:, 0], ci[:, 1] - rate], 0.0, None) if len(rows) else None
        ax.barh(y, rate, h, xerr=err, capsize=2,
                color="#888888" if arm == "baseline" else colours(j), label=arm)
    ax.set_yticks(np.arange(len(rows)), [f"{c} | {lab} | {s}" for c, lab, s, _ in rows], fontsize=6)
    ax.invert_yaxis()
    ax.set_xlim(0, 1.05)
    ax.set_xlabel("success rate (Wilson 95% interval)")
    ax.set_title(f"{results['experiment']}" + (" (quick size)" if results.get("quick") else ""), fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())


def wilson_pct(k: int, n: int) -> tuple[float, float]:
    """Wilson 95% interval in percent."""
    lo, hi = wilson_interval(k, n)
    return 100 * lo, 100 * hi
