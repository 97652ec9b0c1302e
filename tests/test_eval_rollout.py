"""Closed-loop policy rollout: shapes, determinism, action chunking, Wilson summary."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.data import fit_normalizer
from equibim_jax.evaluation.rollout import (_runner, evaluate, evaluate_sides, make_policy_rollout,
                                            mirror_pair_gap, summarize)
from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig, make_policy
from equibim_jax.sim.env import Env, EnvConfig
from equibim_jax.sim.scenes import BoxScene

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)


def test_policy_rollout_runs_chunks_and_is_deterministic():
    """The tiny env/policy below: 8 steps in 2 chunks of Ta = 4, through the same compiled
    runner that ``evaluate`` uses, twice with the same keys."""
    env, policy, params, norm, s = _tiny_env_policy()
    sym = env.symmetry_ops(("qpos", "point_cloud"))
    assert sym == {"qpos": env.obs_symmetry.ops["qpos"], "point_cloud": env.obs_symmetry.ops["point_cloud"],
                   "action": env.action_symmetry}
    roll = _tiny_rollout()
    run = _runner(roll)
    keys = jax.random.split(jax.random.key(2), 2)
    flags = jnp.zeros(2, bool)
    a, b = run(params, keys, flags), run(params, keys, flags)
    assert a["success_t"].shape == (2, 8)  # 2 chunks of Ta = 4
    np.testing.assert_array_equal(np.asarray(a["final_qpos"]), np.asarray(b["final_qpos"]))
    assert np.all(np.isfinite(np.asarray(a["final_qpos"])))
    # The policy moved the arms (random weights, so not towards anything in particular).
    assert np.abs(np.asarray(a["final_qpos"])[:, :14] - np.asarray(s.data.qpos)[:14]).max() > 1e-3
    summary = evaluate(roll, params, jax.random.key(3), 2, chunk=2)
    assert summary["episodes"] == 2 and 0.0 <= summary["ci95"][0] <= summary["ci95"][1] <= 1.0


@functools.lru_cache(maxsize=None)  # building it takes ~25 s on 2 cores; all of it is immutable
def _tiny_env_policy(action_noise=0.0, obs_horizon=1, pred_horizon=4):
    """An 8-step box env, a one-level policy with To = 1, Tp = Ta = 4 (by default), and a
    normaliser fitted (mirror-consistently) on jittered copies of the reset state."""
    env = Env(EnvConfig(obs=("qpos", "point_cloud"), n_points=32, episode_length=8), BoxScene())
    cfg = DP3Config(
        action_dim=env.action_size, state_dim=env.action_size, obs_horizon=obs_horizon,
        pred_horizon=pred_horizon,
        action_horizon=4, encoder=EncoderConfig(pc_hidden=(8,), pc_out=8, state_out=8, state_hidden=(8,)),
        unet=UNetConfig(down_dims=(8,)), num_inference_steps=2,
    )
    policy = make_policy("dp3", cfg)
    params = policy.init(jax.random.key(0))
    s = jax.jit(env.reset)(jax.random.key(1))
    rng = np.random.default_rng(0)
    frames = {"qpos": np.asarray(s.obs["qpos"])[None] + rng.normal(0, 0.1, (20, 14)),
              "point_cloud": np.asarray(s.obs["point_cloud"])[None].repeat(20, 0),
              "action": np.asarray(s.obs["qpos"])[None] + rng.normal(0, action_noise, (20, 14))}
    sym = env.symmetry_ops(("qpos", "point_cloud"))
    return env, policy, params, fit_normalizer(frames, sym), s


@functools.lru_cache(maxsize=None)
def _tiny_rollout():
    """The default rollout of the tiny env and policy, one object so that every
    ``evaluate_sides`` call with the same batch shape reuses one compile."""
    env, policy, _, norm, _ = _tiny_env_policy()
    return make_policy_rollout(env, policy, norm)


def test_mirrored_rollout_starts_from_the_mirror_image_and_sides_are_paired():
    env, policy, params, norm, s = _tiny_env_policy()
    # Zero steps: the "final" state is the start state.
    roll0 = make_policy_rollout(env, policy, norm, length=0)
    key = jax.random.key(5)
    k_reset = jax.random.split(key)[0]
    start = jax.jit(env.reset)(k_reset)
    run0 = jax.jit(roll0)
    plain, mirr = run0(params, key, False), run0(params, key, True)
    np.testing.assert_array_equal(np.asarray(plain["final_qpos"]), np.asarray(start.data.qpos))
    np.testing.assert_allclose(np.asarray(mirr["final_qpos"]),
                               np.asarray(jax.jit(env.mirror_state)(start).data.qpos), atol=1e-6)
    assert not np.allclose(np.asarray(mirr["final_qpos"]), np.asarray(plain["final_qpos"]))
    # Both sides through one compiled function; same episode count and keys per side.
    roll = _tiny_rollout()
    res = evaluate_sides(roll, params, jax.random.key(3), 3, chunk=2)
    assert set(res) == {"trained", "mirrored"}
    for r in res.values():
        assert r["episodes"] == 3 and len(r["per_episode"]) == 3 and len(r["first_success_step"]) == 3
        assert r["nan_actions"] == 0 and r["episodes_with_nan"] == 0  # finite weights, finite actions
    with pytest.raises(ValueError, match="sides"):
        evaluate_sides(roll, params, jax.random.key(3), 2, sides=("left",))


def test_summarize_matches_wilson():
    r = summarize([True, False, True, True])
    assert r["episodes"] == 4 and r["successes"] == 3 and r["success"] == 0.75
    lo, hi = r["ci95"]
    assert lo < 0.75 < hi
    with pytest.raises(ValueError):
        summarize([])


@pytest.mark.slow  # long compile; CI runs it with the slow suite
def test_mirrored_noise_makes_an_equivariant_policy_repeat_its_episode_mirrored():
    """With ``mirror_noise`` the mirrored episode uses ``S_a z``: an exactly equivariant
    policy (zero weights: eps = 0, so DDIM maps noise to actions by clip and scale, which
    commute with the signed permutation S_a) then repeats the trained-side episode mirrored
    in the (mirror-symmetric) physics. With the plain noise it does not."""
    env, policy, params, norm, s = _tiny_env_policy(action_noise=0.05)
    params = jax.tree.map(np.zeros_like, params)
    key = jax.random.key(7)
    # mirror_pair_gap: mirrored noise, trajectories compared step by step.
    res = mirror_pair_gap(env, policy, norm, params, key, 2)
    assert len(res["gap_final"]) == 2 and set(res["gap_median_at"]) == {1, 8}
    assert max(res["gap_final"]) < 1e-4 and max(res["gap_median_at"].values()) < 1e-4, res
    assert res["both"] + res["trained_only"] + res["mirrored_only"] + res["neither"] == 2
    # The plain pairing (z itself on the mirrored side) is not the mirror image.
    roll = jax.jit(make_policy_rollout(env, policy, norm, mirror_noise=False, record_qpos=True))
    k0 = jax.random.split(key, 2)[0]
    plain, mirr = roll(params, k0, False), roll(params, k0, True)
    q, q_m = np.asarray(plain["qpos_t"]), np.asarray(jax.vmap(env.sym.qpos)(mirr["qpos_t"]))
    assert q.shape == (8, env.mjx_model.nq)
    assert np.abs(q[-1, :14] - np.asarray(s.data.qpos)[:14]).max() > 1e-2  # the arms moved
    assert np.abs(q_m - q).max() > 1e-2


def test_step_without_observation_keeps_obs_and_changes_nothing_else():
    env, _, _, _, s = _tiny_env_policy()
    a = jnp.asarray(s.obs["qpos"])
    full, blind = jax.jit(lambda s, a: (env.step(s, a), env.step(s, a, observe=False)))(s, a)
    for f in s.obs:  # the old observation is kept
        np.testing.assert_array_equal(np.asarray(blind.obs[f]), np.asarray(s.obs[f]))
    assert not np.array_equal(np.asarray(full.obs["qpos"]), np.asarray(s.obs["qpos"]))
    for x, y in zip(jax.tree.leaves((full.data, full.info, full.metrics)),
                    jax.tree.leaves((blind.data, blind.info, blind.metrics))):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-6)


@pytest.mark.slow  # long compile; CI runs it with the slow suite
def test_rollout_observing_only_what_the_policy_reads_is_the_same_episode():
    # To = 2, Ta = 4: the default rollout renders 2 of every 4 steps; the episode (states,
    # successes) must be the one of a rollout that observes every step.
    env, policy, params, norm, _ = _tiny_env_policy(obs_horizon=2, pred_horizon=8)
    key = jax.random.key(3)
    outs = [jax.jit(make_policy_rollout(env, policy, norm, record_qpos=True, observe_every_step=e))(
        params, key, False) for e in (False, True)]
    np.testing.assert_allclose(np.asarray(outs[0]["qpos_t"]), np.asarray(outs[1]["qpos_t"]),
                               rtol=0, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(outs[0]["success_t"]), np.asarray(outs[1]["success_t"]))
    assert outs[0]["qpos_t"].shape == (8, env.mj_model.nq)
    # and it is not trivially so: the arm moves during the episode
    assert float(np.abs(np.diff(np.asarray(outs[0]["qpos_t"]), axis=0)).max()) > 1e-4


def test_nan_policy_is_counted_in_every_episode():
    """A policy whose parameters are NaN emits NaN actions: the env refuses them and
    ``evaluate_sides`` counts them, in every episode of both sides."""
    _, _, params, _, _ = _tiny_env_policy()
    nan_params = jax.tree.map(lambda x: x * jnp.nan, params)
    assert all(np.isnan(np.asarray(x)).all() for x in jax.tree.leaves(nan_params))
    res = evaluate_sides(_tiny_rollout(), nan_params, jax.random.key(4), 2, chunk=2)
    assert set(res) == {"trained", "mirrored"}
    for r in res.values():
        assert r["episodes"] == 2
        assert r["nan_actions"] > 0
        assert r["episodes_with_nan"] == r["episodes"]
