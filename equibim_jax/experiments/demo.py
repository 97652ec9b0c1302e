"""The README's main experiment: baseline vs +EquiBim trained on one side, tested on both.

:func:`run_demo` generates expert demos of one task on the ``train_side`` only, fits ONE
mirror-consistent normaliser, trains two diffusion policies with identical settings (seed
included) that differ only in ``L_sym``'s weight, and evaluates both in closed loop on the
trained side and on the mirrored side (episode ``i`` of the mirrored side starts from the
mirror image of episode ``i``'s initial state). Every number it reports comes from the run.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from equibim_jax._io import atomic_write_bytes, atomic_write_json
from equibim_jax.evaluation.stats import paired_sign_test
from equibim_jax.experiments.pipeline import (
    EnvSpec,
    ModelOptions,
    evaluate_policies,
    frames_from_demos,
    generate_dataset,
    load_policy,
    open_loop_errors,
    raw_symmetry,
    train_policy,
)
from equibim_jax.training import TrainConfig

__all__ = ["DemoConfig", "run_demo", "format_table", "plot_demo"]


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    """Settings of the main experiment (the README's numbers use the defaults)."""

    env: EnvSpec = EnvSpec()
    """Task and observation settings; ``env.side`` is the side the demos come from."""
    n_demos: int = 48
    """Successful expert demos (all on ``env.side``)."""
    model: ModelOptions = ModelOptions()
    batch_size: int = 32
    """Samples per step. Batch 32 for 8000 steps costs about what 64 for 5000 did and fits
    better: the baseline solved 14/32 and 16/32 on the trained side against 11/32 (README)."""
    train_steps: int = 7000
    steps_per_dispatch: int = 50
    learning_rate: float = 3e-3
    warmup_steps: int = 50
    sym_weight: float = 0.1
    """lambda of L_sym in the +EquiBim run (the baseline uses 0). Larger values over-constrain
    this small net: its BC loss stalls about 14x above the baseline's (mse at 1.0, l2 at 0.3;
    see README)."""
    sym_stop_gradient: bool = True
    """Treat S(pi(O)) in L_sym as a fixed target (only the mirrored prediction is pulled).
    The paper does not say which; at 10,000 steps (batch 64) the stop-gradient form kept the
    trained side (27/32 against 22/32 with gradients through both sides) and transferred
    13/32 against 11/32 (README). --no-sym-stop-gradient for the other."""
    sym_norm: str = "l2"
    """L_sym as the paper's unsquared per-sample norm (l2) or the squared error (mse). At
    lambda 0.1 and 5000 steps, l2 transferred 3/32 to the mirrored side, mse 0/32 (README)."""
    sym_space: str = "eps"
    """Compare the noise predictions (eps) or the clean actions they imply (x0) in L_sym."""
    sym_warmup_steps: int = 0
    """Ramp lambda linearly from 0 over this many steps (0: constant)."""
    sym_start_step: int = 0
    """L_sym's weight is 0 before this step (BC first), then as --sym-warmup-steps says."""
    sym_batch_size: int | None = 16
    """Samples of each batch that also go through the mirrored branch for L_sym (None: all).
    16 of 32 makes a +EquiBim step 21 ms instead of 27 ms on 2 cores; at 8000 steps it
    transferred as the full batch did (3/32 against 4/32 and 3/32; README, "How we got
    here")."""
    eval_episodes: int = 32
    """Closed-loop episodes per side and policy."""
    seed: int = 0
    out_dir: str = "results"
    """Writes demo.json, demo.png and demo/ (dataset, checkpoints, logs) here."""

    def __post_init__(self):
        if self.env.side not in ("left", "right"):
            raise ValueError(f"env.side (the trained side) must be left or right, got {self.env.side!r}")
        for name in ("n_demos", "batch_size", "train_steps", "steps_per_dispatch", "eval_episodes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.train_steps % self.steps_per_dispatch:
            raise ValueError(f"train_steps ({self.train_steps}) must be a multiple of "
                             f"steps_per_dispatch ({self.steps_per_dispatch})")
        if not self.sym_weight > 0:
            raise ValueError("sym_weight must be > 0 (the +EquiBim run needs L_sym)")
        if self.sym_batch_size is not None and not 1 <= self.sym_batch_size <= self.batch_size:
            raise ValueError(f"sym_batch_size ({self.sym_batch_size}) must be in [1, batch_size="
                             f"{self.batch_size}] or None (all samples)")

    def train_config(self, sym_weight: float) -> TrainConfig:
        return TrainConfig(batch_size=self.batch_size, learning_rate=self.learning_rate,
                           total_steps=self.train_steps,
                           warmup_steps=min(self.warmup_steps, self.train_steps),
                           steps_per_dispatch=self.steps_per_dispatch, sym_weight=sym_weight,
                           sym_stop_gradient=self.sym_stop_gradient and sym_weight > 0,
                           sym_norm=self.sym_norm, sym_space=self.sym_space,
                           sym_warmup_steps=min(self.sym_warmup_steps, self.train_steps) if sym_weight > 0 else 0,
                           sym_start_step=self.sym_start_step if sym_weight > 0 else 0,
                           sym_batch_size=self.sym_batch_size if sym_weight > 0 else None,
                           seed=self.seed)


RUNS = (("baseline", 0.0), ("equibim", None))
SIDES = (("trained_side", "trained"), ("mirrored_side", "mirrored"))


def run_demo(cfg: DemoConfig = DemoConfig(), command: str = "", progress: bool = True) -> dict:
    """Run the experiment; returns the results dict and writes ``demo.json`` and ``demo.png``.

    Existing run folders under ``out_dir/demo`` are replaced (the experiment always
    starts from scratch, so its numbers belong to this run).
    """
    import shutil

    from equibim_jax.data import fit_normalizer

    t_start = time.perf_counter()
    out = Path(cfg.out_dir)
    work = out / "demo"
    work.mkdir(parents=True, exist_ok=True)
    timings = {}

    # 1. Demos on the training side only.
    t0 = time.perf_counter()
    demos, gen_stats = generate_dataset(cfg.env, work / "demos.zarr", cfg.n_demos, seed=cfg.seed,
                                        overwrite=True, progress=progress)
    timings["generate_s"] = time.perf_counter() - t0

    # 2. One mirror-consistent normaliser for both runs.
    env = cfg.env.make()
    frames, _ = frames_from_demos(demos)
    fields = tuple(f for f in ("qpos", "point_cloud") if f in frames)
    normalizer = fit_normalizer({k: frames[k] for k in (*fields, "action")}, raw_symmetry(env, fields))

    # 3. Two runs, identical but for L_sym.
    results: dict = {}
    params = {}
    model = None
    for name, weight in RUNS:
        weight = cfg.sym_weight if weight is None else weight
        run_dir = work / name
        shutil.rmtree(run_dir, ignore_errors=True)
        t0 = time.perf_counter()
        summary = train_policy(demos, run_dir, cfg.model, cfg.train_config(weight),
                               normalizer=normalizer, progress=progress, desc=f"train {name}")
        timings[f"train_{name}_s"] = time.perf_counter() - t0
        model, state, _, _ = load_policy(run_dir)
        params[name] = state.ema_params
        results[name] = {"sym_weight": weight, "train": summary}

    # 4. Open-loop action error on the demos and on their mirror images (cheap, and
    #    informative even where closed-loop success is 0 for everyone).
    t0 = time.perf_counter()
    ol = open_loop_errors(model, normalizer, params, demos, env, seed=cfg.seed)
    timings["open_loop_s"] = time.perf_counter() - t0
    for name, _ in RUNS:
        results[name]["open_loop_error"] = ol[name]

    # 5. Closed loop, both sides, one compiled rollout for both parameter sets.
    t0 = time.perf_counter()
    ev = evaluate_policies(cfg.env, model, normalizer, params, cfg.eval_episodes, seed=cfg.seed + 1,
                           progress=progress)
    timings["eval_s"] = time.perf_counter() - t0
    for name, _ in RUNS:
        for label, side in SIDES:
            results[name][label] = ev[name][side]
    # Paired episodes (same initial states): exact sign test of +EquiBim against the baseline.
    results["paired_sign_test"] = {
        label: paired_sign_test(ev["baseline"][side]["per_episode"], ev["equibim"][side]["per_episode"])
        for label, side in SIDES}

    results.update({
        "task": cfg.env.task,
        "trained_side": cfg.env.side,
        "wall_time_s": time.perf_counter() - t_start,
        "command": command,
        "demos": {"episodes": demos.n_episodes, "steps": int(np.sum(demos.length)), **gen_stats},
        "timings": timings,
        "config": _plain(dataclasses.asdict(cfg)),
    })
    atomic_write_json(out / "demo.json", results)
    plot_demo(results, out / "demo.png", work)
    return results


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


def format_table(results: dict) -> str:
    """The results table per run and side.

    Columns: closed-loop success rate, its Wilson 95% interval, successes/episodes, and the
    open-loop mean absolute action error on the demos (trained side) or on their mirror
    images (mirrored side): arm joints in rad, gripper opening in [0, 1] units.
    """
    head = (f"{'policy':<10} {'side':<22} {'success':>8}  {'95% CI':<15} {'k/n':>7}"
            f"  {'arm err':>8}  {'grip err':>7}")
    lines = [head, "-" * len(head)]
    trained = results.get("trained_side", "trained")
    other = {"left": "right", "right": "left"}.get(trained, "mirrored")
    for name, _ in RUNS:
        for label, _side in SIDES:
            r = results[name][label]
            where = f"{'trained' if label == 'trained_side' else 'mirrored'} ({trained if label == 'trained_side' else other})"
            lo, hi = r["ci95"]
            ol = results[name].get("open_loop_error", {}).get(
                "demos" if label == "trained_side" else "mirrored_demos")
            extra = f"  {ol['arm_rad']:>8.3f}  {ol['gripper']:>7.3f}" if ol else ""
            lines.append(f"{name:<10} {where:<22} {r['success']:>8.3f}  [{lo:.3f}, {hi:.3f}]  "
                         f"{r['successes']:>3}/{r['episodes']:<3}{extra}")
    paired = results.get("paired_sign_test")
    if paired:
        lines.append("")
        lines.append("paired episodes, exact sign test of equibim against baseline:")
        for label, _side in SIDES:
            t = paired[label]
            lines.append(f"  {label.replace('_', ' '):<14} {t['discordant']:>2} of {t['pairs']} pairs differ, "
                         f"{t['b_only']} for equibim, {t['a_only']} for baseline: p = {t['p_b_better']:.3g} "
                         f"(equibim better, one-sided), {t['p_two_sided']:.3g} two-sided")
    return "\n".join(lines)


def plot_demo(results: dict, path: str | Path, work: str | Path | None = None) -> None:
    """Bar chart of success with Wilson intervals; training curves if the logs are there."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = {}
    if work is not None:
        for name, _ in RUNS:
            log = Path(work) / name / "train.jsonl"
            if log.exists():
                curves[name] = [json.loads(line) for line in log.read_text().splitlines() if line]
    ncol = 3 if curves else 1
    fig, axes = plt.subplots(1, ncol, figsize=(4.2 * ncol, 3.4))
    axes = np.atleast_1d(axes)
    ax = axes[0]
    width = 0.38
    colours = {"baseline": "#888888", "equibim": "#1f77b4"}
    for j, (name, _) in enumerate(RUNS):
        rates = [results[name][lab]["success"] for lab, _ in SIDES]
        lo = [r - results[name][lab]["ci95"][0] for r, (lab, _) in zip(rates, SIDES)]
        hi = [results[name][lab]["ci95"][1] - r for r, (lab, _) in zip(rates, SIDES)]
        x = np.arange(len(SIDES)) + (j - 0.5) * width
        ax.bar(x, rates, width, yerr=[lo, hi], capsize=4, color=colours[name],
               label="+EquiBim" if name == "equibim" else "baseline")
    ax.set_xticks(np.arange(len(SIDES)), ["trained side", "mirrored side"])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate (Wilson 95%)")
    ax.set_title(f"{results.get('task', '')}: demos on the {results.get('trained_side', '')}", fontsize=9)
    ax.legend(fontsize=8)
    if curves:
        for name, rows in curves.items():
            steps = [r["step"] for r in rows]
            axes[1].plot(steps, [r["bc"] for r in rows], color=colours[name], label=name)
            axes[2].plot(steps, [r["equiv_err"] for r in rows], color=colours[name], label=name)
        axes[1].set_title("BC (eps-MSE) loss", fontsize=9)
        axes[1].set_yscale("log")
        axes[2].set_title("relative equivariance error of eps (EMA)", fontsize=9)
        axes[2].set_yscale("log")
        for a in axes[1:]:
            a.set_xlabel("step")
            a.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())
