"""What keeping only the deepest contacts (``EnvConfig.max_contacts``), or lower solver
iteration limits, change in the tasks.

    python benchmarks/contacts.py --out benchmarks/results/contacts_2core_cpu.json \\
        --tasks place_empty_cup pick_dual_bottles handover_block banana_handover --starts 8 --keep 24
    python benchmarks/contacts.py --out solver.json --ref-keep 24 --keep 24 \
        --solver-iterations 3 --ls-iterations 4 --starts 8   # the tasks' setting vs lower limits
    python benchmarks/contacts.py --out touching.json --touching --starts 4   # most touching at once

Default mode: per task, the scripted expert from ``jax.random.split(key(2024), starts)``
and from the mirror images of those starts (2 x starts episodes, the whole step limit), once
with every contact slot (``max_contacts=None``; ``--ref-keep`` K0 for K0) and once with
``--keep`` K (and ``--solver-iterations`` / ``--ls-iterations`` when given); records the
success of each, whether the same episodes succeed, the largest ``qpos`` difference between
the two per episode, and the mirror error per episode (largest difference between the
mirrored start's trajectory and the mirror image of the start's).

``--touching``: per task, the most contact slots with a negative distance at once over the
expert's episodes (every control step, all slots kept), and the number of slots.
Resumes: tasks already in ``--out`` are skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from equibim_jax._io import atomic_write_json  # noqa: E402
from equibim_jax.experts import make_rollout  # noqa: E402
from equibim_jax.tasks import make_env, make_expert, task_names  # noqa: E402


def _starts(env, n):
    s = jax.vmap(env.reset)(jax.random.split(jax.random.key(2024), n))
    sm = jax.vmap(env.mirror_state)(s)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), s, sm)


def compare(task: str, n: int, keep: int, ref_keep: int | None = None, solver: dict | None = None) -> dict:
    """Reference (``max_contacts=ref_keep``, the model's solver limits) against the variant
    (``max_contacts=keep`` and ``solver``: ``solver_iterations`` / ``ls_iterations``)."""
    res = {}
    solver = {k: v for k, v in (solver or {}).items() if v is not None}
    for name, opts in (("ref", dict(max_contacts=ref_keep)), ("var", dict(max_contacts=keep, **solver))):
        env = make_env(task, obs=("qpos",), **opts)
        roll = make_rollout(env, make_expert(env), obs=False)

        @jax.jit
        def run():
            f, tr = jax.vmap(roll.from_state)(_starts(env, n))
            return f.info["success"], tr["qpos"]

        t0 = time.perf_counter()
        succ, q = jax.device_get(run())
        qm = np.asarray(jax.vmap(jax.vmap(env.sym.qpos))(jnp.asarray(q[:n])))
        res[name] = dict(succ=np.asarray(succ), q=q, merr=np.abs(q[n:] - qm).max(axis=(1, 2)),
                         wall=time.perf_counter() - t0)
    a, b = res["ref"], res["var"]
    d = np.abs(a["q"] - b["q"]).max(axis=(1, 2))
    return {"episodes": 2 * n, "keep": keep, "ref_keep": ref_keep, **solver, "success_all": int(a["succ"].sum()), "success_keep": int(b["succ"].sum()),
            "same_per_episode": bool((a["succ"] == b["succ"]).all()),
            "qpos_diff_median": float(np.median(d)), "qpos_diff_max": float(d.max()),
            "mirror_err_all_median": float(np.median(a["merr"])), "mirror_err_all_max": float(a["merr"].max()),
            "mirror_err_keep_median": float(np.median(b["merr"])), "mirror_err_keep_max": float(b["merr"].max()),
            "wall_s_all": a["wall"], "wall_s_keep": b["wall"]}


def touching(task: str, n: int) -> dict:
    env = make_env(task, obs=("qpos",), max_contacts=None)
    ex = make_expert(env)

    def roll(s0):
        def body(c, _):
            s, e = c
            e, a = ex.act(e, s)
            s2 = env.step(s, a, observe=False)
            return (s2, e), jnp.sum(s2.data._impl.contact.dist < 0.0)

        _, cnt = jax.lax.scan(body, (s0, ex.init(s0)), None, length=int(env.config.episode_length))
        return cnt.max()

    m = jax.device_get(jax.jit(lambda: jax.vmap(roll)(_starts(env, n)))())
    slots = int(env.reset(jax.random.key(0)).data._impl.contact.dist.shape[0])
    return {"episodes": 2 * n, "slots": slots, "most_touching": int(np.max(m))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--tasks", nargs="+", default=None, help="default: every task")
    ap.add_argument("--starts", type=int, default=8)
    ap.add_argument("--keep", type=int, default=24, help="contacts the variant keeps")
    ap.add_argument("--ref-keep", type=int, default=None, help="contacts the reference keeps (default: all)")
    ap.add_argument("--solver-iterations", type=int, default=None, help="the variant's Newton iteration limit")
    ap.add_argument("--ls-iterations", type=int, default=None, help="the variant's line-search iteration limit")
    ap.add_argument("--touching", action="store_true")
    args = ap.parse_args(argv)
    out = json.load(open(args.out)) if os.path.exists(args.out) else {"tasks": {}}
    out["command"] = " ".join(["python", "benchmarks/contacts.py", *(argv or sys.argv[1:])])
    for t in args.tasks or task_names():
        if t in out["tasks"]:
            continue
        r = touching(t, args.starts) if args.touching else compare(
            t, args.starts, args.keep, args.ref_keep,
            {"solver_iterations": args.solver_iterations, "ls_iterations": args.ls_iterations})
        out["tasks"][t] = r
        print(t, json.dumps(r), flush=True)
        atomic_write_json(args.out, out)


if __name__ == "__main__":
    main()
