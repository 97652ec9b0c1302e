"""A tiny end-to-end run of the demo path (generate -> normaliser -> two trainings -> eval on
both sides -> table, JSON, plot), then the `equibim train` / `eval` subcommands on its
dataset (resume included).

Tiny means: 2 demos, 16-point clouds, a small network, 4 training steps, 2 episodes per side.
It checks the plumbing and the output contract, not the success rates (see the README for a
real run).
"""

import json
import shutil

import numpy as np
import pytest

from equibim_jax.cli import main
from equibim_jax.experiments.demo import DemoConfig, format_table, run_demo
from equibim_jax.experiments.pipeline import EnvSpec, ModelOptions, env_spec_of, load_policy
from equibim_jax.data.dataset import DatasetError, load

MODEL = ModelOptions(down_dims=(8, 16), pc_hidden=(16,), pc_out=16, state_out=16,
                     pred_horizon=8, action_horizon=4, num_inference_steps=2)
MODEL_FLAGS = ["--model.down-dims", "8", "16", "--model.pc-hidden", "16", "--model.pc-out", "16",
               "--model.state-out", "16", "--model.pred-horizon", "8", "--model.action-horizon", "4",
               "--model.num-inference-steps", "2"]
ENV = EnvSpec(n_points=16, episode_length=212)


@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    cfg = DemoConfig(env=ENV, n_demos=2, model=MODEL, batch_size=8, sym_batch_size=4, train_steps=4,
                     steps_per_dispatch=2, warmup_steps=1, eval_episodes=2, out_dir=str(out))
    res = run_demo(cfg, command="pytest tiny demo", progress=False)
    return out, res


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
    assert saved["baseline"]["sym_weight"] == 0.0 and saved["equibim"]["sym_weight"] == DemoConfig().sym_weight > 0
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
    png = (out / "demo.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    table = format_table(res)
    assert "baseline" in table and "equibim" in table and "mirrored (right)" in table


def test_sampled_action_equivariance_is_zero_for_an_equivariant_policy(tiny_demo):
    """``open_loop_errors``'s ``equivariance`` compares pi(O, z) with S pi(S O, S_a z):
    exactly 0 for zero weights (eps = 0, so DDIM only clips and scales the noise, which
    commutes with S_a), > 0 for the (barely trained, not equivariant) tiny policy."""
    import jax

    from equibim_jax.experiments.pipeline import open_loop_errors

    out, _ = tiny_demo
    model, state, normalizer, config = load_policy(out / "demo" / "baseline")
    demos = load(out / "demo" / "demos.zarr")
    params = {"zero": jax.tree.map(np.zeros_like, state.ema_params), "trained": state.ema_params}
    ol = open_loop_errors(model, normalizer, params, demos, config["env_spec"].make(), n_windows=16)
    assert ol["zero"]["equivariance"]["arm_rad"] < 1e-6
    assert ol["zero"]["equivariance"]["gripper"] < 1e-6
    assert ol["zero"]["demos"]["arm_rad"] > 1e-3  # it is not the expert, only equivariant
    assert ol["trained"]["equivariance"]["arm_rad"] > 1e-3


def test_demo_dataset_is_left_only_and_rebuildable(tiny_demo):
    out, _ = tiny_demo
    demos = load(out / "demo" / "demos.zarr")
    assert np.all(demos.side == 1.0) and np.all(demos.success)
    assert env_spec_of(demos) == ENV
    # Both runs share one normaliser (saved with each checkpoint).
    _, _, n_base, _ = load_policy(out / "demo" / "baseline")
    _, _, n_eq, _ = load_policy(out / "demo" / "equibim")
    for a, b in zip(*(jax_leaves(n.to_state_dict()) for n in (n_base, n_eq))):
        np.testing.assert_array_equal(a, b)


def jax_leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def test_cli_train_resume_is_exact_and_eval(tiny_demo, tmp_path, capsys):
    out, _ = tiny_demo
    data = str(out / "demo" / "demos.zarr")
    common = ["train", "--data", data, "--batch-size", "8", "--steps", "4",
              "--steps-per-dispatch", "2", "--warmup-steps", "1", *MODEL_FLAGS]
    main(common + ["--out", str(tmp_path / "straight")])
    assert "trained to step 4" in capsys.readouterr().out
    # Same run with a checkpoint at step 2, then "crash" after it: drop the step-4 checkpoint.
    run = tmp_path / "run"
    main(common + ["--out", str(run), "--checkpoint-every", "2"])
    shutil.rmtree(run / "ckpt" / "4")
    main(common + ["--out", str(run), "--checkpoint-every", "2"])  # resumes from step 2
    rows = [json.loads(l) for l in (run / "train.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [2, 4]
    _, a, _, _ = load_policy(tmp_path / "straight")
    _, b, _, _ = load_policy(run)
    for x, y in zip(jax_leaves(a.ema_params), jax_leaves(b.ema_params)):
        np.testing.assert_array_equal(x, y)
    # A changed setting is refused rather than silently mixed into the old run.
    with pytest.raises(Exception, match="different config"):
        main(common + ["--out", str(run), "--sym-weight", "0.5"])
    main(["eval", str(run), "--episodes", "2", "--out", str(tmp_path / "eval.json")])
    printed = capsys.readouterr().out
    assert "trained" in printed and "mirrored" in printed
    res = json.loads((tmp_path / "eval.json").read_text())
    assert res["trained"]["episodes"] == 2 and res["mirrored"]["episodes"] == 2


def test_cli_generate_refuses_to_overwrite(tiny_demo, capsys):
    out, _ = tiny_demo
    before = sorted(p.name for p in (out / "demo" / "demos.zarr").iterdir())
    with pytest.raises(FileExistsError, match="overwrite"):
        main(["generate", "--out", str(out / "demo" / "demos.zarr"), "--n-episodes", "1"])
    assert sorted(p.name for p in (out / "demo" / "demos.zarr").iterdir()) == before
    load(out / "demo" / "demos.zarr")


def test_train_rejects_a_dataset_without_env_spec(tmp_path):
    from equibim_jax.data.dataset import Demos, save
    from equibim_jax.experiments.pipeline import train_policy

    demos = Demos(obs={"qpos": np.zeros((1, 4, 14), np.float32)}, action=np.zeros((1, 4, 14), np.float32),
                  length=np.array([4], np.int32), success=np.array([True]),
                  side=np.array([1.0], np.float32), meta={"task": "place_empty_cup"})
    save(demos, tmp_path / "d.zarr")
    with pytest.raises(DatasetError, match="env_spec"):
        train_policy(tmp_path / "d.zarr", tmp_path / "run")


def test_bad_settings_are_refused_with_a_clear_message():
    with pytest.raises(ValueError, match="side"):
        EnvSpec(side="middle")
    with pytest.raises(ValueError, match="unknown task"):
        EnvSpec(task="fold_towel")
    with pytest.raises(ValueError, match="trained side"):
        DemoConfig(env=EnvSpec(side="both"))
    with pytest.raises(ValueError, match="multiple of"):
        DemoConfig(train_steps=120, steps_per_dispatch=50)
    with pytest.raises(ValueError, match="sym_weight"):
        DemoConfig(sym_weight=0.0)
    with pytest.raises(ValueError, match="sym_batch_size"):
        DemoConfig(batch_size=8)  # the default sym_batch_size (16) is larger


def test_demo_train_configs_differ_only_in_l_sym():
    cfg = DemoConfig(sym_stop_gradient=True, sym_warmup_steps=100, sym_batch_size=16)
    base, eq = cfg.train_config(0.0), cfg.train_config(cfg.sym_weight)
    assert (base.sym_warmup_steps, eq.sym_warmup_steps) == (0, 100)
    assert (base.sym_batch_size, eq.sym_batch_size) == (None, 16)
    assert (base.sym_weight, base.sym_stop_gradient, base.uses_mirror) == (0.0, False, False)
    assert (eq.sym_weight, eq.sym_stop_gradient, eq.uses_mirror) == (cfg.sym_weight, True, True)
    import dataclasses
    assert dataclasses.replace(eq, sym_weight=0.0, sym_stop_gradient=False, sym_warmup_steps=0,
                               sym_batch_size=None) == base


def test_mirrored_demo_replays_as_a_right_side_success(tiny_demo):
    """S on the data: the mirrored actions of a left demo, replayed from the mirror image of
    its initial state, succeed and follow the mirrored demo (the mirrored-side windows that
    L_sym and the open-loop metric use are real right-side expert behaviour)."""
    import jax
    import jax.numpy as jnp

    out, _ = tiny_demo
    demos = load(out / "demo" / "demos.zarr")
    env = env_spec_of(demos).make()
    n = int(demos.length[0])
    s0 = env.reset(jax.random.fold_in(jax.random.key(demos.meta["seed"]), 0))
    np.testing.assert_array_equal(np.asarray(s0.obs["qpos"]), demos.obs["qpos"][0, 0])
    acts = jax.vmap(env.action_symmetry)(jnp.asarray(demos.action[0, :n]))

    @jax.jit
    def replay(s, acts):
        def body(s, a):
            s = env.step(s, a)
            return s, (s.obs["qpos"], s.info["success"])
        return jax.lax.scan(body, s, acts)

    _, (qpos, success) = replay(env.mirror_state(s0), acts)
    expected = jax.vmap(env.obs_symmetry.ops["qpos"])(jnp.asarray(demos.obs["qpos"][0, 1:n]))
    assert bool(success[-1])
    assert float(jnp.abs(qpos[:-1] - expected).max()) < 1e-3  # rad; measured 1e-4
