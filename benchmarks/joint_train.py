"""Does training baseline and +EquiBim together beat training them one after the other?
Writes JSON.

Two ways of running the two runs of ``make demo-long`` (the demo's DP3 policy at batch 64,
``L_sym`` on the whole batch, no stop-gradient) at the same time, against each alone:

- ``one_program``: both runs' steps in one jitted ``lax.scan`` body (one compile; XLA may
  overlap their independent operations);
- ``two_devices``: the host CPU split into two XLA devices, one run on each, dispatched
  without waiting (measured in a child process, since the device count is fixed at
  start-up).

Every program is compiled with the package's train-step XLA options
(``equibim_jax._xla_options.train_compiler_options``), as ``make_train_loop`` does.
Seconds per dispatch of K steps are the median of ``--repeats`` dispatches after a first,
compiling one (whose excess is reported as compile time). The persistent compilation cache
is off. Demos: ``--demos`` expert demos of the demo's task, generated here.

    python benchmarks/joint_train.py --out benchmarks/results/joint_train_2core_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time


def _setup(demos_path: str, n_demos: int):
    import jax

    import equibim_jax
    from equibim_jax.data.dataset import load
    from equibim_jax.data.generate import generate_dataset
    from equibim_jax.experiments.demo import load_demo_config
    from equibim_jax.policies import make_policy
    from equibim_jax.training.run import prepare_data

    equibim_jax.disable_compilation_cache()
    cfg = load_demo_config()
    tc = dataclasses.replace(cfg.train, batch_size=64, total_steps=10000, sym_stop_gradient=False,
                             sym_batch_size=None)
    cfg = dataclasses.replace(cfg, train=tc)
    env = cfg.task.make_env()
    if os.path.exists(demos_path):
        demos = load(demos_path)
    else:
        demos, _ = generate_dataset(env, demos_path, n_demos, seed=0, progress=False)
    prep = prepare_data(demos, env, cfg.policy)
    policy = make_policy(prep.policy_config.name, prep.policy_config)
    return jax, cfg, prep, policy


def _time(fn, repeats: int) -> dict:
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    med = statistics.median(ts)
    return {"s_per_dispatch": med, "compile_s": max(first - med, 0.0), "all_s": ts}


def one_process(demos_path: str, n_demos: int, k: int, repeats: int) -> dict:
    """Each run alone and both in one program, on this process's devices."""
    jax, cfg, prep, policy = _setup(demos_path, n_demos)
    from equibim_jax._xla_options import train_compiler_options
    from equibim_jax.training.train_step import base_key, build_step_fn, create_train_state

    opts = train_compiler_options()
    runs = cfg.run_configs()
    fns = {n: build_step_fn(c, prep.sym if c.uses_mirror else None) for n, c in runs.items()}
    states = {n: create_train_state(policy, c) for n, c in runs.items()}
    keys = {n: base_key(c) for n, c in runs.items()}
    out = {}
    for n in runs:
        loop = jax.jit(lambda s, key, d, f=fns[n]: jax.lax.scan(lambda c, _: f(c, key, d), s, None, length=k),
                       compiler_options=opts)
        out[n] = _time(lambda: loop(states[n], keys[n], prep.dataset), repeats)

    @functools.partial(jax.jit, compiler_options=opts)
    def pair(ss, ks, d):
        def body(c, _):
            outs = tuple(fns[n](s, kk, d) for n, s, kk in zip(runs, c, ks))
            return tuple(o[0] for o in outs), tuple(o[1] for o in outs)
        return jax.lax.scan(body, ss, None, length=k)

    out["one_program"] = _time(lambda: pair(tuple(states.values()), tuple(keys.values()), prep.dataset), repeats)
    return out


def two_devices(demos_path: str, n_demos: int, k: int, repeats: int) -> dict:
    """One run per CPU device, dispatched together (needs 2 devices in this process)."""
    jax, cfg, prep, policy = _setup(demos_path, n_demos)
    from equibim_jax._xla_options import train_compiler_options
    from equibim_jax.training.train_step import base_key, build_step_fn, create_train_state

    runs = cfg.run_configs()
    devs = jax.devices()[:2]
    args, loops = {}, {}
    for (n, c), d in zip(runs.items(), devs):
        f = build_step_fn(c, prep.sym if c.uses_mirror else None)
        loops[n] = jax.jit(lambda s, key, data, f=f: jax.lax.scan(lambda c, _: f(c, key, data), s, None, length=k),
                           compiler_options=train_compiler_options())
        args[n] = jax.device_put((create_train_state(policy, c), base_key(c), prep.dataset), d)
    out = {f"{n}_alone_on_{i}": _time(lambda n=n: loops[n](*args[n]), repeats) for i, n in enumerate(runs)}
    out["both"] = _time(lambda: [loops[n](*args[n]) for n in runs], repeats)
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="results/joint_train.json")
    p.add_argument("--demos", type=int, default=8)
    p.add_argument("--k", type=int, default=50, help="steps per dispatch")
    p.add_argument("--repeats", type=int, default=4)
    p.add_argument("--child", choices=["two_devices"], help=argparse.SUPPRESS)
    p.add_argument("--demos-path", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        print(json.dumps(two_devices(a.demos_path, a.demos, a.k, a.repeats)))
        return
    import jax

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "demos.zarr")
        one = one_process(path, a.demos, a.k, a.repeats)
        env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
        res = subprocess.run([sys.executable, __file__, "--child", "two_devices", "--demos-path", path,
                              "--demos", str(a.demos), "--k", str(a.k), "--repeats", str(a.repeats)],
                             env=env, capture_output=True, text=True, check=True)
        two = json.loads(res.stdout.strip().splitlines()[-1])
    sep = one["baseline"]["s_per_dispatch"] + one["equibim"]["s_per_dispatch"]
    result = {
        "benchmark": "joint_train", "k": a.k, "batch_size": 64, "demos": a.demos, "repeats": a.repeats,
        "one_device": one, "two_devices": two,
        "separate_s_per_dispatch": sep,
        "speedup_one_program": sep / one["one_program"]["s_per_dispatch"],
        "speedup_two_devices": sep / two["both"]["s_per_dispatch"],
        "both_runs_10k_steps_s": {"separate": sep * 10000 / a.k,
                                  "one_program": one["one_program"]["s_per_dispatch"] * 10000 / a.k,
                                  "two_devices": two["both"]["s_per_dispatch"] * 10000 / a.k},
        "env": {"jax": jax.__version__, "python": platform.python_version(), "cpus": os.cpu_count()},
    }
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    tmp_out = a.out + ".tmp"
    with open(tmp_out, "w") as f:
        json.dump(result, f, indent=1)
    os.replace(tmp_out, a.out)
    print(json.dumps({k: v for k, v in result.items() if k.startswith(("speedup", "both", "separate"))}, indent=1))


if __name__ == "__main__":
    main()
