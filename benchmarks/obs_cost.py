"""What observing costs in an env step: ``env.step`` with and without the observation.

    python benchmarks/obs_cost.py --out benchmarks/results/obs_cost_2core_cpu.json

For each observation set, ``jit(scan(vmap(env.step)))`` over ``--steps`` control steps of
``--envs`` ``place_empty_cup`` envs; compile (first call) is reported apart from the run
(median of ``--repeats`` later calls). ``observe=False`` steps the same physics and keeps
the old observation, which is what the closed-loop rollout does for the steps its policy
never reads. Writes JSON; nothing here is asserted.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax import make_env
from equibim_jax._io import atomic_write_json


def _time(fn, *args, repeats):
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t)
    return compile_s, float(np.median(runs))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--envs", type=int, default=32)
    p.add_argument("--steps", type=int, default=48)
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    rows = []
    for obs, observe in ((("qpos", "point_cloud"), True), (("qpos", "point_cloud"), False), (("qpos",), True)):
        env = make_env("place_empty_cup", obs=obs, action="joint", side="left", n_points=64)
        s = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), a.envs))
        act = s.obs["qpos"]  # hold the arms where they start (joint targets = current pose)

        def run(s, act=act, env=env, observe=observe):
            body = lambda s, _: (jax.vmap(lambda x, u: env.step(x, u, observe=observe))(s, act), None)
            return jax.lax.scan(body, s, None, length=a.steps)[0]

        compile_s, run_s = _time(jax.jit(run), s, repeats=a.repeats)
        rows.append({"obs": list(obs), "observe": observe, "compile_s": compile_s, "run_s": run_s,
                     "ms_per_env_step": 1e3 * run_s / (a.steps * a.envs)})
        print(json.dumps(rows[-1]))
    full = rows[0]["ms_per_env_step"]
    out = {"benchmark": "env.step with and without observing (place_empty_cup, robot A)",
           "jax": jax.__version__, "python": platform.python_version(), "device": jax.default_backend(),
           "config": vars(a), "rows": rows,
           "observe_false_over_full": rows[1]["ms_per_env_step"] / full,
           "qpos_only_over_full": rows[2]["ms_per_env_step"] / full}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(a.out, out)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
