"""Simulator benchmark: MJX physics, MuJoCo C, mujoco.rollout, and the ray-cast renderer.

    python benchmarks/sim.py --out benchmarks/results/sim_2core_cpu.json [--quick]

Robot A with one free box on the table (``BoxScene``). Physics throughput counts physics
steps (``mjx.step`` calls, one per env) per second of a jitted ``vmap`` over the batch of a
``lax.scan`` of steps. Compile time (the first call) is reported apart from run time (the
best of the later calls), with the persistent compilation cache off so that compiles are
real. MJX figures are also given as a ratio to MuJoCo C measured in the same run (one
thread, the best of 5 runs of 20,000 steps after a warm-up run: a single run can be slow on
a shared host).

MJX runs in one child process per *variant* ``DEVICES:CONTACTS[:ITERATIONS:LS_ITERATIONS]``:

* ``DEVICES``: CPU devices (``--xla_force_host_platform_device_count``), the batch sharded
  over them (``equibim_jax._sharding``). XLA runs one device's program on one thread, so on
  a multi-core CPU more devices use more cores;
* ``CONTACTS``: ``all`` (every candidate pair's contacts) or ``K``
  (``EnvConfig.max_contacts``: the K deepest contacts are kept);
* ``ITERATIONS:LS_ITERATIONS`` (optional): the solver's Newton and line-search iteration
  limits (``EnvConfig.solver_iterations`` / ``ls_iterations``; default: the model's). Such a
  variant changes the physics; MuJoCo C is then also timed with the same limits
  (``c_steps_per_s_same_solver``), since its cost depends on them too.

The JSON keeps the headline figures (``mjx_steps_per_s`` ...) of the first variant and
every variant under ``variants``.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from equibim_jax._io import atomic_write_json  # noqa: E402
from equibim_jax.sim.env import Env, EnvConfig  # noqa: E402
from equibim_jax.sim.scenes import BoxScene  # noqa: E402


def _timeit(fn, *args, reps=5):
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
    from equibim_jax._sharding import data_mesh, round_up, shard_batch
    from equibim_jax.sim._linalg import jax_cholesky

    mesh = data_mesh()
    if round_up(batch, mesh) != batch:
        raise SystemExit(f"batch {batch} is not a multiple of the {jax.device_count()} devices")
    keys = shard_batch(jax.random.split(jax.random.key(0), batch), mesh)
    states = jax.jit(jax.vmap(env.reset))(keys)
    noise = 0.05 * jax.random.normal(jax.random.key(1), (batch, env.mj_model.nu))
    ctrl = states.data.ctrl + shard_batch(noise, mesh)

    @jax.jit
    def run(data, ctrl):
        data = data.replace(ctrl=ctrl)

        def one(d):
            def body(d, _):
                with jax_cholesky():  # as Env does (equibim_jax/sim/_linalg.py)
                    return mjx.step(env.mjx_model, d), None

            return jax.lax.scan(body, d, None, length=n_steps)[0]

        return jax.vmap(one)(data)

    compile_s, run_s, out = _timeit(run, states.data, ctrl)
    return {"compile_s": compile_s, "run_s": run_s, "steps_per_s": batch * n_steps / run_s,
            "finite": bool(np.all(np.isfinite(np.asarray(out.qpos))))}


def bench_c(model: mujoco.MjModel, qpos0, ctrl, n_steps: int, reps: int = 5):
    """MuJoCo C ``mj_step`` steps/s on one thread: the best of ``reps`` runs of ``n_steps``
    from the same start, after one untimed warm-up run (as MJX's figure is the best of its
    timed calls after the first)."""
    data = mujoco.MjData(model)
    best = np.inf
    for r in range(reps + 1):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = qpos0
        data.ctrl[:] = ctrl
        mujoco.mj_forward(model, data)
        t0 = time.perf_counter()
        for _ in range(n_steps):
            mujoco.mj_step(model, data)
        if r:
            best = min(best, time.perf_counter() - t0)
    return n_steps / best


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
    states = jax.jit(jax.vmap(env.reset))(keys)
    render = jax.jit(jax.vmap(env.renderer.rgb))
    compile_s, run_s, _ = _timeit(render, states.data)
    return {"compile_s": compile_s, "run_s": run_s, "fps": batch / run_s}


def child(args) -> dict:
    """One variant, in this (child) process: MJX at each batch, and the renderer."""
    from equibim_jax import disable_compilation_cache

    disable_compilation_cache()
    n_steps = 20 if args.quick else 100
    env = Env(EnvConfig(obs=("qpos",), max_contacts=args.max_contacts, solver_iterations=args.solver_iterations,
                        ls_iterations=args.ls_iterations), BoxScene())
    d0 = env.reset(jax.random.key(0)).data
    res = {"devices": jax.device_count(), "max_contacts": args.max_contacts,
           "solver_iterations": int(env.mj_model.opt.iterations), "ls_iterations": int(env.mj_model.opt.ls_iterations),
           "contacts": int(d0._impl.contact.dist.shape[0]), "constraint_rows": int(d0._impl.efc_J.shape[0]),
           "mjx": {}, "render": {}}
    for b in [int(x) for x in args.batches.split(",")]:
        res["mjx"][str(b)] = bench_mjx(env, b, n_steps)
    if args.render:
        for size in (64, 96):
            res["render"][str(size)] = bench_render(size, 64)
    return res


def _variant(spec: str) -> tuple[int, int | None, int | None, int | None]:
    """``DEVICES:CONTACTS[:ITERATIONS:LS_ITERATIONS]`` -> (devices, contacts, iterations, ls)."""
    parts = spec.split(":")
    if len(parts) not in (1, 2, 4):
        raise ValueError(spec)
    dev = int(parts[0])
    con = parts[1] if len(parts) > 1 else ""
    it, ls = (int(parts[2]), int(parts[3])) if len(parts) == 4 else (None, None)
    return dev, (None if con in ("", "all") else int(con)), it, ls


def run_variant(spec: str, args) -> dict:
    devices, max_contacts, iterations, ls_iterations = _variant(spec)
    batches = ",".join(b for b in args.batches.split(",") if int(b) % devices == 0)
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--batches", batches]
    if max_contacts is not None:
        cmd += ["--max-contacts", str(max_contacts)]
    if iterations is not None:
        cmd += ["--solver-iterations", str(iterations), "--ls-iterations", str(ls_iterations)]
    if args.quick:
        cmd.append("--quick")
    if spec == args.variants.split(",")[0]:
        cmd.append("--render")
    env = dict(os.environ)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "force_host_platform_device_count" not in f]
    env["XLA_FLAGS"] = " ".join(flags + [f"--xla_force_host_platform_device_count={devices}"])
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"variant {spec} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="JSON file to write")
    ap.add_argument("--quick", action="store_true", help="fewer steps (smoke run)")
    ap.add_argument("--batches", default="1,64,256")
    ap.add_argument("--variants", default="2:24,1:all,2:all,1:24,2:24:2:4,2:24:4:2",
                    help="comma-separated DEVICES:CONTACTS[:ITERATIONS:LS_ITERATIONS] (CONTACTS 'all' or a "
                         "number; solver limits default to the model's); the first is the headline")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--max-contacts", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--solver-iterations", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--ls-iterations", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--render", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args)))
        return
    if not args.out:
        ap.error("--out is required")
    for spec in args.variants.split(","):
        try:
            d, k, it, ls = _variant(spec)
            assert d >= 1 and (k is None or k >= 1) and (it is None or (it >= 1 and ls >= 1))
        except (ValueError, AssertionError):
            ap.error(f"bad variant {spec!r}: expected DEVICES:CONTACTS[:ITERATIONS:LS_ITERATIONS], "
                     "e.g. 2:24, 1:all or 2:24:3:4")

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

    variants = {}
    c_same = {}  # (iterations, ls_iterations) -> MuJoCo C steps/s with those limits
    for spec in args.variants.split(","):
        v = run_variant(spec, args)
        solver = (v["solver_iterations"], v["ls_iterations"])
        if solver != (m.opt.iterations, m.opt.ls_iterations):
            if solver not in c_same:
                mv = copy.deepcopy(m)
                mv.opt.iterations, mv.opt.ls_iterations = solver
                c_same[solver] = bench_c(mv, qpos0, ctrl0, 20000 if not args.quick else 2000)
                print(f"MuJoCo C mj_step, 1 thread, iterations {solver[0]}, ls_iterations {solver[1]}: "
                      f"{c_same[solver]:,.0f} steps/s")
            v["c_steps_per_s_same_solver"] = c_same[solver]
        variants[spec] = v
        for b, r in v["mjx"].items():
            print(f"MJX {spec:>7s} ({v['contacts']} contacts, {v['constraint_rows']} rows) batch {int(b):4d}: "
                  f"{r['steps_per_s']:,.0f} physics steps/s (compile {r['compile_s']:.1f} s, run {r['run_s']:.3f} s "
                  f"for {n_steps} steps), ratio to C {r['steps_per_s'] / c_sps:.3f}", flush=True)
    head = variants[args.variants.split(",")[0]]
    render = head["render"]
    for size, r in render.items():
        print(f"render {size}x{size}, vmapped over 64 envs: {r['fps']:,.0f} frames/s (compile {r['compile_s']:.1f} s)")

    out = {
        "headline_variant": args.variants.split(",")[0],
        "mjx_steps_per_s": {k: v["steps_per_s"] for k, v in head["mjx"].items()},
        "mjx_over_c": {k: v["steps_per_s"] / c_sps for k, v in head["mjx"].items()},
        "variants": {spec: {**v, "mjx_over_c": {k: r["steps_per_s"] / c_sps for k, r in v["mjx"].items()}}
                     for spec, v in variants.items()},
        "c_steps_per_s": c_sps,
        "timing": "MJX: best of 5 calls after the compiling one; MuJoCo C: best of 5 runs after a warm-up run",
        "rollout_steps_per_s": ro_sps,
        "render_fps": {k: v["fps"] for k, v in render.items()},
        "compile_s": {
            **{f"mjx_batch_{k}": v["compile_s"] for k, v in head["mjx"].items()},
            **{f"render_{k}": v["compile_s"] for k, v in render.items()},
        },
        "run_s": {
            **{f"mjx_batch_{k}": v["run_s"] for k, v in head["mjx"].items()},
            **{f"render_{k}": v["run_s"] for k, v in render.items()},
        },
        "compile_cache": "off",
        "n_physics_steps": n_steps,
        "render_batch": 64,
        "model": {"nq": m.nq, "nv": m.nv, "ngeom": m.ngeom, "timestep": m.opt.timestep,
                  "iterations": m.opt.iterations, "ls_iterations": m.opt.ls_iterations},
        "versions": {"jax": jax.__version__, "mujoco": mujoco.__version__,
                     "python": platform.python_version(), "numpy": np.__version__},
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "command": " ".join(["python", "benchmarks/sim.py", *(argv or sys.argv[1:])]),
    }
    atomic_write_json(args.out, out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
