"""Data parallelism (``equibim_jax._sharding``): 1 and 2 devices give the same run.

The device count of a JAX process is fixed when its backend starts, so each check runs
this file as a script in fresh subprocesses, once with one CPU device and once with
``XLA_FLAGS=--xla_force_host_platform_device_count=2``; the rest of the suite keeps its
single device. Each subprocess gets its own empty compilation cache
(``EQUIBIM_JAX_CACHE_DIR``), so the timings are those of a cold start.

What is checked: a tiny offline training run through ``equibim_jax.training.train`` gives
the same losses per step on 1 and 2 devices (up to float reordering in the sharded
gradient sum), with the sampled batch really split over 2 devices and ``config.json``
recording the mesh; on 1 device the traced step is the unsharded one; a run started on 1
device resumes on 2. The slow test checks that a paired closed-loop evaluation gives the
same per-episode successes, first-success steps and (to ``QPOS_ATOL``) final states.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

HERE = Path(__file__).resolve()
LOSS_RTOL = 1e-4  # float reordering of the sharded batch sums only
QPOS_ATOL = 1e-5  # m or rad, final state of an 8-step episode
TWO_DEVICES = "--xla_force_host_platform_device_count=2"


# ----------------------------------------------------------------------------- subprocess side


def _tiny_policy_config():
    """test_demo.py's tiny DP3 made narrower, with one U-Net level: its cold init and
    compiles are what this file's subprocesses spend most of their time on."""
    from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig

    return DP3Config(pred_horizon=8, action_horizon=4, num_inference_steps=2,
                     encoder=EncoderConfig(pc_hidden=(8,), pc_out=8, state_out=8, state_hidden=(8,)),
                     unet=UNetConfig(down_dims=(8,)))


def _tiny_demos(env, episodes=4, length=24, seed=0):
    """Hand-made demos of ``env``'s observation fields (no simulation): smooth joint paths
    around the home pose, the next pose as the action, a noisy cloud per frame."""
    from equibim_jax.data.dataset import Demos

    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, length + 1)[None, :, None]
    qpos = env.home_qpos[None, None, :14] + 0.2 * np.sin(
        2 * np.pi * (t + rng.uniform(0, 1, (episodes, 1, 14))))
    n_points = env.config.n_points
    cloud = rng.normal(0.0, 0.1, (episodes, length, n_points, 3)) + np.array([0.3, 0.0, 0.1])
    return Demos(obs={"qpos": qpos[:, :-1].astype(np.float32), "point_cloud": cloud.astype(np.float32)},
                 action=qpos[:, 1:].astype(np.float32), length=np.full(episodes, length, np.int32),
                 success=np.ones(episodes, bool), meta={})


TRAIN_KW = dict(batch_size=8, sym_batch_size=4, total_steps=4, steps_per_dispatch=2, warmup_steps=1, seed=3)


def _train_check(out_dir: Path) -> dict:
    """Train 4 steps (2 dispatches) on this process's devices, look at the sharding of a
    batch as the train step constrains it, and (on 1 device) leave a run stopped after its
    first dispatch in ``out_dir / "partial"`` for :func:`_resume_check`."""
    import jax

    from equibim_jax import make_env
    from equibim_jax._sharding import constrain_batch, data_mesh, shard_batch
    from equibim_jax.data.windows import sample_batch
    from equibim_jax.policies import make_policy
    from equibim_jax.training import TrainConfig, read_log, train
    from equibim_jax.training.run import prepare_data
    from equibim_jax.training.train_step import build_step_fn, create_train_state

    env = make_env("place_empty_cup", obs=("qpos", "point_cloud"), n_points=16)
    demos = _tiny_demos(env)
    tc = TrainConfig(**TRAIN_KW)
    run_dir = out_dir / "run"
    train(demos, run_dir, _tiny_policy_config(), tc, env=env, progress=False)
    if jax.device_count() == 1:
        train(demos, out_dir / "partial", _tiny_policy_config(), tc, env=env, progress=False, max_wall_s=0)
    rows = read_log(run_dir / "train.jsonl")
    config = json.loads((run_dir / "config.json").read_text())

    mesh = data_mesh()
    data = prepare_data(demos, env, _tiny_policy_config())
    inside = jax.jit(lambda d, k: constrain_batch(sample_batch(d, k, 8), mesh))(data.dataset, jax.random.key(0))
    outside = shard_batch({"x": np.zeros((8, 3), np.float32)}, mesh)
    same_program = None
    if mesh.size == 1:  # the step traced with the (trivial) mesh is the unsharded one
        policy = make_policy(data.policy_config.name, data.policy_config)
        state = jax.eval_shape(lambda: create_train_state(policy, tc))
        key = jax.eval_shape(lambda: jax.random.key(0))
        same_program = len({jax.jit(build_step_fn(tc, data.sym, mesh=m)).lower(state, key, data.dataset).as_text()
                            for m in (None, mesh)}) == 1
    bad_batch = None
    if mesh.size > 1:
        try:
            shard_batch({"x": np.zeros((3, 2))}, mesh)
        except ValueError as e:
            bad_batch = str(e)
    return {"devices": jax.device_count(), "config_devices": config["devices"], "mesh": config["mesh"],
            "rows": rows, "batch_shards": len(inside["action"].addressable_shards),
            "batch_shard_rows": [int(s.data.shape[0]) for s in inside["action"].addressable_shards],
            "outside_shards": len(getattr(outside["x"], "addressable_shards", [None])), "bad_batch_error": bad_batch,
            "same_program": same_program}


def _resume_check(run_dir: Path) -> dict:
    """Continue the run in ``run_dir`` (stopped at step 2) to step 4 on this process's devices."""
    import jax

    from equibim_jax import make_env
    from equibim_jax.training import TrainConfig, read_log, train

    env = make_env("place_empty_cup", obs=("qpos", "point_cloud"), n_points=16)
    tc = TrainConfig(**TRAIN_KW)
    res = train(_tiny_demos(env), run_dir, _tiny_policy_config(), tc, env=env, progress=False)
    return {"devices": jax.device_count(), "resumed_from": res["resumed_from"], "steps": res["steps"],
            "rows": read_log(run_dir / "train.jsonl")}


def _eval_check() -> dict:
    """A paired evaluation (4 episodes per side, one batch of 8) of a random tiny policy in
    the 8-step box env of ``tests/test_eval_rollout.py``."""
    import jax

    from equibim_jax.data import fit_normalizer
    from equibim_jax.evaluation.rollout import _run_paired, _runner, evaluate_sides, make_policy_rollout
    from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig, make_policy
    from equibim_jax.sim.env import Env, EnvConfig
    from equibim_jax.sim.scenes import BoxScene

    env = Env(EnvConfig(obs=("qpos", "point_cloud"), n_points=32, episode_length=8), BoxScene())
    cfg = DP3Config(action_dim=env.action_size, state_dim=env.action_size, obs_horizon=1, pred_horizon=4,
                    action_horizon=4, encoder=EncoderConfig(pc_hidden=(8,), pc_out=8, state_out=8,
                                                            state_hidden=(8,)),
                    unet=UNetConfig(down_dims=(8,)), num_inference_steps=2)
    policy = make_policy("dp3", cfg)
    params = policy.init(jax.random.key(0))
    rng = np.random.default_rng(0)
    home = env.home_qpos[:14]
    frames = {"qpos": home[None] + rng.normal(0, 0.1, (20, 14)),
              "point_cloud": rng.normal(0, 0.1, (20, 32, 3)) + np.array([0.3, 0.0, 0.1]),
              "action": home[None] + rng.normal(0, 0.3, (20, 14))}
    norm = fit_normalizer(frames, env.symmetry_ops(("qpos", "point_cloud")))
    roll = make_policy_rollout(env, policy, norm, record_qpos=False)
    res = evaluate_sides(roll, params, jax.random.key(7), 4, chunk=8)
    # The same compiled runner again, for the final joint positions of every episode.
    qpos, _, _ = _run_paired(_runner(roll), params, jax.random.key(7), 4, 8, ("trained", "mirrored"),
                             ("final_qpos",), False, "")
    return {"devices": jax.device_count(),
            **{side: {**{k: r[k] for k in ("per_episode", "first_success_step", "nan_actions")},
                      "final_qpos": qpos[side]["final_qpos"].tolist()}
               for side, r in res.items()}}


def _worker(what: str, out: Path) -> None:
    t0 = time.perf_counter()
    if what == "train":
        res = _train_check(out.parent)
    elif what == "resume":
        res = _resume_check(out.parent.parent / "dev1" / "partial")
    elif what == "eval":
        res = _eval_check()
    else:
        raise SystemExit(f"unknown check {what!r}")
    res["wall_s"] = time.perf_counter() - t0
    out.write_text(json.dumps(res))


# ----------------------------------------------------------------------------- pytest side


def _env(devices: int, cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if "device_count" not in f]
    if devices == 2:
        flags.append(TWO_DEVICES)
    if flags:
        env["XLA_FLAGS"] = " ".join(flags)
    env.update(JAX_PLATFORMS="cpu", EQUIBIM_JAX_CACHE_DIR=str(cache), PYTHONPATH=str(HERE.parents[1]))
    return env


def _start(what: str, devices: int, work: Path) -> tuple[subprocess.Popen, Path]:
    work.mkdir(parents=True, exist_ok=True)
    out = work / f"{what}.json"
    proc = subprocess.Popen([sys.executable, str(HERE), what, str(out)], env=_env(devices, work / "xla"),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc, out


def _finish(proc: subprocess.Popen, out: Path, timeout: float = 600) -> dict:
    log, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, f"subprocess failed ({proc.returncode}):\n{log[-4000:]}"
    return json.loads(out.read_text())


def _run_both(what: str, tmp_path: Path) -> tuple[dict, dict]:
    """Run check ``what`` on 1 and 2 devices, in parallel (one core each)."""
    jobs = [_start(what, n, tmp_path / f"dev{n}") for n in (1, 2)]
    return tuple(_finish(*job) for job in jobs)


def _losses(rows: list[dict]) -> np.ndarray:
    return np.array([[r[m] for m in ("bc", "sym", "total", "grad_norm")] for r in rows])


@pytest.mark.slow  # two cold subprocesses on both cores (the default suite keeps its budget)
def test_training_on_two_devices_matches_one_and_resumes_across_device_counts(tmp_path):
    one, two = _run_both("train", tmp_path)
    assert (one["devices"], two["devices"]) == (1, 2)
    assert (one["config_devices"], one["mesh"]) == (1, {"data": 1})
    assert (two["config_devices"], two["mesh"]) == (2, {"data": 2})
    # On 2 devices the batch is split in halves, one per device; on 1 it is whole.
    assert (one["batch_shards"], two["batch_shards"]) == (1, 2)
    assert two["batch_shard_rows"] == [4, 4] and two["outside_shards"] == 2
    assert "batch size 3 is not divisible by the device count 2" in two["bad_batch_error"]
    assert one["same_program"]  # on 1 device sharding adds nothing to the traced step
    l1, l2 = _losses(one["rows"]), _losses(two["rows"])
    assert l1.shape == (2, 4) and np.all(np.isfinite(l1))
    np.testing.assert_allclose(l2, l1, rtol=LOSS_RTOL)
    # A run stopped after one dispatch on 1 device resumes on 2 (devices and mesh are not
    # part of the checkpoint's config) and ends as the uninterrupted 1-device run did.
    proc, out = _start("resume", 2, tmp_path / "dev2")  # dev2's cache: the 2-device compiles
    res = _finish(proc, out)
    assert (res["devices"], res["resumed_from"], res["steps"]) == (2, 2, 4)
    np.testing.assert_allclose(_losses(res["rows"]), l1, rtol=LOSS_RTOL)


def test_helpers_are_no_ops_on_one_device_and_refuse_uneven_batches():
    import jax

    from equibim_jax._sharding import (check_divisible, constrain_batch, data_mesh, mesh_shape, replicate,
                                       round_up, shard_batch)

    mesh = data_mesh()
    assert mesh is data_mesh() and mesh_shape(mesh) == {"data": jax.device_count()}
    if jax.device_count() == 1:  # the suite's own process; the subprocesses cover 2
        tree = {"x": np.arange(6.0).reshape(3, 2)}
        assert shard_batch(tree, mesh) is tree and replicate(tree, mesh) is tree
        assert constrain_batch(tree, mesh) is tree and round_up(3, mesh) == 3
    check_divisible(8, None)
    with pytest.raises(ValueError, match="batch size 7 is not divisible by the device count 2"):
        check_divisible(7, SimpleNamespace(size=2))  # only the mesh's size is read


def test_distributed_opt_in_reads_the_environment():
    from equibim_jax._sharding import distributed_args, distributed_requested

    assert not distributed_requested({})
    assert not distributed_requested({"EQUIBIM_JAX_DISTRIBUTED": "0"})
    assert distributed_requested({"EQUIBIM_JAX_DISTRIBUTED": "1"})
    env = {"JAX_COORDINATOR_ADDRESS": "10.0.0.1:1234", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"}
    assert distributed_requested(env)
    assert distributed_args(env) == {"num_processes": 2, "process_id": 1}
    assert distributed_args({}) == {}
    with pytest.raises(ValueError, match="JAX_PROCESS_ID must be an integer"):
        distributed_args({"JAX_PROCESS_ID": "one"})


@pytest.mark.slow
def test_evaluation_on_two_devices_matches_one(tmp_path):
    one, two = _run_both("eval", tmp_path)
    assert (one["devices"], two["devices"]) == (1, 2)
    for side in ("trained", "mirrored"):
        q1, q2 = (np.array(r[side].pop("final_qpos")) for r in (one, two))
        assert one[side] == two[side], side  # successes, first-success steps, NaN counts
        np.testing.assert_allclose(q2, q1, atol=QPOS_ATOL)


if __name__ == "__main__":
    _worker(sys.argv[1], Path(sys.argv[2]))
