"""Adding a policy and a task: a test-only toy of each, registered from here, trains and
evaluates end to end through the generic code (data, training, evaluation, CLI), which
never names either."""

import dataclasses
import json
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import equibim_jax as eb
from equibim_jax.cli import main
from equibim_jax.config import EvalConfig
from equibim_jax.data.generate import generate_dataset
from equibim_jax.evaluation.evaluate import evaluate_run
from equibim_jax.policies import Policy, PolicyConfig, policy_names, register_policy
from equibim_jax.sim.scenes import BoxScene
from equibim_jax.tasks import TaskEntry, register_task
from equibim_jax.training import TrainConfig, load_run, read_log, train

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)


# --------------------------------------------------------------------------- a toy policy
@dataclasses.dataclass(frozen=True)
class LinearConfig(PolicyConfig):
    """A linear map from the state window to the action chunk (deterministic)."""

    name: ClassVar[str] = "toy_linear"
    state_field: str = "qpos"

    @property
    def obs_keys(self):
        return (self.state_field,)

    @property
    def state_key(self):
        return self.state_field


def make_linear(cfg: LinearConfig) -> Policy:
    d_in, d_out = cfg.obs_horizon * cfg.state_dim, cfg.pred_horizon * cfg.action_dim

    def init(key):
        return {"w": 0.01 * jax.random.normal(key, (d_in, d_out)), "b": jnp.zeros((d_out,))}

    def apply(params, inputs):
        x = inputs["obs"][cfg.state_field]
        y = x.reshape(x.shape[0], -1) @ params["w"] + params["b"]
        return y.reshape(x.shape[0], cfg.pred_horizon, cfg.action_dim)

    return Policy(
        config=cfg, init=init,
        prepare=lambda batch, key: ({"obs": {cfg.state_field: batch[cfg.state_field]}},
                                    {"action": batch[cfg.action_key]}),
        apply=apply,
        bc_loss=lambda pred, t: jnp.mean(jnp.square(pred - t["action"])),
        mirror_inputs=lambda sym, i: {"obs": {k: sym[k](v) for k, v in i["obs"].items()}},
        mirror_targets=lambda sym, t: {"action": sym[cfg.action_key](t["action"])},
        sym_view=lambda inputs, pred: pred,
        mirror_view=lambda sym, v: sym[cfg.action_key](v),
        sample=lambda params, obs, key, noise_op=None: apply(params, {"obs": obs}),
    )


# --------------------------------------------------------------------------- a toy task
@dataclasses.dataclass(frozen=True)
class CloseGripper(BoxScene):
    """A box on one side; success: the gripper on the box's side has closed."""

    name = "toy_close_gripper"
    closed_below: float = 0.5

    def evaluate(self, data, info, env):
        opening = env.gripper_opening(data.qpos)  # [2]: left, right
        mine = jnp.where(info["side"] > 0, opening[0], opening[1])
        return jnp.zeros(()), mine < self.closed_below, {}


def close_gripper_expert(env):
    from equibim_jax.experts import Expert

    home = jnp.asarray(env.home_qpos)[env.arm_qadr]  # [2, n_arm]

    def act(e, s):
        grip = jnp.where(s.info["side"] > 0, jnp.array([0.0, 1.0]), jnp.array([1.0, 0.0]))
        return e, jnp.concatenate([home, grip[:, None]], axis=-1).reshape(-1)

    return Expert(init=lambda s: jnp.zeros(()), act=act, horizon=8, phase=lambda e: jnp.zeros((), jnp.int32))


TOY_TASK = TaskEntry(name="toy_close_gripper", scene=CloseGripper, robot="robot_a", step_limit=16,
                     expert=close_gripper_expert, env_defaults={"obs": ("qpos",)})


@pytest.fixture(scope="module")
def registered():
    register_policy("toy_linear", LinearConfig, make_linear)
    register_task(TOY_TASK)
    return LinearConfig(obs_horizon=1, pred_horizon=4, action_horizon=4)


@pytest.fixture(scope="module")
def toy_data(registered, tmp_path_factory):
    out = tmp_path_factory.mktemp("toy")
    env = eb.make_env("toy_close_gripper", side="left")
    demos, stats = generate_dataset(env, out / "demos.zarr", 4, seed=0, progress=False)
    return env, demos, out


def test_registries_list_the_toys(registered):
    assert "toy_linear" in policy_names() and "toy_close_gripper" in eb.task_names()
    with pytest.raises(ValueError, match="already registered"):
        register_policy("toy_linear", LinearConfig, lambda c: None)
    with pytest.raises(ValueError, match="unknown option"):
        eb.make_env("toy_close_gripper", colour="red")
    with pytest.raises(ValueError, match="closed_below"):
        eb.make_env("toy_close_gripper", closed_below="not a number")


@pytest.mark.slow  # two 300-step trainings and an evaluation; the CLI test below runs the same path short
def test_toy_task_and_policy_train_and_evaluate_end_to_end(toy_data, registered, tmp_path):
    env, demos, out = toy_data
    assert demos.meta["task"] == "toy_close_gripper" and demos.meta["task_options"]["side"] == "left"
    tc = TrainConfig(batch_size=8, total_steps=300, steps_per_dispatch=100, learning_rate=3e-2,
                     sym_weight=10.0, sym_norm="mse")
    runs = {}
    for name, weight in (("bc", 0.0), ("sym", 10.0)):
        summary = train(out / "demos.zarr", tmp_path / name, registered,
                        dataclasses.replace(tc, sym_weight=weight), env=env, progress=False)
        assert summary["steps"] == 300
        runs[name] = read_log(tmp_path / name / "train.jsonl")[-1]
    # L_sym is what makes the toy (a generic linear map) equivariant.
    assert runs["sym"]["equiv_err"] < 0.5 * runs["bc"]["equiv_err"]
    cfg = json.loads((tmp_path / "sym" / "config.json").read_text())
    assert cfg["policy"]["name"] == "toy_linear" and cfg["task"]["name"] == "toy_close_gripper"
    run = load_run(tmp_path / "sym")
    assert run.policy.config.name == "toy_linear" and run.make_env().scene.side == "left"
    res = evaluate_run(tmp_path / "sym", EvalConfig(episodes=2, batch=2), progress=False)
    for side in ("trained", "mirrored"):
        assert res[side]["episodes"] == 2 and res[side]["nan_actions"] == 0


def test_toy_policy_through_the_cli(toy_data, registered, tmp_path, capsys):
    _, _, out = toy_data
    main(["train", "--data", str(out / "demos.zarr"), "--out", str(tmp_path / "run"), "--policy", "toy_linear",
          "--policy.obs-horizon", "1", "--policy.pred-horizon", "4", "--policy.action-horizon", "4",
          "--steps", "20", "--train.steps-per-dispatch", "10", "--train.batch-size", "8"])
    assert "trained to step 20" in capsys.readouterr().out
    assert load_run(tmp_path / "run").policy.config == registered.with_data(14, {"qpos": 14})
    main(["eval", str(tmp_path / "run"), "--episodes", "2", "--eval.batch", "2"])
    assert "mirrored" in capsys.readouterr().out


def test_nonfinite_loss_stops_training_and_keeps_the_last_good_checkpoint(toy_data, registered, tmp_path):
    from equibim_jax.training import TrainingDiverged, latest_step

    _, _, out = toy_data
    tc = TrainConfig(batch_size=8, total_steps=40, steps_per_dispatch=10, learning_rate=1e30,
                     warmup_steps=0, sym_weight=0.0)
    with pytest.raises(TrainingDiverged, match="non-finite") as err:
        train(out / "demos.zarr", tmp_path / "run", registered, tc, progress=False)
    kept = latest_step(tmp_path / "run" / "ckpt")
    assert kept is not None and f"step {kept}" in str(err.value)
    state = load_run(tmp_path / "run").state
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(state.params))


def test_a_torn_last_log_line_does_not_break_resume(toy_data, registered, tmp_path):
    _, _, out = toy_data
    tc = TrainConfig(batch_size=8, total_steps=20, steps_per_dispatch=10, sym_weight=0.0)
    train(out / "demos.zarr", tmp_path / "run", registered, tc, checkpoint_every=10, progress=False)
    log = tmp_path / "run" / "train.jsonl"
    import shutil

    shutil.rmtree(tmp_path / "run" / "ckpt" / "20")
    log.write_text(log.read_text() + '{"step": 30, "bc": 0.1')  # a write cut short
    with pytest.warns(UserWarning, match="unreadable line"):
        train(out / "demos.zarr", tmp_path / "run", registered, tc, checkpoint_every=10, progress=False)
    assert [r["step"] for r in read_log(log)] == [10, 20]


def test_max_wall_s_stops_after_the_dispatch_that_crosses_it(toy_data, registered, tmp_path):
    _, _, out = toy_data
    tc = TrainConfig(batch_size=8, total_steps=40, steps_per_dispatch=10, sym_weight=0.0)
    s = train(out / "demos.zarr", tmp_path / "run", registered, tc, progress=False, max_wall_s=0.0)
    assert s["steps"] == 10
    assert [r["step"] for r in read_log(tmp_path / "run" / "train.jsonl")] == [10]
    assert load_run(tmp_path / "run").state.step == 10  # checkpointed where it stopped


def test_option_strings_are_parsed_by_field_type():
    """Options given as strings (CLI, JSON) become the field's type, for every union form."""
    from typing import Optional

    from equibim_jax.tasks import _coerce

    assert _coerce("cone", str | None, "elliptic") == "elliptic"
    assert _coerce("cone", Optional[str], "elliptic") == "elliptic"
    assert _coerce("r", tuple[float, float] | None, "0.1,0.2") == (0.1, 0.2)
    assert _coerce("r", tuple[float, float] | None, "none") is None
    assert _coerce("n", int, "64") == 64
    assert _coerce("b", bool, "True") is True and _coerce("b", bool, "false") is False
    with pytest.raises(ValueError, match="not a valid"):
        _coerce("n", int, "sixty")
