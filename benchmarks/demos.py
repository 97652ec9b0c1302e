"""Demo-generation benchmark: 50 expert demos per task with rendered observations.

    python benchmarks/demos.py --out benchmarks/results/demos_2core_cpu.json [--tasks T ...]

For each task: the compiled batch rollout that ``equibim generate`` runs
(``equibim_jax.data.generate.make_demo_rollout``), with the head-camera image (64x64 by
default) and ``qpos`` observed every step. Compile time is the first call's time minus a
second call's on the same shapes; the generation time is then a full
``generate_demos(..., n_episodes=50)`` on the compiled program (rendering, the host copy
and the episode bookkeeping included). Reported per task: demos/s, env-steps/s (control
steps of every simulated episode, kept or not), physics steps/s, and MuJoCo C's
``mj_step`` rate on the same model measured in the same run (one core, one env) as the
reference. Tasks already in ``--out`` with the same settings are skipped (reruns resume).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import jax
import mujoco
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from equibim_jax._io import atomic_write_json  # noqa: E402
from equibim_jax.data.generate import default_length, generate_demos, make_demo_rollout  # noqa: E402
from equibim_jax.tasks import make_env, task_entry, task_names  # noqa: E402


def mujoco_c_steps_per_s(model: mujoco.MjModel, qpos: np.ndarray, ctrl: np.ndarray, seconds: float = 2.0) -> float:
    """Physics steps per second of MuJoCo C (``mj_step``, one env, one thread)."""
    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    d.ctrl[:] = ctrl
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(100):
            mujoco.mj_step(model, d)
        n += 100
    return n / (time.perf_counter() - t0)


def bench_task(task: str, n_demos: int, obs: tuple[str, ...], image_size: int, chunk: int) -> dict:
    env = make_env(task, obs=obs, image_size=image_size)
    length = default_length(env)
    roll = make_demo_rollout(env, length)
    keys = jax.random.split(jax.random.key(123), 2 * chunk)
    t0 = time.perf_counter()
    jax.block_until_ready(roll(keys[:chunk]))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(roll(keys[chunk:]))
    second = time.perf_counter() - t0
    t0 = time.perf_counter()
    demos, stats = generate_demos(env, jax.random.key(0), n_demos, chunk=chunk, rollout=roll, progress=False)
    gen_s = time.perf_counter() - t0
    env_steps = stats["attempts"] * length
    ref = mujoco_c_steps_per_s(env.mj_model, env.home_qpos, env.home_ctrl)
    phys = env_steps * env.n_substeps / gen_s
    return {
        "demos": n_demos, "obs": list(obs), "image_size": image_size, "chunk": chunk,
        "rollout_length": length, "attempts": stats["attempts"], "kept": stats["kept"],
        "compile_s": first - second, "first_call_s": first, "chunk_call_s": second,
        "generate_s": gen_s, "demos_per_s": n_demos / gen_s, "env_steps_per_s": env_steps / gen_s,
        "physics_steps_per_s": phys, "substeps": env.n_substeps,
        "mujoco_c_steps_per_s": ref, "ratio_to_mujoco_c": phys / ref,
        "frames_per_s": env_steps / gen_s if "image" in obs else None,
        "demo_steps": int(demos.n_steps),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write (and resume from)")
    ap.add_argument("--tasks", nargs="*", default=None, help="tasks (default: every task with an expert)")
    ap.add_argument("--demos", type=int, default=50)
    ap.add_argument("--obs", default="qpos,image", help="observed fields, comma separated")
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--chunk", type=int, default=25, help="episodes per compiled call (<= 32 on the CPU)")
    args = ap.parse_args()
    tasks = args.tasks or [n for n in task_names() if task_entry(n).expert is not None]
    obs = tuple(f.strip() for f in args.obs.split(",") if f.strip())
    out = {}
    if os.path.exists(args.out):
        import json

        out = json.load(open(args.out))
    out.setdefault("tasks", {})
    out["meta"] = {"jax": jax.__version__, "mujoco": mujoco.__version__, "backend": jax.default_backend(),
                   "cpus": os.cpu_count(), "platform": platform.platform(),
                   "command": "python benchmarks/demos.py " + " ".join(sys.argv[1:])}
    for task in tasks:
        old = out["tasks"].get(task)
        if old and (old["demos"], old["obs"], old["image_size"], old["chunk"]) == (
                args.demos, list(obs), args.image_size, args.chunk):
            print(f"{task}: done already, skipped")
            continue
        r = bench_task(task, args.demos, obs, args.image_size, args.chunk)
        out["tasks"][task] = r
        atomic_write_json(args.out, out)
        print(f"{task}: {r['demos']} demos in {r['generate_s']:.1f} s after {r['compile_s']:.1f} s compile; "
              f"{r['env_steps_per_s']:.0f} env-steps/s, {r['ratio_to_mujoco_c']:.2f}x MuJoCo C")


if __name__ == "__main__":
    main()
