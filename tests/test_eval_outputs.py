"""`equibim eval` outputs: paired videos, per-episode records, the NaN flag, held-out
equivariance and argument errors, on test_extending's toy task (qpos only, 16 steps) and
toy linear policy, so every compiled program is small."""

import json

import jax
import numpy as np
import pytest
from test_extending import TOY_TASK, LinearConfig, make_linear

import equibim_jax as eb
from equibim_jax.cli import main
from equibim_jax.config import EvalConfig
from equibim_jax.data.dataset import Demos
from equibim_jax.evaluation.evaluate import episode_records, episode_steps, evaluate_run
from equibim_jax.evaluation.videos import check_episodes, paired_frames, write_video
from equibim_jax.policies import register_policy
from equibim_jax.tasks import register_task
from equibim_jax.training import TrainConfig, load_run, train

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)

RECORD_FIELDS = {"episode", "side", "success", "steps", "nan_actions", "any_nan"}


@pytest.fixture(scope="module")
def toy_run(tmp_path_factory):
    """A 10-step training run of the toy policy on 4 synthetic demos (jittered home poses:
    no expert rollout to compile), with the same registrations as test_extending
    (registering the same objects twice is a no-op). Returns ``(env, run_dir, run)``."""
    register_policy("toy_linear", LinearConfig, make_linear)
    register_task(TOY_TASK)
    out = tmp_path_factory.mktemp("eval_outputs")
    env = eb.make_env("toy_close_gripper", side="left")
    q0 = np.asarray(jax.jit(env.reset)(jax.random.key(0)).obs["qpos"])
    rng = np.random.default_rng(0)
    qpos = (q0 + rng.normal(0, 0.05, (4, 12, 14))).astype(np.float32)
    demos = Demos(obs={"qpos": qpos}, action=qpos + 0.01, length=np.full(4, 12, np.int32),
                  success=np.ones(4, bool), meta={"task": env.task, "task_options": {}})
    tc = TrainConfig(batch_size=8, total_steps=10, steps_per_dispatch=10, sym_weight=1.0, sym_norm="mse")
    train(demos, out / "run", LinearConfig(obs_horizon=1, pred_horizon=4, action_horizon=4), tc,
          env=env, progress=False)
    return env, out / "run", load_run(out / "run")


@pytest.mark.slow  # renders and encodes the paired episodes (about a minute and a half cold)
def test_paired_videos_and_per_episode_records(toy_run, tmp_path):
    env, _, run = toy_run
    out = tmp_path / "ev"
    res = evaluate_run(run, EvalConfig(episodes=3, batch=3), env=env, progress=False, out_dir=out,
                       video_episodes=(0, 2), video_size=16)
    limit = res["steps_limit"]
    assert limit == episode_steps(env, run.policy) == 16
    # Videos: T + 1 frames (start, then after each of the 16 steps), two 16-px halves side by side.
    from PIL import Image

    assert [v["episode"] for v in res["videos"]] == [0, 2]
    for v in res["videos"]:
        assert v["path"] == str(out / "videos" / f"episode_{v['episode']:03d}.gif")
        with Image.open(v["path"]) as gif:
            assert gif.n_frames == limit + 1 == v["frames"]
            assert gif.size == (2 * 16, 16) == (v["width"], v["height"])
        # The refilmed episode (a second rollout pass, same keys) is the evaluated one.
        i = v["episode"]
        assert v["success"] == res["trained"]["per_episode"][i]
        assert v["mirror_success"] == res["mirrored"]["per_episode"][i]
        assert v["matches_evaluation"] is True
    # Per-episode records: one per episode and side, consistent with the summaries.
    saved = json.loads((out / "eval.json").read_text())
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert rows == saved["records"] == res["records"] and len(rows) == 6
    for side in ("trained", "mirrored"):
        mine = [r for r in rows if r["side"] == side]
        assert [r["episode"] for r in mine] == [0, 1, 2]
        assert all(set(r) == RECORD_FIELDS for r in mine)
        assert sum(r["success"] for r in mine) == res[side]["successes"] == saved[side]["successes"]
        lo, hi = res[side]["ci95"]
        assert lo <= res[side]["success"] <= hi
        for r in mine:
            assert r["any_nan"] is False and r["nan_actions"] == 0
            assert (1 <= r["steps"] <= limit) if r["success"] else r["steps"] == limit
    # The old summary fields are all still there.
    assert {"success", "ci95", "episodes", "successes", "per_episode", "first_success_step", "nan_actions",
            "episodes_with_nan", "wall_s", "batch_s"} <= set(res["trained"])


def test_nan_actions_are_flagged_per_episode(toy_run, tmp_path):
    env, _, run = toy_run
    # NaN weights: every action is NaN (the env refuses each one). Same env, policy and
    # normaliser objects as above: the compiled evaluation is reused.
    bad = run._replace(state=run.state.replace(ema_params=jax.tree.map(
        lambda x: np.full_like(x, np.nan), run.state.ema_params)))
    res = evaluate_run(bad, EvalConfig(episodes=3, batch=3), env=env, progress=False)
    limit = res["steps_limit"]
    assert len(res["records"]) == 6
    assert all(r["any_nan"] and r["nan_actions"] == limit and not r["success"] and r["steps"] == limit
               for r in res["records"])
    assert res["trained"]["nan_per_episode"] == [limit] * 3 and res["mirrored"]["episodes_with_nan"] == 3
    # episode_records on a summary as evaluate_policies returns it
    recs = episode_records({"trained": {"per_episode": [True, False], "first_success_step": [4, -1],
                                        "nan_per_episode": [0, 2]}}, 16)
    assert recs == [{"episode": 0, "side": "trained", "success": True, "steps": 5, "nan_actions": 0, "any_nan": False},
                    {"episode": 1, "side": "trained", "success": False, "steps": 16, "nan_actions": 2,
                     "any_nan": True}]


@pytest.mark.slow  # loads the run again (a new compile) and generates expert demos
def test_cli_eval_outputs_and_heldout_equivariance(toy_run, tmp_path, capsys):
    _, run_dir, _ = toy_run
    out = tmp_path / "ev"
    main(["eval", str(run_dir), "--episodes", "2", "--eval.batch", "2", "--videos", "1", "--video-size", "16",
          "--video-format", "mp4", "--out-dir", str(out), "--equivariance-demos", "2",
          "--out", str(tmp_path / "e.json")])
    printed = capsys.readouterr().out
    assert "video of episode 0" in printed and "equivariance on 64 windows of 2" in printed
    res = json.loads((out / "eval.json").read_text())
    assert (out / "videos" / "episode_000.mp4").stat().st_size > 0 and res["videos"][0]["matches_evaluation"]
    eq = res["equivariance"]
    assert eq["demos"] == 2 and eq["windows"] == 64 and 0 <= eq["relative"] < 10
    assert np.isfinite(eq["equivariance"]["arm_rad"]) and len(eq["equivariance"]["per_dim_normalized_rms"]) == 14
    old = json.loads((tmp_path / "e.json").read_text())  # --out: the old content, plus records
    assert old["trained"]["episodes"] == 2 and "command" in old and len(old["records"]) == 4


def test_bad_video_arguments_fail_before_anything_runs(toy_run, tmp_path):
    _, run, _ = toy_run
    with pytest.raises(ValueError, match="video episode 3 does not exist.*numbered 0 to 2"):
        evaluate_run(run, EvalConfig(episodes=3), video_episodes=(3,), progress=False)
    with pytest.raises(ValueError, match="given twice"):
        check_episodes((1, 1), 3)
    with pytest.raises(ValueError, match="integers"):
        check_episodes((0.5,), 3)
    with pytest.raises(ValueError, match="video format"):
        evaluate_run(run, EvalConfig(episodes=3), video_episodes=(0,), video_format="avi", progress=False)
    with pytest.raises(SystemExit, match="more than the 2 episodes"):
        main(["eval", str(run), "--episodes", "2", "--videos", "5"])
    with pytest.raises(SystemExit, match="does not exist"):
        main(["eval", str(run), "--episodes", "2", "--video-episodes", "2"])
    with pytest.raises(SystemExit, match="not both"):
        main(["eval", str(run), "--videos", "1", "--video-episodes", "0"])
    with pytest.raises(SystemExit, match="even"):
        main(["eval", str(run), "--videos", "1", "--video-format", "mp4", "--video-size", "17"])


def test_write_video_gif_and_mp4_and_labels(tmp_path):
    av = pytest.importorskip("av")
    rng = np.random.default_rng(0)
    ep = {"episode": 4, "frames": rng.integers(0, 255, (5, 24, 24, 3), np.uint8),
          "mirror_frames": rng.integers(0, 255, (5, 24, 24, 3), np.uint8),
          "success_t": np.array([False, False, True, True]), "mirror_success_t": np.zeros(4, bool)}
    pair = paired_frames(ep)
    assert pair.shape == (5, 24, 48, 3)
    np.testing.assert_array_equal(paired_frames(ep, label=False)[:, :, 24:], ep["mirror_frames"])
    assert not np.array_equal(pair[:, :, :24], ep["frames"])  # the label is drawn in
    # The success label turns green from the step the episode succeeded (frame 3 = after step 3).
    assert pair[3, 1, 0, 1] > pair[3, 1, 0, 0] and pair[2, 1, 0, 1] == pair[2, 1, 0, 0]
    path = write_video(pair, tmp_path / "v.mp4", fps=10)
    with av.open(str(path)) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape == (24, 48, 3)
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    with pytest.raises(ValueError, match="even"):
        write_video(pair[:, :, :47], tmp_path / "odd.mp4")
    with pytest.raises(ValueError, match="format"):
        write_video(pair, tmp_path / "v.avi")
    with pytest.raises(ValueError, match="uint8"):
        write_video(pair.astype(np.float32), tmp_path / "v.gif")


@pytest.mark.slow  # trains a toy run in end-effector actions and generates expert demos
def test_heldout_equivariance_of_an_ee_action_run(toy_run, tmp_path):
    """The experts emit joint actions: an EE-action run's held-out demos come from the
    env's joint-action twin, read in the end-effector space (as the experiment runner
    does), instead of feeding joint actions to the EE env."""
    from equibim_jax.evaluation.evaluate import heldout_equivariance

    joint_env, _, _ = toy_run
    env = eb.make_env("toy_close_gripper", side="left", action="ee")
    assert env.config.action == "ee" and joint_env.config.action == "joint"
    q0 = np.asarray(jax.jit(joint_env.reset)(jax.random.key(0)).obs["qpos"])
    rng = np.random.default_rng(1)
    qpos = (q0 + rng.normal(0, 0.05, (4, 12, 14))).astype(np.float32)
    act_ee = np.asarray(jax.jit(jax.vmap(jax.vmap(joint_env.ee_action_from_joint)))(qpos))
    demos = Demos(obs={"qpos": qpos}, action=act_ee, length=np.full(4, 12, np.int32),
                  success=np.ones(4, bool), meta={"task": env.task, "task_options": dict(env.task_options)})
    tc = TrainConfig(batch_size=8, total_steps=10, steps_per_dispatch=10, sym_weight=1.0, sym_norm="mse")
    train(demos, tmp_path / "run", LinearConfig(obs_horizon=1, pred_horizon=4, action_horizon=4), tc,
          env=env, progress=False)
    run = load_run(tmp_path / "run")
    assert run.policy.config.action_dim == act_ee.shape[-1] != 14
    eq = heldout_equivariance(env, run.policy, run.normalizer, run.state.ema_params, jax.random.key(3), 2, 8)
    assert eq["demos"] == 2 and eq["windows"] == 8 and np.isfinite(eq["relative"])
    assert set(eq["demos_error"]) == set(eq["equivariance"]) - {"per_dim_normalized_rms"} \
        == {"position_m", "rotation", "gripper"}  # the EE layout's groups, not joint radians
    assert all(np.isfinite(v) for v in eq["demos_error"].values())


def test_state_from_qpos_matches_the_observation():
    """The state inputs rebuilt from a recorded qpos equal what the env observes."""
    from equibim_jax.evaluation.input_range import state_from_qpos

    register_task(TOY_TASK)
    env = eb.make_env("toy_close_gripper", side="left", obs=("qpos", "ee"))
    s = jax.jit(env.reset)(jax.random.key(2))
    for field in ("qpos", "ee"):
        got = state_from_qpos(env, field, s.data.qpos[None, None])
        assert got.shape == (1, 1) + s.obs[field].shape
        np.testing.assert_allclose(got[0, 0], s.obs[field], atol=1e-5)
    with pytest.raises(ValueError, match="state field must be one of"):
        state_from_qpos(env, "image", s.data.qpos)


def test_closed_loop_input_range(toy_run):
    from equibim_jax.evaluation.input_range import closed_loop_input_range

    env, _, run = toy_run
    rep = closed_loop_input_range(env, run.policy, run.normalizer, run.state.ema_params, jax.random.key(0), 3)
    assert rep["field"] == "qpos" and len(rep["success"]) == 3 and len(rep["first_out"]) == 3
    assert len(rep["max_abs"]) == 14 and len(rep["max_abs_t"]) == episode_steps(env, run.policy)
    assert max(rep["max_abs"]) == pytest.approx(max(rep["max_abs_t"]), abs=1e-3)
    assert all(f == -1 or 0 <= f < len(rep["max_abs_t"]) for f in rep["first_out"])


def test_error_groups_follow_the_action_layout():
    from equibim_jax.evaluation.open_loop import describe_errors, error_groups

    register_task(TOY_TASK)
    joint = eb.make_env("toy_close_gripper", side="left")
    ee = eb.make_env("toy_close_gripper", side="left", action="ee")
    for env, names in ((joint, {"arm_rad", "gripper"}), (ee, {"position_m", "rotation", "gripper"})):
        g = error_groups(env)
        assert set(g) == names
        idx = np.sort(np.concatenate(list(g.values())))
        np.testing.assert_array_equal(idx, np.arange(env.action_size))  # a partition of the channels
    np.testing.assert_array_equal(error_groups(ee)["gripper"], [3 + ee.rot_dim, 2 * (3 + ee.rot_dim) + 1])
    assert describe_errors({"arm_rad": 0.01, "gripper": 0.2}) == "arm 0.0100 rad, gripper 0.2000"
    assert describe_errors({"position_m": 0.002, "rotation": 0.03, "gripper": 0.1}) == \
        "position 0.0020 m, rotation 0.0300, gripper 0.1000"
