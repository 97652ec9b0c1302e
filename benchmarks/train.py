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

Policy mode (``--policies``): every named policy at its *default* config (``DPConfig()``,
``DP3Config()``, ``ACTConfig()``) on synthetic frames of robot A's shapes (qpos 14, action
14, ``image`` 64x64x3 for dp/act, ``point_cloud`` 512x3 for dp3), batch 64: parameter
count, ms per step without and with the full mirrored batch (``sym_weight`` 0.1, the
``TrainConfig`` defaults otherwise) timed inside ``make_train_loop`` dispatches of K steps
(median over ``--repeats``), AOT compile times, XLA's FLOP count and memory analysis of the
compiled step, GFLOP/s and its fraction of a dense fp32 matmul measured in the same run,
and the jitted ``policy.sample`` on batch 1. ``--vs-torch`` adds the PyTorch twins of
``benchmarks/torch_twins.py`` (same architecture, asserted equal parameter counts, same
AdamW + EMA, 2 threads, eager); ``--online`` adds the fused online loop's throughput:

    python benchmarks/train.py --policies dp dp3 act --vs-torch --online --k 10 --repeats 3 \\
        --out benchmarks/results/train_policies_2core_cpu.json
"""

from __future__ import annotations

import os

os.environ["EQUIBIM_JAX_CACHE"] = "0"  # before importing equibim_jax: measure real compiles

import argparse
import dataclasses
import json
import platform
import resource
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
    p.add_argument("--policies", nargs="+", choices=["dp", "dp3", "act"],
                   help="policy mode: benchmark these policies at their default configs")
    p.add_argument("--vs-torch", action="store_true", help="policy mode: also time the PyTorch twins")
    p.add_argument("--online", action="store_true", help="policy mode: also time the fused online loop")
    p.add_argument("--online-task", default="click_bell")
    p.add_argument("--tiny", action="store_true",
                   help="policy mode: tiny networks and data (a smoke test, not a measurement)")
    p.add_argument("--infer-repeats", type=int, default=20)
    p.add_argument("--policy-variants", nargs="+", default=["bc", "sym"], choices=["bc", "sym"],
                   help="policy mode: without and/or with the mirrored L_sym branch")
    p.add_argument("--matmul-n", type=int, default=2048, help="policy mode: side of the reference matmul")
    p.add_argument("--no-step-compile", action="store_true",
                   help="policy mode: compile only the K-step loop (FLOPs and memory from it; "
                        "no single-step compile time)")
    args = p.parse_args()
    if args.policies or args.online:
        return policies_main(args)
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


# ---------------------------------------------------------------------------------------
# Policy mode: dp, dp3, act at their default configs (and their PyTorch twins).
# ---------------------------------------------------------------------------------------

ACTION_DIM = 14  # robot A: two arms of 6 joints + a gripper each
TARGETS = {
    "speedup_vs_torch_min": 2.0,
    "fraction_of_matmul_min": 0.5,
    "sym_ratio_max": 1.4,
    "dp_infer_ms_max": 50.0,
}


def _mirror_perm_signs(a: int = ACTION_DIM):
    """Left arm <-> right arm; every other joint flips sign (a signed permutation)."""
    half = a // 2
    perm = np.concatenate([np.arange(half, a), np.arange(half)])
    signs = np.where(np.arange(a) % 2 == 1, -1.0, 1.0)
    return perm, signs


def policy_config(name: str, tiny: bool):
    """The default config of ``name`` resolved on robot A's shapes (tiny: shrunk)."""
    from equibim_jax.policies import ACTConfig, DPConfig, ImageObsConfig, VisionConfig

    if name == "dp3":
        cfg = DP3Config()
        if tiny:
            cfg = dataclasses.replace(cfg, unet=UNetConfig(down_dims=(8,), step_embed_dim=8, n_groups=4),
                                      encoder=EncoderConfig(state_hidden=(8,), state_out=8,
                                                            pc_hidden=(8,), pc_out=8))
        return cfg.with_data(ACTION_DIM, {"qpos": ACTION_DIM, "point_cloud": 3})
    image = (16, 16, 3) if tiny else (64, 64, 3)
    enc = ImageObsConfig(vision=VisionConfig(channels=(8,), groups=4, keypoints=4, out=8),
                         state_hidden=(8,), state_out=8) if tiny else None
    if name == "dp":
        cfg = DPConfig()
        if tiny:
            cfg = dataclasses.replace(cfg, encoder=enc,
                                      unet=UNetConfig(down_dims=(8,), step_embed_dim=8, n_groups=4))
    else:
        cfg = ACTConfig()
        if tiny:
            cfg = dataclasses.replace(cfg, encoder=enc, d_model=16, n_heads=2, enc_layers=1,
                                      dec_layers=1, ff_dim=16, latent_dim=4, cvae_layers=1)
    return cfg.with_data(ACTION_DIM, {"qpos": ACTION_DIM, "image": 3}, {"image": image})


def policy_problem(name: str, cfg, tiny: bool):
    """Synthetic normalised frames of the policy's fields, the dataset and ``S`` in JAX."""
    rng = np.random.default_rng(0)
    n_eps, ep_len = (2, 40) if tiny else ((4, 100) if name in ("dp", "act") else (20, 100))
    f = n_eps * ep_len
    frames = {"qpos": rng.uniform(-1, 1, (f, ACTION_DIM)).astype(np.float32),
              "action": rng.uniform(-1, 1, (f, ACTION_DIM)).astype(np.float32)}
    if "image" in cfg.obs_keys:
        frames["image"] = rng.uniform(-1, 1, (f,) + tuple(cfg.image_shapes[0])).astype(np.float32)
    if "point_cloud" in cfg.obs_keys:
        frames["point_cloud"] = rng.uniform(-1, 1, (f, 64 if tiny else 512, 3)).astype(np.float32)
    ends = np.arange(1, n_eps + 1) * ep_len
    dataset = make_dataset(frames, ends, cfg)
    perm, signs = _mirror_perm_signs()
    joint = signed_permutation(perm, signs)
    sym = {"qpos": joint, "action": joint,
           "image": lambda x: jnp.flip(x, axis=-2),  # [..., H, W, C]: flip W
           "point_cloud": lambda p: p * jnp.array([1.0, -1.0, 1.0])}
    return frames, dataset, sym, (perm, signs)


def _train_config(args, mirror: bool) -> TrainConfig:
    return TrainConfig(batch_size=args.batch, sym_weight=0.1 if mirror else 0.0,
                       steps_per_dispatch=args.k, warmup_steps=10, total_steps=10_000 * args.k)


def _memory_mb(compiled) -> dict | None:
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend gives one
        return None
    if m is None:
        return None
    arg, out, tmp = m.argument_size_in_bytes, m.output_size_in_bytes, m.temp_size_in_bytes
    alias = getattr(m, "alias_size_in_bytes", 0)
    return {"argument_mb": arg / 2**20, "output_mb": out / 2**20, "temp_mb": tmp / 2**20,
            "alias_mb": alias / 2**20, "total_mb": (arg + out + tmp - alias) / 2**20}


def _max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def bench_policy_variant(args, name, policy, dataset, sym, mirror: bool, peak: float) -> dict:
    """One policy, BC or BC + ``L_sym``: compile times, FLOPs, memory, ms per step."""
    train = _train_config(args, mirror)
    state = create_train_state(policy, train)
    key = base_key(train)
    out = {"params": int(sum(x.size for x in jax.tree.leaves(state.params)))}
    loop = make_train_loop(train, dataset, sym if mirror else None)
    t = time.perf_counter()
    loop_c = loop.lower(state, key).compile()
    out["compile_s_loop"] = time.perf_counter() - t
    if args.no_step_compile:
        # XLA's cost analysis counts a while loop's body once: the loop's FLOPs are one step's.
        step_c = loop_c
        out["compile_s"] = None
    else:
        step = make_train_step(train, dataset, sym if mirror else None)
        t = time.perf_counter()
        step_c = step.lower(state, key).compile()
        out["compile_s"] = time.perf_counter() - t
    cost = step_c.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    flops = float(cost["flops"])
    out["gflop_per_step"] = flops / 1e9
    out["memory_analysis"] = _memory_mb(step_c)
    s, m = _block(loop_c(state, key, dataset))  # warm-up dispatch
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        s, m = _block(loop_c(s, key, dataset))
        times.append((time.perf_counter() - t) / args.k)
    ms = 1e3 * statistics.median(times)
    out["step_ms"] = ms
    out["step_ms_all"] = [1e3 * x for x in times]
    out["gflops"] = flops / (ms / 1e3) / 1e9
    out["fraction_of_matmul"] = out["gflops"] / peak
    out["final_loss"] = float(m["total"][-1])
    out["state"] = s
    return out


def bench_inference(args, name, policy, params, frames) -> dict:
    """``jax.jit(policy.sample)`` on batch 1 (raw-size observations, the eval crop inside)."""
    cfg = policy.config
    obs = {k: jnp.asarray(frames[k][: cfg.obs_horizon])[None] for k in cfg.obs_keys}
    f = jax.jit(policy.sample)
    key = jax.random.key(3)
    t = time.perf_counter()
    f_c = f.lower(params, obs, key).compile()
    compile_s = time.perf_counter() - t
    _block(f_c(params, obs, key))
    times = []
    for i in range(args.infer_repeats):
        k = jax.random.fold_in(key, i)
        t = time.perf_counter()
        _block(f_c(params, obs, k))
        times.append(time.perf_counter() - t)
    return {"infer_ms_per_chunk": 1e3 * statistics.median(times), "infer_compile_s": compile_s,
            "infer_what": ("DDIM %d steps" % cfg.num_inference_steps) if name != "act" else "one pass (z = 0)"}


def bench_torch(args, name, cfg, frames, dataset, perm_signs) -> dict:
    import torch

    import torch_twins

    torch.set_num_threads(2)
    out = {"torch_version": torch.__version__, "torch_threads": torch.get_num_threads()}
    mirror = torch_twins.Mirror(*perm_signs)
    for mirror_on in [v == "sym" for v in args.policy_variants]:
        twin = torch_twins.TorchTwin(name, cfg, _train_config(args, mirror_on), frames,
                                     np.array(dataset.obs_index), np.array(dataset.action_index), mirror)
        out["params_torch"] = twin.num_params
        r = twin.time_steps(mirror_on, args.k, args.repeats)
        sfx = "_sym" if mirror_on else ""
        out["torch_step_ms" + sfx] = r["ms"]
        out["torch_step_ms_all" + sfx] = r["all_ms"]
        out["torch_final_loss" + sfx] = r["final_loss"]
        del twin
    return out


def bench_policy(args, name: str, peak: float) -> dict:
    cfg = policy_config(name, args.tiny)
    policy = make_policy(name, cfg)
    frames, dataset, sym, perm_signs = policy_problem(name, cfg, args.tiny)
    rec = {"config": repr(cfg), "batch": args.batch, "obs_horizon": cfg.obs_horizon,
           "pred_horizon": cfg.pred_horizon,
           "obs_shapes": {k: list(frames[k].shape[1:]) for k in cfg.obs_keys}}
    params = None
    for variant in args.policy_variants:
        r = bench_policy_variant(args, name, policy, dataset, sym, variant == "sym", peak)
        print(f"{name} {variant}: {r['step_ms']:.1f} ms/step, compile {r['compile_s']} (step) "
              f"{r['compile_s_loop']:.1f} (loop) s", flush=True)
        params = r.pop("state").params
        rec["params"] = r["params"]
        sfx = "_sym" if variant == "sym" else ""
        for k in ("step_ms", "step_ms_all", "compile_s", "compile_s_loop", "gflop_per_step", "gflops",
                  "fraction_of_matmul", "memory_analysis", "final_loss"):
            rec[k + sfx] = r[k]
    if "step_ms" in rec and "step_ms_sym" in rec:
        rec["sym_ratio"] = rec["step_ms_sym"] / rec["step_ms"]
    mem = rec.get("memory_analysis_sym") or rec.get("memory_analysis") or {}
    rec["peak_mem_mb"] = mem.get("total_mb")
    rec["peak_mem_what"] = ("XLA memory_analysis() of the compiled single step (with the mirrored "
                            "branch where it ran): argument + output + temp - alias bytes")
    rec.update(bench_inference(args, name, policy, params, frames))
    print(f"{name} infer: {rec['infer_ms_per_chunk']:.1f} ms/chunk", flush=True)
    rec["process_max_rss_mb_after_jax"] = _max_rss_mb()
    if args.vs_torch:
        t = bench_torch(args, name, cfg, frames, dataset, perm_signs)
        if t["params_torch"] != rec["params"]:
            raise AssertionError(f"{name}: torch twin has {t['params_torch']} parameters, JAX {rec['params']}")
        rec.update(t)
        for sfx in ("", "_sym"):
            if "torch_step_ms" + sfx in rec:
                rec["ratio_vs_torch" + sfx] = rec["step_ms" + sfx] / rec["torch_step_ms" + sfx]
        if "torch_step_ms" in rec and "torch_step_ms_sym" in rec:
            rec["torch_sym_ratio"] = rec["torch_step_ms_sym"] / rec["torch_step_ms"]
        print(f"{name} torch: " + ", ".join(f"{k} {rec[k]:.1f} ms" for k in ("torch_step_ms", "torch_step_ms_sym")
                                             if k in rec), flush=True)
    rec["targets_met"] = _targets_met(name, rec)
    return rec


def _targets_met(name: str, r: dict) -> dict:
    t = TARGETS
    out = {}
    if "sym_ratio" in r:
        out["sym_ratio"] = r["sym_ratio"] <= t["sym_ratio_max"]
    for sfx in ("", "_sym"):
        if "fraction_of_matmul" + sfx in r:
            out["fraction_of_matmul" + sfx] = r["fraction_of_matmul" + sfx] >= t["fraction_of_matmul_min"]
        if "ratio_vs_torch" + sfx in r:
            out["speedup_vs_torch" + sfx] = 1 / r["ratio_vs_torch" + sfx] >= t["speedup_vs_torch_min"]
    if name == "dp":
        out["infer_ms"] = r["infer_ms_per_chunk"] <= t["dp_infer_ms_max"]
    return out


def rescale_to_best_matmul(result: dict) -> None:
    """Fractions of the matmul against the better of the two matmul measurements (start and
    end of the run), so that a slow reference never flatters a policy; targets re-checked."""
    best = max(result["matmul_2048_fp32"]["gflops"], result["matmul_2048_fp32_end"]["gflops"])
    result["matmul_reference_gflops"] = best
    for name, r in result["policies"].items():
        for sfx in ("", "_sym"):
            if "gflops" + sfx in r:
                r["fraction_of_matmul" + sfx] = r["gflops" + sfx] / best
        r["targets_met"] = _targets_met(name, r)


def bench_online(args, peak: float) -> dict:
    """The fused online loop (expert envs + ring buffer + update) on one task, against the
    same policy's offline step."""
    from equibim_jax.config import TaskConfig
    from equibim_jax.training import OnlineConfig
    from equibim_jax.training.online import train_online

    iters = 20
    dispatches = 2 if args.tiny else 4
    policy = DP3Config(encoder=EncoderConfig(pc_key=None))
    oc = OnlineConfig(num_envs=8, env_steps=8, grad_steps=1, iterations=iters)
    tc = TrainConfig(batch_size=args.batch, sym_weight=0.1, steps_per_dispatch=iters,
                     total_steps=dispatches * iters)
    task = TaskConfig(args.online_task, {"obs": ["qpos"]})
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        s = train_online(task, os.path.join(tmp, "run"), policy, tc, oc, progress=False)
        wall = time.perf_counter() - t
        with open(s["log"]) as f:
            rows = [json.loads(x) for x in f if x.strip()]
    steady = [r["dispatch_s"] for r in rows[1:]]
    out = {"task": args.online_task, "policy": "dp3 default, state only (pc_key=None)",
           "online_config": dataclasses.asdict(oc), "batch": args.batch, "sym_weight": 0.1,
           "dispatches": len(rows), "steps_per_dispatch": iters * oc.grad_steps,
           "env_steps_per_dispatch": iters * oc.env_steps * oc.num_envs,
           "env_steps_per_s": s["env_steps_per_s"], "train_steps_per_s": s["train_steps_per_s"],
           "steady_dispatch_s": steady,
           "first_dispatch_s_incl_compile": s["first_dispatch_s_incl_compile"],
           "compile_s_est": s["first_dispatch_s_incl_compile"] - statistics.median(steady),
           "preload_s": s["preload_s"], "wall_s": wall, "episodes": s["episodes"],
           "successes": s["successes"]}
    out["ms_per_iteration"] = 1e3 * statistics.median(steady) / iters
    # The same policy's offline step (BC + L_sym), on synthetic state-only frames.
    cfg = policy.with_data(ACTION_DIM, {"qpos": ACTION_DIM})
    pol = make_policy("dp3", cfg)
    rng = np.random.default_rng(0)
    frames = {"qpos": rng.uniform(-1, 1, (2000, ACTION_DIM)).astype(np.float32),
              "action": rng.uniform(-1, 1, (2000, ACTION_DIM)).astype(np.float32)}
    dataset = make_dataset(frames, np.arange(1, 21) * 100, cfg)
    perm, signs = _mirror_perm_signs()
    joint = signed_permutation(perm, signs)
    r = bench_policy_variant(args, "dp3", pol, dataset, {"qpos": joint, "action": joint}, True, peak)
    out["offline_step_ms_sym"] = r["step_ms"]
    out["offline_compile_s_loop"] = r["compile_s_loop"]
    out["offline_train_steps_per_s"] = 1e3 / r["step_ms"]
    out["online_ms_per_train_step_incl_env"] = 1e3 / s["train_steps_per_s"]
    return out


def policies_main(args) -> None:
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # torch_twins
    device = jax.devices()[0]
    t_start = time.perf_counter()
    result = {
        "benchmark": "policy train steps (dp, dp3, act; AdamW + EMA, fp32) at default configs",
        "command": "python benchmarks/train.py " + " ".join(sys.argv[1:]),
        "versions": {"jax": jax.__version__, "flax": flax.__version__, "optax": optax.__version__,
                     "numpy": np.__version__, "python": platform.python_version()},
        "device": {"platform": device.platform, "kind": device.device_kind, "count": jax.device_count()},
        "host": {"cpus": os.cpu_count(), "loadavg_start": os.getloadavg()},
        "train_compiler_options": train_compiler_options(),
        "config": vars(args),
        "targets": TARGETS,
        "notes": ("step_ms: median over --repeats make_train_loop dispatches of K steps, one warm-up "
                  "dispatch first; compile_s: AOT compile of the single step (compile_s_loop: of the "
                  "K-step loop), persistent cache off; gflop_per_step: XLA cost_analysis() of the "
                  "single step; peak_mem_mb: memory_analysis() of the compiled single step with the "
                  "mirrored branch; process_max_rss_mb: getrusage max RSS of the whole process. "
                  "sym: sym_weight 0.1, all B samples mirrored, L_sym 'rms' with stop-gradient (the "
                  "TrainConfig defaults)."),
        "policies": {},
    }
    result["matmul_2048_fp32"] = matmul_gflops(args.matmul_n)
    peak = result["matmul_2048_fp32"]["gflops"]
    for name in args.policies or []:
        result["policies"][name] = bench_policy(args, name, peak)
        _write_json(args.out, result)
    if args.online:
        result["online"] = bench_online(args, peak)
        print(f"online: {result['online']['env_steps_per_s']:.0f} env-steps/s, "
              f"{result['online']['train_steps_per_s']:.1f} train-steps/s", flush=True)
    result["matmul_2048_fp32_end"] = matmul_gflops(args.matmul_n)
    rescale_to_best_matmul(result)
    result["host"]["loadavg_end"] = os.getloadavg()
    result["process_max_rss_mb"] = _max_rss_mb()
    result["wall_s"] = time.perf_counter() - t_start
    _write_json(args.out, result)
    print(f"wrote {args.out} in {result['wall_s']:.0f} s")


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
