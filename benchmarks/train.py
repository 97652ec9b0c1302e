"""Benchmark the diffusion-policy train step on this machine; writes JSON.

Measures, for each variant (conv implementation x with/without the mirrored ``L_sym``
branch): compile time (apart from run time), ms per train step inside a ``lax.scan`` of
K steps and as single dispatched steps, XLA's FLOP count of one step
(``jax.jit(step).lower(...).compile().cost_analysis()``), the achieved GFLOP/s, and its
ratio to a dense fp32 2048x2048 matmul measured in the same run.

    python benchmarks/train.py --out bench_train.json

The demo's model (U-Net 32/64/128, DP3 encoder 32/64/128 on 64 points), with the package's
XLA:CPU train-step options on and off (``equibim_jax._xla_options``; each setting in its
own process):

    python benchmarks/train.py --out bench_train_demo.json --dims 32 64 128 \
        --pc-hidden 32 64 128 --num-points 64 --k 50 \
        --variants im2col:0 im2col:1 im2col:1:16 --compare-xla-tuning

A variant is ``conv_impl:mirror[:sym_batch]``: ``sym_batch`` samples of the batch go
through the mirrored branch (default all). The persistent compilation cache is turned off
so compile times are real.
"""

from __future__ import annotations

import os

os.environ["EQUIBIM_JAX_CACHE"] = "0"  # before importing equibim_jax: measure real compiles

import argparse
import dataclasses
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax

from equibim_jax._xla_options import train_compiler_options
from equibim_jax.data.normalizer import signed_permutation
from equibim_jax.data import make_dataset
from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig, make_policy
from equibim_jax.training import (
    TrainConfig,
    base_key,
    create_train_state,
    make_train_loop,
    make_train_step,
)


def _block(tree):
    return jax.block_until_ready(tree)


def matmul_gflops(n: int = 2048, repeats: int = 10) -> dict:
    """Dense fp32 ``n x n`` matmul throughput, the practical peak to compare against."""
    a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32)
    b = jax.random.normal(jax.random.key(1), (n, n), jnp.float32)
    f = jax.jit(jnp.matmul)
    _block(f(a, b))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        _block(f(a, b))
        times.append(time.perf_counter() - t)
    med = statistics.median(times)
    return {"n": n, "median_s": med, "gflops": 2 * n**3 / med / 1e9}


def synthetic_problem(args):
    """Random normalised frames, a two-arm joint swap S, and the policy/train configs."""
    a = args.action_dim
    half = a // 2
    encoder = EncoderConfig(
        pc_key="point_cloud" if args.num_points > 0 else None,
        pc_hidden=tuple(args.pc_hidden),
    )
    policy = DP3Config(
        action_dim=a,
        state_dim=a,
        obs_horizon=2,
        pred_horizon=args.horizon,
        action_horizon=8,
        encoder=encoder,
        unet=UNetConfig(down_dims=tuple(args.dims)),
    )
    rng = np.random.default_rng(0)
    f = args.frames
    frames = {
        "qpos": rng.uniform(-1, 1, (f, a)).astype(np.float32),
        "action": rng.uniform(-1, 1, (f, a)).astype(np.float32),
    }
    if args.num_points > 0:
        frames["point_cloud"] = rng.uniform(-1, 1, (f, args.num_points, 3)).astype(np.float32)
    ends = np.arange(1, f // 100 + 1) * 100
    dataset = make_dataset(frames, ends, policy)
    # Left arm <-> right arm; every other joint flips sign (a signed permutation).
    perm = np.concatenate([np.arange(half, a), np.arange(half)])
    signs = np.where(np.arange(a) % 2 == 1, -1.0, 1.0)
    joint = signed_permutation(perm, signs)
    sym = {"qpos": joint, "action": joint}
    if args.num_points > 0:
        sym["point_cloud"] = lambda p: p * jnp.array([1.0, -1.0, 1.0])
    return policy, dataset, sym


def bench_variant(args, policy, dataset, sym, conv_impl: str, mirror: bool, peak: float,
                  sym_batch: int | None = None) -> dict:
    policy = dataclasses.replace(policy, unet=dataclasses.replace(policy.unet, conv_impl=conv_impl))
    train = TrainConfig(
        batch_size=args.batch,
        sym_batch_size=sym_batch if mirror else None,
        sym_weight=0.1 if mirror else 0.0,
        sym_norm="mse",
        sym_stop_gradient=False,
        steps_per_dispatch=args.k,
        warmup_steps=10,
        total_steps=10_000 * args.k,
    )
    state = create_train_state(make_policy("dp3", policy), train)
    n_params = sum(x.size for x in jax.tree.leaves(state.params))
    key = base_key(train)
    out = {"conv_impl": conv_impl, "mirror_branch": mirror,
           "sym_batch": (sym_batch or args.batch) if mirror else 0, "params": int(n_params)}

    # Single step: AOT compile (timed), FLOPs from XLA's cost analysis.
    step = make_train_step(train, dataset, sym)
    t = time.perf_counter()
    step_c = step.lower(state, key).compile()
    out["compile_s_step"] = time.perf_counter() - t
    cost = step_c.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    flops = float(cost["flops"])
    out["gflop_per_step"] = flops / 1e9

    # K steps in one lax.scan dispatch.
    loop = make_train_loop(train, dataset, sym)
    t = time.perf_counter()
    loop_c = loop.lower(state, key).compile()
    out["compile_s_loop"] = time.perf_counter() - t

    s, _ = _block(step_c(state, key, dataset))  # warm-up run
    times = []
    for _ in range(args.repeats * args.k):
        t = time.perf_counter()
        s, m = _block(step_c(s, key, dataset))
        times.append(time.perf_counter() - t)
    out["ms_per_step_single_dispatch"] = 1e3 * statistics.median(times)

    s, _ = _block(loop_c(state, key, dataset))  # warm-up run
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        s, m = _block(loop_c(s, key, dataset))
        times.append((time.perf_counter() - t) / args.k)
    ms = 1e3 * statistics.median(times)
    out["ms_per_step_scan"] = ms
    out["ms_per_step_scan_all"] = [1e3 * x for x in times]
    out["gflops"] = flops / (ms / 1e3) / 1e9
    out["fraction_of_matmul"] = out["gflops"] / peak
    out["final_loss"] = float(m["total"][-1])
    out["loadavg_1min_after"] = os.getloadavg()[0]
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="JSON file to write")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--dims", type=int, nargs="+", default=[64, 128, 256])
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--action-dim", type=int, default=14)
    p.add_argument("--num-points", type=int, default=0, help="0: state-only observations")
    p.add_argument("--pc-hidden", type=int, nargs="+", default=[64, 128, 256],
                   help="per-point MLP widths of the point-cloud encoder")
    p.add_argument("--frames", type=int, default=2000)
    p.add_argument("--k", type=int, default=5, help="train steps per lax.scan dispatch")
    p.add_argument("--repeats", type=int, default=3, help="timed dispatches per variant")
    p.add_argument(
        "--variants",
        nargs="+",
        default=["im2col:0", "im2col:1", "xla:0", "xla:1"],
        help="conv_impl:mirror[:sym_batch]; xla = lax.conv_general_dilated, what flax.linen.Conv calls",
    )
    p.add_argument("--compare-xla-tuning", action="store_true",
                   help="run everything twice, in two processes, with EQUIBIM_JAX_XLA_TUNING=1 "
                        "and =0 (the train step's XLA:CPU options on and off), and report both")
    args = p.parse_args()
    if args.compare_xla_tuning:
        return compare_xla_tuning(args)

    device = jax.devices()[0]
    result = {
        "benchmark": "diffusion-policy train step (AdamW + EMA), fp32",
        "versions": {
            "jax": jax.__version__,
            "jaxlib": jax.lib.__version__ if hasattr(jax.lib, "__version__") else None,
            "flax": flax.__version__,
            "optax": optax.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
        "device": {"platform": device.platform, "kind": device.device_kind, "count": jax.device_count()},
        "host": {"cpus": os.cpu_count(), "loadavg_start": os.getloadavg()},
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "train_compiler_options": train_compiler_options(),
        "config": vars(args),
        "notes": (
            "compile_s_* are AOT compile times with the persistent cache off. "
            "gflops = XLA flops of one step / median ms per step in the scan. "
            "'xla' convs use lax.conv_general_dilated with the same parameters, which is "
            "the op flax.linen.Conv lowers to."
        ),
    }
    policy, dataset, sym = synthetic_problem(args)
    result["matmul_2048_fp32"] = matmul_gflops()
    peak = result["matmul_2048_fp32"]["gflops"]
    result["variants"] = []
    for v in args.variants:
        impl, mirror, *rest = v.split(":")
        r = bench_variant(args, policy, dataset, sym, impl, mirror == "1", peak,
                          sym_batch=int(rest[0]) if rest else None)
        print(json.dumps(r), flush=True)
        result["variants"].append(r)
    result["matmul_2048_fp32_end"] = matmul_gflops()
    result["host"]["loadavg_end"] = os.getloadavg()
    _write_json(args.out, result)
    print(f"wrote {args.out}")


def compare_xla_tuning(args) -> None:
    """Run this benchmark in two child processes (flag on, flag off) and merge the JSONs."""
    argv = [a for a in sys.argv[1:] if a != "--compare-xla-tuning"]
    i = argv.index("--out")
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, value in (("xla_tuning_on", "1"), ("xla_tuning_off", "0")):
            out = os.path.join(tmp, label + ".json")
            child = argv[:i + 1] + [out] + argv[i + 2:]
            env = dict(os.environ, EQUIBIM_JAX_XLA_TUNING=value)
            print(f"== {label}", flush=True)
            subprocess.run([sys.executable, os.path.abspath(__file__), *child], env=env, check=True)
            with open(out) as f:
                runs[label] = json.load(f)
    on, off = runs["xla_tuning_on"], runs["xla_tuning_off"]
    runs["speedup_of_tuning"] = [
        {"conv_impl": a["conv_impl"], "mirror_branch": a["mirror_branch"], "sym_batch": a["sym_batch"],
         "ms_per_step_on": a["ms_per_step_scan"], "ms_per_step_off": b["ms_per_step_scan"],
         "speedup": b["ms_per_step_scan"] / a["ms_per_step_scan"]}
        for a, b in zip(on["variants"], off["variants"])
    ]
    for r in runs["speedup_of_tuning"]:
        print(json.dumps(r))
    _write_json(args.out, runs)
    print(f"wrote {args.out}")


def _write_json(path: str, obj) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=2)
    os.replace(tmp, path)


if __name__ == "__main__":
    main()
