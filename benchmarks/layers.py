"""Micro-benchmarks behind the train step's layout choices; writes JSON.

1. The weight gradient of a per-point ``Dense`` (``relu(x @ w).sum()``) with ``x`` as
   ``[B, To, N, 3]`` (a dot with several contracting dims) and flattened to ``[rows, 3]``.
2. The gradient of the demo's DP3-style encoder (``PointCloudEncoder``, widths 32/64/128,
   batch 64, 2 frames of 64 points), compiled with XLA:CPU's default YNNPACK fusions and
   with the train step's options (``equibim_jax._xla_options.TRAIN_CPU_OPTIONS``: YNNPACK
   fusions for dots only).

    python benchmarks/layers.py --out benchmarks/results/layers_2core_cpu.json

Times are the minimum over repeats of one jitted call (milliseconds); compile excluded.
"""

from __future__ import annotations

import os

os.environ["EQUIBIM_JAX_CACHE"] = "0"

import argparse
import json
import platform
import time

import jax
import jax.numpy as jnp

from equibim_jax._xla_options import TRAIN_CPU_OPTIONS
from equibim_jax.policies.encoders import PointCloudEncoder


def best_ms(f, *args, repeats: int = 30) -> float:
    jax.block_until_ready(f(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t)
    return 1e3 * min(times)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="JSON file to write")
    p.add_argument("--repeats", type=int, default=30)
    args = p.parse_args()
    r = args.repeats
    x4 = jax.random.normal(jax.random.key(0), (64, 2, 64, 3))
    w = jax.random.normal(jax.random.key(1), (3, 128))
    layer = jax.grad(lambda w_, x: jax.nn.relu(x @ w_).sum())
    res = {
        "benchmark": "layout micro-benchmarks (ms, min over repeats, compile excluded)",
        "versions": {"jax": jax.__version__, "python": platform.python_version()},
        "host": {"cpus": os.cpu_count(), "loadavg_start": os.getloadavg()},
        "dense_weight_grad_ms": {
            "x_4d_[64,2,64,3]": best_ms(jax.jit(layer), w, x4, repeats=r),
            "x_2d_[8192,3]": best_ms(jax.jit(layer), w, x4.reshape(-1, 3), repeats=r),
        },
    }
    enc = PointCloudEncoder((32, 64, 128), 64)
    params = enc.init(jax.random.key(2), x4)
    grad = jax.grad(lambda p_: jnp.square(enc.apply(p_, x4)).sum())
    res["pc_encoder_grad_ms"] = {
        "default_fusions": best_ms(jax.jit(grad), params, repeats=r),
        "train_options": best_ms(jax.jit(grad, compiler_options=dict(TRAIN_CPU_OPTIONS)), params, repeats=r),
        "options": TRAIN_CPU_OPTIONS,
    }
    res["host"]["loadavg_end"] = os.getloadavg()
    tmp = f"{args.out}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(res, f, indent=2)
    os.replace(tmp, args.out)
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
