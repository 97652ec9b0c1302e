"""Noise or clean-sample prediction for a diffusion policy on end-effector actions.

Trains a ``table1`` end-effector preset (``dp3_pc_ee`` by default, or ``dp_image_ee``;
baseline arm: plain BC) on one task's demos in four variants and reports how well each
fits its own training windows:

* ``joint/epsilon``: joint actions, noise prediction (the DP3 joint row's setting);
* ``joint/sample``: joint actions, clean-sample prediction (the DP image joint row's);
* ``ee/epsilon``: end-effector actions, noise prediction;
* ``ee/sample``: end-effector actions, clean-sample prediction (what both EE rows use).

The two joint variants separate the prediction type from the action space. All four
read the preset's observations (``ee`` + point cloud, or ``ee`` + image). Per variant: the BC loss per logged dispatch (not comparable between the two prediction types:
different targets), and the open-loop error of DDIM samples on ``windows`` training
windows per action channel, in normalised units (comparable across variants), plus the
action channels that are constant in the data. Run::

    python -m equibim_jax.experiments.prediction_check --task beat_block_hammer \\
        --steps 1500 --out docs/results/ee_prediction.json
    python -m equibim_jax.experiments.prediction_check --preset dp_image_ee \\
        --task beat_block_hammer --steps 1500 --out docs/results/ee_prediction_dp_image.json
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import shutil
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from equibim_jax._io import atomic_write_json

VARIANTS = (("joint", "epsilon"), ("joint", "sample"), ("ee", "epsilon"), ("ee", "sample"))
PRESETS = ("dp3_pc_ee", "dp_image_ee")


def run(task: str, steps: int = 1500, demos: int = 50, windows: int = 64, seed: int = 0,
        progress: bool = True, preset: str = "dp3_pc_ee") -> dict:
    """Generate ``demos`` expert demos of ``task`` (joint env; EE actions recorded too),
    train each variant of ``table1``'s ``preset`` for ``steps`` steps and measure it.
    Returns the JSON-able report."""
    if preset not in PRESETS:
        raise ValueError(f"prediction_check: unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    from equibim_jax.config import TaskConfig
    from equibim_jax.data.generate import generate_dataset
    from equibim_jax.data.windows import frames_from_demos, make_dataset, sample_batch
    from equibim_jax.experiments.runner import load_experiment
    from equibim_jax.training import run as trun

    cell = load_experiment("table1", only=(f"{task}/{preset}",)).cells[0]
    opts = {k: v for k, v in cell.task.options.items() if k != "action"}
    tmp = Path(tempfile.mkdtemp(prefix="prediction_check_"))
    cmd = f"python -m equibim_jax.experiments.prediction_check --task {task} --steps {steps}"
    if preset != "dp3_pc_ee":
        cmd += f" --preset {preset}"
    out = {"task": task, "preset": preset, "steps": steps, "demos": demos, "windows": windows,
           "seed": seed, "command": cmd,
           "variants": {}}
    try:
        gen_env = TaskConfig(task, {**opts, "action": "joint"}).make_env()
        data, _ = generate_dataset(gen_env, tmp / "demos.zarr", demos, seed=seed, progress=progress)
        out["constant_ee_channels"] = trun.constant_channels(data.action_ee).tolist()
        for space, pred in VARIANTS:
            name = f"{space}/{pred}"
            d = data.in_action_space(space)
            env = TaskConfig(task, {**opts, "action": space}).make_env()
            pol = dataclasses.replace(cell.policy, prediction=pred, sym_target="x0" if pred == "sample" else "eps")
            base = cell.arm_config("baseline")
            tc = dataclasses.replace(base, total_steps=steps, warmup_steps=min(base.warmup_steps, steps),
                                     steps_per_dispatch=math.gcd(steps, base.steps_per_dispatch))
            t0 = time.perf_counter()
            trun.train(d, tmp / name.replace("/", "_"), pol, tc, env=env, progress=progress, desc=name)
            wall = time.perf_counter() - t0
            r = trun.load_run(tmp / name.replace("/", "_"))
            frames, ends = frames_from_demos(d, tuple(r.policy.config.obs_keys))
            ds = make_dataset(r.normalizer.normalize(frames), ends, r.policy.config)
            batch = sample_batch(ds, jax.random.key(seed), windows)
            obs = {f: batch[f] for f in r.policy.config.obs_keys}
            a = r.policy.sample(r.state.ema_params, obs, jax.random.key(seed + 1), None)
            err = np.abs(np.asarray(a) - np.asarray(batch["action"])).mean((0, 1))
            rows = trun.read_log(tmp / name.replace("/", "_") / "train.jsonl")
            out["variants"][name] = {
                "bc": [[r_["step"], r_["bc"]] for r_ in rows],
                "open_loop_abs_err_normalized": err.tolist(),
                "open_loop_abs_err_mean": float(err.mean()),
                "wall_s": wall}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="beat_block_hammer")
    p.add_argument("--preset", default="dp3_pc_ee", choices=PRESETS,
                   help="table1's end-effector policy preset to check")
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--demos", type=int, default=50)
    p.add_argument("--out", default="results/ee_prediction.json")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    if a.steps < 1 or a.demos < 1:
        p.error("--steps and --demos must be positive")
    res = run(a.task, a.steps, a.demos, progress=not a.no_progress, preset=a.preset)
    atomic_write_json(Path(a.out), res)
    for name, v in res["variants"].items():
        print(f"{name:<14} final bc {v['bc'][-1][1]:.4f}  open-loop |err| (normalised) mean "
              f"{v['open_loop_abs_err_mean']:.3f}  max {max(v['open_loop_abs_err_normalized']):.3f}")
    print(f"constant EE action channels: {res['constant_ee_channels']}; wrote {a.out}")
    return res


if __name__ == "__main__":
    main()
