"""The fused online loop: ring-buffer sampling, exact agreement with the offline step on a
preloaded buffer, and expert frames written where they belong."""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.data import fit_normalizer, make_dataset, normalized_symmetry, sample_batch
from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig, make_policy
from equibim_jax.tasks import make_env
from equibim_jax.training import (
    OnlineConfig,
    TrainConfig,
    base_key,
    buffer_from_frames,
    create_train_state,
    make_online_train_loop,
    make_train_loop,
    sample_ring,
)

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)

POLICY = DP3Config(obs_horizon=2, pred_horizon=8, action_horizon=4,
                   encoder=EncoderConfig(pc_key=None, state_hidden=(16,), state_out=8),
                   unet=UNetConfig(down_dims=(16,), kernel_size=3, n_groups=4, step_embed_dim=16))


def _frames(lengths, dim=14, seed=0):
    rng = np.random.default_rng(seed)
    f = int(np.sum(lengths))
    q = np.cumsum(rng.normal(size=(f, dim)) * 0.1, axis=0).astype(np.float32)
    return {"qpos": q, "action": np.roll(q, -1, 0)}, np.cumsum(lengths)


def test_ring_sampling_equals_offline_sampling():
    lengths = [9, 30, 3, 17, 25]  # the 3-frame episode has no window of Tp = 8
    frames, ends = _frames(lengths)
    cfg = POLICY.with_data(14, {"qpos": 14})
    ds = make_dataset(frames, ends, cfg)
    buf = buffer_from_frames(frames, ends, cfg, slots=7, slot_len=32)
    assert int(jnp.sum(buf.window_counts())) == ds.num_windows
    draw = jax.jit(sample_ring, static_argnums=2)
    for i in range(20):
        key = jax.random.key(i)
        a, b = sample_batch(ds, key, 64), draw(buf, key, 64)
        for k in a:
            np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]))
    # Preloading from a later slot changes the slot order, not the windows' law.
    later = buffer_from_frames(frames, ends, cfg, slots=9, slot_len=32, first_slot=2)
    assert int(jnp.sum(later.window_counts())) == ds.num_windows
    with pytest.raises(ValueError, match="do not fit"):
        buffer_from_frames(frames, ends, cfg, slots=4)


@pytest.fixture(scope="module")
def bell():
    env = make_env("click_bell", obs=("qpos",))
    return env


def test_online_loop_on_a_preloaded_buffer_matches_the_offline_loop_exactly(bell):
    lengths = [40, 35, 50, 44]
    frames, ends = _frames(lengths)
    norm = fit_normalizer(frames, bell.symmetry_ops(("qpos",)))
    sym = normalized_symmetry(bell.symmetry_ops(("qpos",)), norm)
    nframes = norm.normalize(frames)
    cfg = POLICY.with_data(14, {"qpos": 14})
    policy = make_policy("dp3", cfg)
    tc = TrainConfig(batch_size=16, total_steps=100, warmup_steps=5, sym_weight=0.1, steps_per_dispatch=20)
    oc = OnlineConfig(num_envs=2, env_steps=0, grad_steps=1, iterations=20, rounds=2, episode_length=50)
    buf = buffer_from_frames(nframes, ends, cfg, slots=oc.slots, slot_len=50)
    loop = make_online_train_loop(bell, tc, oc, norm, sym)
    carry, m_on = loop.run(loop.init(create_train_state(policy, tc), buf), base_key(tc))
    offline = make_train_loop(tc, make_dataset(nframes, ends, cfg), sym)
    state, m_off = offline(create_train_state(policy, tc), base_key(tc))
    assert int(carry.train.step) == int(state.step) == 20
    for a, b in zip(jax.tree.leaves((carry.train.params, carry.train.opt_state, carry.train.ema_params)),
                    jax.tree.leaves((state.params, state.opt_state, state.ema_params))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(m_on["total"]), np.asarray(m_off["total"]))
    assert int(m_on["env_steps"][-1]) == 0


@pytest.mark.slow
def test_online_collection_writes_the_expert_frames(bell):
    """Two envs, one full round: the buffer's slots hold the normalised frames of the
    expert rollouts from the same reset keys, cut after success + tail, and training ran."""
    from equibim_jax.data.generate import make_demo_rollout

    t_len = 140  # click_bell's expert script plus 20 steps
    roll = make_demo_rollout(bell, t_len)
    oc = OnlineConfig(num_envs=2, env_steps=20, grad_steps=2, iterations=8, rounds=2,
                      episode_length=t_len, tail=5)
    keys = jax.random.split(jax.random.fold_in(jax.random.key(oc.seed), 0), 2)
    _, traj = roll(keys)
    frames = {"qpos": np.asarray(traj["obs"]["qpos"]).reshape(-1, 14),
              "action": np.asarray(traj["action"]).reshape(-1, 14)}
    norm = fit_normalizer(frames, bell.symmetry_ops(("qpos",)))
    sym = normalized_symmetry(bell.symmetry_ops(("qpos",)), norm)
    cfg = POLICY.with_data(14, {"qpos": 14})
    policy = make_policy("dp3", cfg)
    tc = TrainConfig(batch_size=8, total_steps=100, warmup_steps=5, steps_per_dispatch=20)
    # Slots 2, 3 hold a preloaded copy so that the first round can train.
    pre = buffer_from_frames(norm.normalize(frames), [t_len, 2 * t_len], cfg, slots=oc.slots,
                             slot_len=t_len, first_slot=2)
    loop = make_online_train_loop(bell, tc, oc, norm, sym)
    carry, m = loop.run(loop.init(create_train_state(policy, tc), pre), base_key(tc))
    # 160 steps: round 0 ended at step 140 (slots 0, 1 finished), round 1 is writing 2, 3.
    assert int(m["env_steps"][-1]) == 160 * 2 and int(m["episodes"][-1]) == 2
    assert int(carry.round) == 1 and int(carry.t) == 20
    succ = np.asarray(traj["success"])
    assert succ.any(axis=1).all()  # the expert succeeds: the slots below are not vacuous
    assert int(m["successes"][-1]) == 2
    lengths = np.asarray(carry.buffer.lengths)
    for e in range(2):
        first = int(np.argmax(succ[e])) if succ[e].any() else None
        n = 0 if first is None else min(t_len, first + 1 + oc.tail)
        assert lengths[e] == n
        got = np.asarray(carry.buffer.frames["qpos"][e * t_len : e * t_len + n])
        want = np.asarray(norm.fields["qpos"].normalize(traj["obs"]["qpos"][e, :n]))
        np.testing.assert_allclose(got, want, atol=1e-5)
        got_a = np.asarray(carry.buffer.frames["action"][e * t_len : e * t_len + n])
        np.testing.assert_allclose(got_a, np.asarray(norm.fields["action"].normalize(traj["action"][e, :n])),
                                   atol=1e-5)
    assert list(lengths[2:]) == [0, 0]  # being overwritten by round 1
    assert int(carry.train.step) == 16 and np.isfinite(np.asarray(m["total"])).all()


def test_online_config_errors():
    with pytest.raises(ValueError, match="rounds must be >= 2"):
        OnlineConfig(rounds=1)
    with pytest.raises(ValueError, match="action_space"):
        OnlineConfig(action_space="cartesian")
    with pytest.raises(ValueError, match="num_envs"):
        OnlineConfig(num_envs=0)


@pytest.mark.slow
def test_train_online_cli_writes_a_run_that_loads(tmp_path):
    from equibim_jax.cli import main
    from equibim_jax.training import load_run, read_log

    out = tmp_path / "run"
    args = ["train", "--online", "--task", "click_bell", "--out", str(out), "--policy", "dp3",
            "--policy.encoder.pc-key", "None", "--policy.unet.down-dims", "16",
            "--policy.unet.n-groups", "4", "--online.num-envs", "2", "--online.env-steps", "20",
            "--online.iterations", "7", "--online.rounds", "2", "--train.batch-size", "8", "--steps", "14"]
    main(args)
    rows = read_log(out / "train.jsonl")
    assert [r["step"] for r in rows] == [7, 14]  # click_bell's rollout: 140 steps
    assert rows[-1]["env_steps"] == 14 * 20 * 2 and rows[-1]["episodes"] == 4
    assert "env_steps_per_s" in rows[-1] and "env_steps_per_s" not in rows[0]
    run = load_run(out)
    assert int(run.state.step) == 14 and run.config["task"].name == "click_bell"
    assert run.config["task"].options["obs"] == ["qpos"]
