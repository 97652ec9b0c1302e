"""Online against offline training on the same wall-clock budget; writes JSON.

Both arms train the same policy with the same ``TrainConfig`` and stop after the dispatch
that crosses the budget, or at the end of the file's schedule (``total_steps``), whichever
comes first (compiles included: the time a user waits). Task options, policy,
train settings and the demo count come from the task's experiment file
``tasks/<task>.json`` (for ``click_bell``: trained on the left side, ``qpos`` and a 64-point
cloud, dp3 at the demo's width, batch 32, ``L_sym`` on):

* ``offline``: ``equibim generate`` (the file's demo count), then the offline train loop
  on them;
* ``online``: ``equibim train --online`` (expert envs, on-device ring buffer and the
  update in one compiled loop), its first preload round included.

Each trained policy is then evaluated closed loop (``EvalConfig``, both sides; evaluation
time is outside the budget). An arm already in ``--out`` with the same settings is
skipped, so a rerun resumes.

    python benchmarks/online_vs_offline.py --task click_bell --budget-s 600 \\
        --out benchmarks/results/online_vs_offline_2core_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import shutil
import tempfile
import time
from pathlib import Path

import jax

from equibim_jax._io import atomic_write_json
from equibim_jax.config import EvalConfig
from equibim_jax.data.generate import generate_demos
from equibim_jax.evaluation.evaluate import evaluate_run
from equibim_jax.experiments.demo import load_demo_config
from equibim_jax.training import OnlineConfig, train
from equibim_jax.training.online import train_online


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--task", default="click_bell")
    p.add_argument("--budget-s", type=float, default=600.0)
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--env-steps", type=int, default=2, help="env steps per env per gradient step (online)")
    p.add_argument("--eval-episodes", type=int, default=32)
    p.add_argument("--arms", nargs="+", default=["offline", "online"])
    args = p.parse_args()

    cfg = load_demo_config(f"tasks/{args.task}.json")
    task, policy, demos_n = cfg.task, cfg.policy, cfg.demos
    iters = cfg.train.steps_per_dispatch
    # the file's schedule for both arms: each stops at its end or at the budget, whichever
    # comes first
    tc = cfg.train
    oc = OnlineConfig(num_envs=args.num_envs, env_steps=args.env_steps, grad_steps=1, iterations=iters)
    settings = {"task": args.task, "task_options": dict(task.options), "budget_s": args.budget_s,
                "demos": demos_n, "online": dataclasses.asdict(oc), "train": dataclasses.asdict(tc),
                "policy": f"{policy.name} from tasks/{args.task}.json", "eval_episodes": args.eval_episodes}
    out = Path(args.out)
    results = json.loads(out.read_text()) if out.exists() else {}
    if results.get("settings") != json.loads(json.dumps(settings)):
        results = {"settings": settings}
    results["machine"] = {"platform": platform.platform(), "cpus": jax.local_device_count(),
                          "jax": jax.__version__}
    ev = EvalConfig(episodes=args.eval_episodes)
    for arm in args.arms:
        if arm in results:
            print(f"{arm}: already in {out}, skipped")
            continue
        work = Path(tempfile.mkdtemp(prefix=f"ovo_{arm}_"))
        t0 = time.perf_counter()
        if arm == "offline":
            env = task.make_env()
            demos, stats = generate_demos(env, jax.random.key(cfg.seed), demos_n)
            gen_s = time.perf_counter() - t0
            s = train(demos, work / "run", policy, tc, env=env, max_wall_s=args.budget_s - gen_s)
            row = {"generate_s": gen_s, "demos": demos.n_episodes, "env_steps": int(stats["attempts"])
                   * int(demos.obs["qpos"].shape[1])}
        elif arm == "online":
            s = train_online(task, work / "run", policy, tc, oc, max_wall_s=args.budget_s)
            row = {"env_steps": s["env_steps"], "episodes": s["episodes"], "successes": s["successes"],
                   "env_steps_per_s": s["env_steps_per_s"], "train_steps_per_s": s["train_steps_per_s"],
                   "preload_s": s["preload_s"]}
        else:
            raise SystemExit(f"unknown arm {arm!r}")
        row.update(wall_s=time.perf_counter() - t0, train_steps=s["steps"],
                   first_dispatch_s_incl_compile=s["first_dispatch_s_incl_compile"],
                   final_bc=s["final"].get("bc"))
        res = evaluate_run(work / "run", ev)
        row["eval"] = {side: {k: res[side][k] for k in ("success", "ci95", "episodes")} for side in res}
        results[arm] = row
        atomic_write_json(out, results)
        shutil.rmtree(work, ignore_errors=True)
        print(f"{arm}: {row['train_steps']} steps in {row['wall_s']:.0f} s; success trained "
              f"{row['eval']['trained']['success']:.2f}, mirrored {row['eval']['mirrored']['success']:.2f}")


if __name__ == "__main__":
    main()
