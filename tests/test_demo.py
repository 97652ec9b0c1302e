"""A tiny end-to-end run of the demo path (generate -> normaliser -> two trainings -> eval on
both sides -> table, JSON, plot), then the `equibim train` / `eval` subcommands on its
dataset (resume included).

Tiny means: 2 demos, 16-point clouds, a small network, 4 training steps, 2 episodes per side.
It checks the plumbing and the output contract, not the success rates (see the README for a
real run).
"""

import dataclasses
import json
import shutil

import numpy as np
import pytest

from equibim_jax.cli import main
from equibim_jax.config import ConfigError, EvalConfig, TaskConfig, config_from_dict, load_config
from equibim_jax.data.dataset import DatasetError, load
from equibim_jax.data.generate import env_from_meta
from equibim_jax.experiments.demo import (DemoConfig, _first_call_split, format_table, load_demo_config,
                                         run_demo)
from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig
from equibim_jax.training import TrainConfig, load_run

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)

POLICY = DP3Config(pred_horizon=8, action_horizon=4, num_inference_steps=2,
                   encoder=EncoderConfig(pc_hidden=(16,), pc_out=16, state_out=16),
                   unet=UNetConfig(down_dims=(8, 16)))
POLICY_FLAGS = ["--policy.unet.down-dims", "8", "16", "--policy.encoder.pc-hidden", "16",
                "--policy.encoder.pc-out", "16", "--policy.encoder.state-out", "16",
                "--policy.pred-horizon", "8", "--policy.action-horizon", "4",
                "--policy.num-inference-steps", "2"]
TASK = TaskConfig("place_empty_cup", {"side": "left", "n_points": 16, "episode_length": 212})
TRAIN = TrainConfig(batch_size=8, sym_batch_size=4, total_steps=4, steps_per_dispatch=2, warmup_steps=1,
                    sym_norm="rms", sym_stop_gradient=True)


@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    cfg = DemoConfig(task=TASK, demos=2, policy=POLICY, train=TRAIN, eval=EvalConfig(episodes=2),
                     out_dir=str(out))
    res = run_demo(cfg, command="pytest tiny demo", progress=False)
    return out, res


@pytest.mark.slow  # builds the tiny demo (about 4 min of compiling on a cold cache); the slow suite runs it
def test_demo_outputs(tiny_demo):
    out, res = tiny_demo
    saved = json.loads((out / "demo.json").read_text())
    for name in ("baseline", "equibim"):
        for side in ("trained_side", "mirrored_side"):
            r = saved[name][side]
            assert r["episodes"] == 2 and isinstance(r["success"], float)
            lo, hi = r["ci95"]
            assert 0.0 <= lo <= r["success"] <= hi <= 1.0
            assert len(r["per_episode"]) == 2
    assert saved["baseline"]["sym_weight"] == 0.0 and saved["equibim"]["sym_weight"] == TRAIN.sym_weight > 0
    assert all(saved[n][s]["nan_actions"] == 0 for n in ("baseline", "equibim")
               for s in ("trained_side", "mirrored_side"))
    assert saved["wall_time_s"] > 0 and saved["command"] == "pytest tiny demo"
    assert saved["demos"]["episodes"] == 2
    # The baseline never ran the mirrored branch; +EquiBim did (its L_sym term is logged).
    assert saved["baseline"]["train"]["final"]["sym"] == 0.0
    assert saved["equibim"]["train"]["final"]["sym"] > 0.0
    for name in ("baseline", "equibim"):
        rows = [json.loads(l) for l in (out / "demo" / name / "train.jsonl").read_text().splitlines()]
        assert [r["step"] for r in rows] == [2, 4]
        assert all(np.isfinite(r["equiv_err"]) and r["equiv_err"] >= 0 for r in rows)
    for name in ("baseline", "equibim"):
        ol = saved[name]["open_loop_error"]
        for which in ("demos", "mirrored_demos", "equivariance"):
            assert np.isfinite(ol[which]["arm_rad"]) and ol[which]["arm_rad"] > 0
            assert 0 <= ol[which]["gripper"] <= 1
    # where the time went: every stage, compile told apart where a stage made several calls
    br = saved["timings"]["breakdown"]
    assert set(br) == {"generate", "train", "open_loop", "eval_baseline", "eval_equibim"}
    assert all(v["wall_s"] > 0 for v in br.values())
    t = br["train"]  # both runs in one program: 2 dispatches of 2 steps
    assert t["compile_s"] >= 0 and t["run_s"] > 0
    assert saved["baseline"]["train"]["train_s"] == saved["equibim"]["train"]["train_s"]
    assert t["compile_s"] + t["run_s"] == pytest.approx(saved["equibim"]["train"]["train_s"])
    assert br["generate"]["compile_s"] is None  # one chunk: nothing to compare it with
    png = (out / "demo.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    table = format_table(res)
    assert "baseline" in table and "equibim" in table and "mirrored" in table
    # The run folder holds its resolved config, which rebuilds the same DemoConfig.
    again = config_from_dict(DemoConfig, load_config(out / "demo" / "config.json"))
    assert again == DemoConfig(task=TASK, demos=2, policy=POLICY, train=TRAIN, eval=EvalConfig(episodes=2),
                               out_dir=str(out))


@pytest.mark.slow  # builds the tiny demo (about 4 min of compiling on a cold cache); the slow suite runs it
def test_sampled_action_equivariance_is_zero_for_an_equivariant_policy(tiny_demo):
    """``open_loop_errors``'s ``equivariance`` compares pi(O, z) with S pi(S O, S_a z):
    exactly 0 for zero weights (eps = 0, so DDIM only clips and scales the noise, which
    commutes with S_a), > 0 for the (barely trained, not equivariant) tiny policy."""
    import jax

    from equibim_jax.evaluation.open_loop import open_loop_errors

    out, _ = tiny_demo
    run = load_run(out / "demo" / "baseline")
    demos = load(out / "demo" / "demos.zarr")
    params = {"zero": jax.tree.map(np.zeros_like, run.state.ema_params), "trained": run.state.ema_params}
    ol = open_loop_errors(run.policy, run.normalizer, params, demos, run.make_env(), n_windows=16)
    assert ol["zero"]["equivariance"]["arm_rad"] < 1e-6
    assert ol["zero"]["equivariance"]["gripper"] < 1e-6
    assert ol["zero"]["demos"]["arm_rad"] > 1e-3  # it is not the expert, only equivariant
    assert ol["trained"]["equivariance"]["arm_rad"] > 1e-3


@pytest.mark.slow  # builds the tiny demo (about 4 min of compiling on a cold cache); the slow suite runs it
def test_demo_dataset_records_its_task_and_is_rebuildable(tiny_demo):
    out, _ = tiny_demo
    demos = load(out / "demo" / "demos.zarr")
    assert np.all(demos.success)
    assert demos.meta["task"] == "place_empty_cup" and demos.meta["task_options"]["side"] == "left"
    env = env_from_meta(dict(demos.meta))
    assert env.scene.side == "left" and env.config.n_points == 16 and env.config.episode_length == 212
    # Both runs share one normaliser (saved with each checkpoint).
    n_base = load_run(out / "demo" / "baseline").normalizer
    n_eq = load_run(out / "demo" / "equibim").normalizer
    for a, b in zip(*(jax_leaves(n.to_state_dict()) for n in (n_base, n_eq))):
        np.testing.assert_array_equal(a, b)


def jax_leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree.leaves(tree)]


@pytest.mark.slow  # compiles its own train and eval programs (the default suite keeps its budget)
def test_cli_train_resume_is_exact_and_eval(tiny_demo, tmp_path, capsys):
    out, _ = tiny_demo
    data = str(out / "demo" / "demos.zarr")
    common = ["train", "--data", data, "--policy", "dp3", "--train.batch-size", "8", "--steps", "4",
              "--train.steps-per-dispatch", "2", "--train.warmup-steps", "1", *POLICY_FLAGS]
    main(common + ["--out", str(tmp_path / "straight")])
    assert "trained to step 4" in capsys.readouterr().out
    # Same run with a checkpoint at step 2, then "crash" after it: drop the step-4 checkpoint.
    run = tmp_path / "run"
    main(common + ["--out", str(run), "--checkpoint-every", "2"])
    shutil.rmtree(run / "ckpt" / "4")
    main(common + ["--out", str(run), "--checkpoint-every", "2"])  # resumes from step 2
    rows = [json.loads(l) for l in (run / "train.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [2, 4]
    a, b = load_run(tmp_path / "straight").state, load_run(run).state
    for x, y in zip(jax_leaves(a.ema_params), jax_leaves(b.ema_params)):
        np.testing.assert_array_equal(x, y)
    # A changed setting is refused rather than silently mixed into the old run.
    with pytest.raises(Exception, match="different config"):
        main(common + ["--out", str(run), "--train.sym-weight", "0.5"])
    # config.json repeats the run: --config with a new folder gives the same parameters.
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["policy"]["name"] == "dp3" and cfg["train"]["total_steps"] == 4 and cfg["devices"] >= 1
    main(["train", "--config", str(run / "config.json"), "--data", data, "--out", str(tmp_path / "again")])
    c = load_run(tmp_path / "again").state
    for x, y in zip(jax_leaves(a.ema_params), jax_leaves(c.ema_params)):
        np.testing.assert_array_equal(x, y)
    main(["eval", str(run), "--episodes", "2", "--out", str(tmp_path / "eval.json")])
    printed = capsys.readouterr().out
    assert "trained" in printed and "mirrored" in printed
    res = json.loads((tmp_path / "eval.json").read_text())
    assert res["trained"]["episodes"] == 2 and res["mirrored"]["episodes"] == 2


@pytest.mark.slow  # builds the tiny demo (about 4 min of compiling on a cold cache); the slow suite runs it
def test_cli_generate_refuses_to_overwrite(tiny_demo, capsys):
    out, _ = tiny_demo
    before = sorted(p.name for p in (out / "demo" / "demos.zarr").iterdir())
    with pytest.raises(FileExistsError, match="overwrite"):
        main(["generate", "--task", "place_empty_cup", "--out", str(out / "demo" / "demos.zarr"),
              "--episodes", "1"])
    assert sorted(p.name for p in (out / "demo" / "demos.zarr").iterdir()) == before
    load(out / "demo" / "demos.zarr")


def test_train_rejects_a_dataset_without_its_task(tmp_path):
    from equibim_jax.data.dataset import Demos, save
    from equibim_jax.training import train

    demos = Demos(obs={"qpos": np.zeros((1, 4, 14), np.float32)}, action=np.zeros((1, 4, 14), np.float32),
                  length=np.array([4], np.int32), success=np.array([True]), meta={"task": "place_empty_cup"})
    save(demos, tmp_path / "d.zarr")
    with pytest.raises(DatasetError, match="task_options"):
        train(tmp_path / "d.zarr", tmp_path / "run", POLICY)


def test_bad_settings_are_refused_with_a_clear_message(tmp_path):
    with pytest.raises(ValueError, match="side must be one of"):
        TaskConfig("place_empty_cup", {"side": "middle"}).make_env()
    with pytest.raises(ValueError, match="unknown task"):
        TaskConfig("fold_towel").make_env()
    with pytest.raises(ValueError, match="multiple of"):
        TrainConfig(total_steps=120, steps_per_dispatch=50)
    with pytest.raises(ValueError, match="sym_weight"):
        DemoConfig(train=TrainConfig(sym_weight=0.0))
    with pytest.raises(ValueError, match="sym_batch_size"):
        TrainConfig(batch_size=8, sym_batch_size=16)
    bad = tmp_path / "bad.json"
    bad.write_text('{"demos": 2, "colour": "red"}')
    with pytest.raises(ConfigError, match="colour"):
        load_demo_config(str(bad))
    bad.write_text('{"policy": {"name": "no_such_policy"}}')
    with pytest.raises(ConfigError, match="unknown policy"):
        load_demo_config(str(bad))


def test_the_main_demo_config_file_is_the_documented_experiment():
    cfg = load_demo_config()
    assert cfg.task == TaskConfig("place_empty_cup", {"side": "left", "obs": ["qpos", "point_cloud"],
                                                      "action": "joint", "n_points": 64, "episode_length": 240})
    assert (cfg.demos, cfg.train.batch_size, cfg.train.total_steps, cfg.train.sym_batch_size) == (48, 32, 7000, 16)
    assert (cfg.train.sym_weight, cfg.train.sym_norm, cfg.train.sym_stop_gradient) == (0.1, "rms", True)
    assert cfg.policy.unet.down_dims == (32, 64, 128) and cfg.eval.episodes == 32


def test_demo_train_configs_differ_only_in_l_sym():
    cfg = DemoConfig(train=TrainConfig(sym_stop_gradient=True, sym_warmup_steps=100, sym_batch_size=16))
    runs = cfg.run_configs()
    base, eq = runs["baseline"], runs["equibim"]
    assert (base.sym_warmup_steps, eq.sym_warmup_steps) == (0, 100)
    assert (base.sym_batch_size, eq.sym_batch_size) == (None, 16)
    assert (base.sym_weight, base.sym_stop_gradient, base.uses_mirror) == (0.0, False, False)
    assert (eq.sym_weight, eq.sym_stop_gradient, eq.uses_mirror) == (cfg.train.sym_weight, True, True)
    assert dataclasses.replace(eq, sym_weight=0.0, sym_stop_gradient=False, sym_warmup_steps=0,
                               sym_batch_size=None) == base


@pytest.mark.slow  # long compile; CI runs it with the slow suite
def test_mirrored_demo_replays_as_a_right_side_success(tiny_demo):
    """S on the data: the mirrored actions of a left demo, replayed from the mirror image of
    its initial state, succeed and follow the mirrored demo (the mirrored-side windows that
    L_sym and the open-loop metric use are real right-side expert behaviour)."""
    import jax
    import jax.numpy as jnp

    out, _ = tiny_demo
    demos = load(out / "demo" / "demos.zarr")
    env = env_from_meta(dict(demos.meta))
    n = int(demos.length[0])

    @jax.jit  # one program: the demo's start, its mirror image, the mirrored actions replayed
    def replay(key, acts):
        s0 = env.reset(key)
        def body(s, a):
            s = env.step(s, a)
            return s, (s.obs["qpos"], s.info["success"])
        return s0.obs["qpos"], jax.lax.scan(body, env.mirror_state(s0), jax.vmap(env.action_symmetry)(acts))[1]

    key = jax.random.fold_in(jax.random.key(demos.meta["seed"]), 0)
    q0, (qpos, success) = replay(key, jnp.asarray(demos.action[0, :n]))
    np.testing.assert_array_equal(np.asarray(q0), demos.obs["qpos"][0, 0])
    expected = jax.vmap(env.obs_symmetry.ops["qpos"])(jnp.asarray(demos.obs["qpos"][0, 1:n]))
    assert bool(success[-1])
    assert float(jnp.abs(qpos[:-1] - expected).max()) < 1e-3  # rad; measured 1e-4


def test_first_call_split():
    assert _first_call_split(10.0, 16.0, 4) == {"compile_s": 8.0, "run_s": 8.0}  # later calls 2 s each
    assert _first_call_split(1.0, 4.0, 2) == {"compile_s": 0.0, "run_s": 4.0}  # no excess: no compile
    assert _first_call_split(5.0, 5.0, 1) == {"compile_s": None, "run_s": None}
    assert _first_call_split(None, 5.0, 3) == {"compile_s": None, "run_s": None}
