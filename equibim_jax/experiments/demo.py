"""The main experiment (``equibim demo``): baseline against +EquiBim, trained on demos of
one task configuration, tested on it and on its mirror image. Every number it reports
comes from the run."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from equibim_jax._io import atomic_write_bytes, atomic_write_json
from equibim_jax.config import (
    ConfigError,
    EvalConfig,
    TaskConfig,
    config_from_dict,
    config_to_dict,
    find_config,
    load_config,
    save_config,
)
from equibim_jax.data.generate import generate_dataset
from equibim_jax.evaluation.evaluate import evaluate_policies
from equibim_jax.evaluation.open_loop import open_loop_errors
from equibim_jax.evaluation.stats import paired_sign_test
from equibim_jax.policies import DP3Config, PolicyConfig
from equibim_jax.training.run import load_run, prepare_data, read_log, train_together
from equibim_jax.training.train_step import TrainConfig

__all__ = ["DemoConfig", "DEFAULT_CONFIG", "load_demo_config", "run_demo", "format_table", "plot_demo"]

DEFAULT_CONFIG = "tasks/place_empty_cup.json"
"""The main demo's settings (relative to the working directory or the repository root)."""


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    """Settings of the experiment; ``tasks/place_empty_cup.json`` holds the main demo's.

    Attributes:
      task: the task and its options; the demos come from its initial-state distribution
        (e.g. one side only), the mirrored evaluation from the mirror images of it.
      demos: successful expert demos to generate.
      seed: seed of demo generation and training.
      policy: the policy config (both runs use it).
      train: the +EquiBim run's settings; the baseline is the same with ``sym_weight = 0``.
      eval: closed-loop evaluation settings.
      out_dir: writes ``demo.json``, ``demo.png`` and ``demo/`` (dataset, runs) here.
    """

    task: TaskConfig = TaskConfig()
    demos: int = 48
    seed: int = 0
    policy: PolicyConfig = DP3Config()
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()
    out_dir: str = "results"

    def __post_init__(self):
        if self.demos < 1:
            raise ConfigError(f"DemoConfig.demos must be >= 1, got {self.demos}")
        if not self.train.sym_weight > 0:
            raise ConfigError("DemoConfig.train.sym_weight must be > 0 (the +EquiBim run needs L_sym)")

    def run_configs(self) -> dict[str, TrainConfig]:
        """``{"baseline": ..., "equibim": ...}``: identical but for ``L_sym``."""
        base = dataclasses.replace(self.train, sym_weight=0.0, sym_stop_gradient=False,
                                   sym_warmup_steps=0, sym_start_step=0, sym_batch_size=None,
                                   mirror_augment=False)
        return {"baseline": base, "equibim": self.train}


def load_demo_config(path: str = DEFAULT_CONFIG) -> DemoConfig:
    """Read a demo config file (the format :func:`run_demo` writes to ``demo/config.json``)."""
    p = find_config(path)
    try:
        return config_from_dict(DemoConfig, load_config(p))
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from None


RUNS = ("baseline", "equibim")
SIDES = (("trained_side", "trained"), ("mirrored_side", "mirrored"))


def run_demo(cfg: DemoConfig = DemoConfig(), command: str = "", progress: bool = True) -> dict:
    """Run the experiment; returns the results dict and writes ``demo.json`` and ``demo.png``.

    Builds the env once. Generates the demos, fits one mirror-consistent normaliser, trains
    the two policies with identical settings (seed included) that differ only in ``L_sym``,
    measures open-loop errors, and evaluates both in closed loop on the trained side and on
    the mirrored side (episode ``i`` of the mirrored side starts from the mirror image of
    episode ``i``'s initial state). Existing run folders under ``out_dir/demo`` are
    replaced: the numbers belong to this run.
    """
    import shutil

    t_start = time.perf_counter()
    out = Path(cfg.out_dir)
    work = out / "demo"
    work.mkdir(parents=True, exist_ok=True)
    save_config(work / "config.json", cfg)
    timings = {}
    env = cfg.task.make_env()

    t0 = time.perf_counter()
    demos, gen_stats = generate_dataset(env, work / "demos.zarr", cfg.demos, seed=cfg.seed,
                                        overwrite=True, progress=progress)
    timings["generate_s"] = time.perf_counter() - t0
    normalizer = prepare_data(demos, env, cfg.policy).normalizer

    results: dict = {}
    params = {}
    configs = {name: dataclasses.replace(tc, seed=cfg.seed) for name, tc in cfg.run_configs().items()}
    for name in configs:
        shutil.rmtree(work / name, ignore_errors=True)
    t0 = time.perf_counter()
    # both runs in one compiled program, each taking the steps it would take alone
    summaries = train_together(demos, {name: (work / name, tc) for name, tc in configs.items()}, cfg.policy,
                               env=env, normalizer=normalizer, progress=progress,
                               desc="train " + " + ".join(configs))
    timings["train_s"] = time.perf_counter() - t0
    policy = None
    for name, tc in configs.items():
        run = load_run(work / name)
        policy = run.policy
        params[name] = run.state.ema_params
        results[name] = {"sym_weight": tc.sym_weight, "train": summaries[name]}

    # Open-loop errors on the demos and on their mirror images: cheap, and informative
    # even where closed-loop success is 0 for everyone.
    t0 = time.perf_counter()
    ol = open_loop_errors(policy, normalizer, params, demos, env, seed=cfg.seed)
    timings["open_loop_s"] = time.perf_counter() - t0
    for name in RUNS:
        results[name]["open_loop_error"] = ol[name]

    t0 = time.perf_counter()
    ev = evaluate_policies(env, policy, normalizer, params, cfg.eval, progress=progress)
    timings["eval_s"] = time.perf_counter() - t0
    for name in RUNS:
        for label, side in SIDES:
            results[name][label] = ev[name][side]
    results["paired_sign_test"] = {
        label: paired_sign_test(ev["baseline"][side]["per_episode"], ev["equibim"][side]["per_episode"])
        for label, side in SIDES}
    timings["breakdown"] = time_breakdown(cfg, timings, gen_stats, results, ev)
    results.update({
        "task": cfg.task.name,
        "task_options": config_to_dict(cfg.task.options),
        "wall_time_s": time.perf_counter() - t_start,
        "command": command,
        "demos": {"episodes": demos.n_episodes, "steps": int(np.sum(demos.length)), **gen_stats},
        "timings": timings,
        "config": config_to_dict(cfg),
    })
    atomic_write_json(out / "demo.json", results)
    plot_demo(results, out / "demo.png", work)
    return results


def _first_call_split(first_s: float | None, total_s: float, calls: int) -> dict:
    """``{"compile_s", "run_s"}`` of a stage whose first of ``calls`` equal calls took
    ``first_s`` of ``total_s``: compile is the first call's excess over the mean of the
    others (tracing, lowering and compiling, or loading from the compile cache); with one
    call it cannot be told apart (``None``)."""
    if first_s is None or calls < 2:
        return {"compile_s": None, "run_s": None}
    steady = (total_s - first_s) / (calls - 1)
    compile_s = max(first_s - steady, 0.0)
    return {"compile_s": compile_s, "run_s": total_s - compile_s}


def time_breakdown(cfg: "DemoConfig", timings: dict, gen_stats: dict, results: dict, ev: dict) -> dict:
    """Where the demo's time went, per stage: ``{stage: {"wall_s", "compile_s", "run_s"}}``.

    Stages: ``generate``, ``train`` (both runs in one program), ``open_loop``, ``eval_<run>``. Compile time is
    estimated per stage from its first call against its later, equal-shaped calls
    (:func:`_first_call_split`): generation chunks, training dispatches, evaluation
    batches (both sides of a run share them). ``open_loop`` makes one call per run and is
    reported as wall time only.
    """
    out = {"generate": {"wall_s": timings["generate_s"],
                        **_first_call_split(gen_stats.get("first_chunk_s_incl_compile"),
                                            gen_stats["wall_s"], int(gen_stats.get("chunks", 1)))}}
    tr = results["equibim"]["train"]
    calls = -(-(int(tr["steps"]) - int(tr.get("resumed_from", 0))) // cfg.train.steps_per_dispatch)
    out["train"] = {"wall_s": timings["train_s"],
                    **_first_call_split(tr.get("first_dispatch_s_incl_compile"), tr["train_s"], calls)}
    out["open_loop"] = {"wall_s": timings["open_loop_s"], "compile_s": None, "run_s": None}
    for name in RUNS:
        batch_s = ev[name].get("trained", {}).get("batch_s", [])
        wall = float(sum(batch_s))
        out[f"eval_{name}"] = {"wall_s": wall, **_first_call_split(batch_s[0] if batch_s else None, wall,
                                                                   len(batch_s))}
    return out


def format_table(results: dict) -> str:
    """The results table per run and side.

    Columns: closed-loop success rate, its Wilson 95% interval, successes/episodes, and the
    open-loop mean absolute action error on the demos (trained side) or on their mirror
    images (mirrored side): arm joints in rad, gripper opening in [0, 1] units.
    """
    head = (f"{'policy':<10} {'side':<10} {'success':>8}  {'95% CI':<15} {'k/n':>7}"
            f"  {'arm err':>8}  {'grip err':>7}")
    lines = [head, "-" * len(head)]
    for name in RUNS:
        for label, side in SIDES:
            r = results[name][label]
            where = side
            lo, hi = r["ci95"]
            ol = results[name].get("open_loop_error", {}).get(
                "demos" if label == "trained_side" else "mirrored_demos")
            extra = f"  {ol['arm_rad']:>8.3f}  {ol['gripper']:>7.3f}" if ol else ""
            lines.append(f"{name:<10} {where:<10} {r['success']:>8.3f}  [{lo:.3f}, {hi:.3f}]  "
                         f"{r['successes']:>3}/{r['episodes']:<3}{extra}"
                         + (f"  ({r['nan_actions']} NaN actions)" if r.get("nan_actions") else ""))
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
        for name in RUNS:
            log = Path(work) / name / "train.jsonl"
            if log.exists():
                curves[name] = read_log(log)
    ncol = 3 if curves else 1
    fig, axes = plt.subplots(1, ncol, figsize=(4.2 * ncol, 3.4))
    axes = np.atleast_1d(axes)
    ax = axes[0]
    width = 0.38
    colours = {"baseline": "#888888", "equibim": "#1f77b4"}
    for j, name in enumerate(RUNS):
        rates = [results[name][lab]["success"] for lab, _ in SIDES]
        lo = [r - results[name][lab]["ci95"][0] for r, (lab, _) in zip(rates, SIDES)]
        hi = [results[name][lab]["ci95"][1] - r for r, (lab, _) in zip(rates, SIDES)]
        x = np.arange(len(SIDES)) + (j - 0.5) * width
        ax.bar(x, rates, width, yerr=[lo, hi], capsize=4, color=colours[name],
               label="+EquiBim" if name == "equibim" else "baseline")
    ax.set_xticks(np.arange(len(SIDES)), ["trained side", "mirrored side"])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate (Wilson 95%)")
    ax.set_title(f"{results.get('task', '')}: trained vs mirrored starts", fontsize=9)
    ax.legend(fontsize=8)
    if curves:
        for name, rows in curves.items():
            steps = [r["step"] for r in rows]
            axes[1].plot(steps, [r["bc"] for r in rows], color=colours[name], label=name)
            axes[2].plot(steps, [r["equiv_err"] for r in rows], color=colours[name], label=name)
        axes[1].set_title("BC loss", fontsize=9)
        axes[1].set_yscale("log")
        axes[2].set_title("relative equivariance error (EMA)", fontsize=9)
        axes[2].set_yscale("log")
        for a in axes[1:]:
            a.set_xlabel("step")
            a.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())
