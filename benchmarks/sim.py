"""Simulator benchmark: MJX physics, MuJoCo C, mujoco.rollout, and the ray-cast renderer.

    python benchmarks/sim.py --out results/bench_sim.json [--quick]

Robot A with one free box on the table (``BoxScene``). On the CPU, batches above 32 run
as a scan over vmapped chunks of 32 (``equibim_jax._batching``: jaxlib 0.10.2's batched
Cholesky deadlocks at 64 on 2 cores). Physics throughput counts physics
steps (``mjx.step`` calls, one per env) per second; compile time is reported apart from run
time, and the MJX figures are given as a ratio to MuJoCo C measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from equibim_jax._batching import chunked_vmap, default_chunk  # noqa: E402
from equibim_jax._io import atomic_write_json  # noqa: E402
from equibim_jax.sim.env import Env, EnvConfig  # noqa: E402
from equibim_jax.sim.scenes import BoxScene  # noqa: E402


def _timeit(fn, *args, reps=3):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return compile_s, best, out


def bench_mjx(env: Env, batch: int, n_steps: int):
    keys = jax.random.split(jax.random.key(0), batch)
    states = jax.jit(chunked_vmap(env.reset))(keys)
    noise = 0.05 * jax.random.normal(jax.random.key(1), (batch, env.mj_model.nu))
    ctrl = states.data.ctrl + noise

    @jax.jit
    def run(data, ctrl):
        data = data.replace(ctrl=ctrl)

        def one(d):
            def body(d, _):
                return mjx.step(env.mjx_model, d), None

            return jax.lax.scan(body, d, None, length=n_steps)[0]

        return chunked_vmap(one)(data)

    compile_s, run_s, _ = _timeit(run, states.data, ctrl)
    return {"compile_s": compile_s, "run_s": run_s, "steps_per_s": batch * n_steps / run_s}


def bench_c(model: mujoco.MjModel, qpos0, ctrl, n_steps: int):
    data = mujoco.MjData(model)
    data.qpos[:] = qpos0
    data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        mujoco.mj_step(model, data)
    dt = time.perf_counter() - t0
    return n_steps / dt


def bench_rollout(model, qpos0, ctrl, batch: int, n_steps: int, threads: int = 2):
    from mujoco import rollout

    data = mujoco.MjData(model)
    data.qpos[:] = qpos0
    data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    init = np.tile(state, (batch, 1))
    control = np.tile(ctrl, (batch, n_steps, 1))
    datas = [mujoco.MjData(model) for _ in range(threads)]
    rollout.rollout(model, datas, init, control[:, :2])  # warm-up
    t0 = time.perf_counter()
    rollout.rollout(model, datas, init, control)
    dt = time.perf_counter() - t0
    return batch * n_steps / dt


def bench_render(size: int, batch: int):
    env = Env(EnvConfig(obs=("image",), image_size=size), BoxScene())
    keys = jax.random.split(jax.random.key(0), batch)
    states = jax.jit(chunked_vmap(env.reset))(keys)
    render = jax.jit(jax.vmap(env.renderer.rgb))  # no Cholesky inside: plain vmap is safe
    compile_s, run_s, _ = _timeit(render, states.data)
    return {"compile_s": compile_s, "run_s": run_s, "fps": batch / run_s}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--quick", action="store_true", help="fewer steps (smoke run)")
    ap.add_argument("--batches", default="1,64,256")
    args = ap.parse_args(argv)

    n_steps = 20 if args.quick else 100
    env = Env(EnvConfig(obs=("qpos",)), BoxScene())
    m = env.mj_model
    print(f"model: nq={m.nq} nv={m.nv} ngeom={m.ngeom} timestep={m.opt.timestep} "
          f"iterations={m.opt.iterations} ls_iterations={m.opt.ls_iterations} cone={m.opt.cone}")
    s0 = env.reset(jax.random.key(0))
    qpos0, ctrl0 = np.asarray(s0.data.qpos, np.float64), np.asarray(s0.data.ctrl, np.float64)

    c_sps = bench_c(m, qpos0, ctrl0, 20000 if not args.quick else 2000)
    print(f"MuJoCo C mj_step, 1 thread: {c_sps:,.0f} steps/s")
    ro_sps = bench_rollout(m, qpos0, ctrl0, 256, 100 if not args.quick else 10)
    print(f"mujoco.rollout, 2 threads, batch 256: {ro_sps:,.0f} steps/s")

    mjx_res = {}
    for b in [int(x) for x in args.batches.split(",")]:
        r = bench_mjx(env, b, n_steps)
        mjx_res[str(b)] = r
        print(f"MJX batch {b:4d}: {r['steps_per_s']:,.0f} physics steps/s "
              f"(compile {r['compile_s']:.1f} s, run {r['run_s']:.3f} s for {n_steps} steps), "
              f"ratio to C {r['steps_per_s'] / c_sps:.3f}")

    render = {}
    for size in (64, 96):
        r = bench_render(size, 64)
        render[str(size)] = r
        print(f"render {size}x{size}, vmapped over 64 envs: {r['fps']:,.0f} frames/s "
              f"(compile {r['compile_s']:.1f} s)")

    out = {
        "mjx_steps_per_s": {k: v["steps_per_s"] for k, v in mjx_res.items()},
        "mjx_over_c": {k: v["steps_per_s"] / c_sps for k, v in mjx_res.items()},
        "c_steps_per_s": c_sps,
        "rollout_steps_per_s": ro_sps,
        "render_fps": {k: v["fps"] for k, v in render.items()},
        "compile_s": {
            **{f"mjx_batch_{k}": v["compile_s"] for k, v in mjx_res.items()},
            **{f"render_{k}": v["compile_s"] for k, v in render.items()},
        },
        "run_s": {
            **{f"mjx_batch_{k}": v["run_s"] for k, v in mjx_res.items()},
            **{f"render_{k}": v["run_s"] for k, v in render.items()},
        },
        "n_physics_steps": n_steps,
        "render_batch": 64,
        "model": {"nq": m.nq, "nv": m.nv, "ngeom": m.ngeom, "timestep": m.opt.timestep,
                  "iterations": m.opt.iterations, "ls_iterations": m.opt.ls_iterations},
        "versions": {"jax": jax.__version__, "mujoco": mujoco.__version__,
                     "python": platform.python_version(), "numpy": np.__version__},
        "device": str(jax.devices()[0]),
        "vmap_chunk": default_chunk(),
        "cpu_count": os.cpu_count(),
        "command": " ".join(["python", "benchmarks/sim.py", *(argv or sys.argv[1:])]),
    }
    atomic_write_json(args.out, out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
