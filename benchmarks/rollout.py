"""Closed-loop rollout of a trained policy: trace, compile and run time, observing every
step or only what the policy reads.

    python benchmarks/rollout.py --run results/demo/equibim --out benchmarks/results/rollout_2core_cpu.json

For each mode, one ``jit(vmap(rollout))`` over ``--episodes`` episodes (trained side):
lowering (tracing), compile and the median of ``--repeats`` runs are timed apart, with the
persistent compilation cache off so compile times are real. The successes of both modes
are recorded too (the episodes are the same; a test checks it on a small policy).
Writes JSON; nothing here is asserted.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_compilation_cache", False)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from equibim_jax._io import atomic_write_json  # noqa: E402
from equibim_jax.evaluation.rollout import make_policy_rollout  # noqa: E402
from equibim_jax.training import load_run  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="run folder written by `equibim train` / `equibim demo`")
    p.add_argument("--out", required=True)
    p.add_argument("--episodes", type=int, default=32)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args(argv)
    run = load_run(a.run)
    state, normalizer, env = run.state, run.normalizer, run.make_env()
    keys = jax.random.split(jax.random.key(a.seed), a.episodes)
    flags = jnp.zeros(a.episodes, bool)
    rows = []
    for every in (True, False):
        fn = jax.jit(jax.vmap(make_policy_rollout(env, run.policy, normalizer, observe_every_step=every),
                              in_axes=(None, 0, 0)))
        t = time.perf_counter()
        lowered = fn.lower(state.ema_params, keys, flags)
        t1 = time.perf_counter()
        compiled = lowered.compile()
        t2 = time.perf_counter()
        runs, out = [], None
        for _ in range(a.repeats):
            t3 = time.perf_counter()
            out = jax.block_until_ready(compiled(state.ema_params, keys, flags))
            runs.append(time.perf_counter() - t3)
        rows.append({"observe_every_step": every, "lower_s": t1 - t, "compile_s": t2 - t1,
                     "run_s": float(np.median(runs)), "runs_s": runs,
                     "successes": int(np.asarray(out["success"]).sum())})
        print(rows[-1])
    res = {"benchmark": "closed-loop policy rollout (trained side)", "run": a.run,
           "jax": jax.__version__, "python": platform.python_version(), "device": jax.default_backend(),
           "config": vars(a), "rows": rows, "run_ratio_observe_needed_over_every": rows[1]["run_s"] / rows[0]["run_s"]}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(a.out, res)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
