"""The dp3 diffusion policy: configs, convs, U-Net, encoders, schedule, DDIM sampling, EMA."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.data import FieldNormalizer, Normalizer
from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig, make_policy, predict_action
from equibim_jax.policies.diffusion import (
    NoisePredictor,
    ddim_loop,
    ddim_timesteps,
    make_schedule,
    squared_cosine_betas,
)
from equibim_jax.policies.dp3 import ddim_sample
from equibim_jax.policies.encoders import PointCloudEncoder
from equibim_jax.policies.unet1d import Conv1d
from equibim_jax.training.ema import EmaConfig, ema_decay, ema_update

TINY = DP3Config(
    action_dim=4,
    state_dim=4,
    obs_horizon=2,
    pred_horizon=8,
    action_horizon=4,
    encoder=EncoderConfig(state_hidden=(16,), state_out=8, pc_hidden=(8, 16), pc_out=8),
    unet=UNetConfig(down_dims=(16, 32), kernel_size=5, n_groups=4, step_embed_dim=16),
)


@pytest.fixture(scope="module")
def tiny():
    policy = make_policy("dp3", TINY)
    return NoisePredictor(TINY), policy, policy.init(jax.random.key(0))


def example_obs(config, batch=1, num_points=16):
    """Zero observations of the shapes the encoder reads: ``{state: [B, To, D], pc: [B, To, N, 3]}``."""
    return {config.encoder.state_key: jnp.zeros((batch, config.obs_horizon, config.state_dim), jnp.float32),
            config.encoder.pc_key: jnp.zeros((batch, config.obs_horizon, num_points, 3), jnp.float32)}


# ---------------------------------------------------------------- configs


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(kernel_size=4), "kernel_size must be odd"),
        (dict(down_dims=(16, 30), n_groups=4), "must divide every down_dim"),
        (dict(down_dims=()), "non-empty"),
        (dict(conv_impl="cudnn"), "conv_impl"),
        (dict(step_embed_dim=15), "step_embed_dim"),
    ],
)
def test_unet_config_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        UNetConfig(**kwargs)


def test_policy_config_errors():
    with pytest.raises(ValueError, match="divisible by 4"):
        DP3Config(action_dim=2, state_dim=2, pred_horizon=10, action_horizon=4)
    with pytest.raises(ValueError, match="exceeds pred_horizon"):
        DP3Config(action_dim=2, state_dim=2, obs_horizon=2, pred_horizon=8, action_horizon=8)
    with pytest.raises(ValueError, match="num_inference_steps"):
        DP3Config(action_dim=2, state_dim=2, num_inference_steps=200)
    with pytest.raises(ValueError, match="action_dim"):
        DP3Config(action_dim=0, state_dim=2)
    # Hashable, so usable as a static argument.
    assert hash(TINY) == hash(dataclasses.replace(TINY))


# ---------------------------------------------------------------- layers


@pytest.mark.parametrize("k,stride,length", [(5, 1, 8), (3, 2, 8), (3, 2, 7), (1, 1, 5)])
def test_im2col_conv_matches_lax_conv(k, stride, length):
    x = jax.random.normal(jax.random.key(1), (3, length, 6))
    conv = Conv1d(5, k, stride=stride, impl="im2col")
    params = jax.jit(conv.init)(jax.random.key(2), x)
    params = jax.tree.map(lambda p: p + 0.1, params)  # nonzero bias
    y = jax.jit(conv.apply)(params, x)
    ref = jax.lax.conv_general_dilated(
        x, params["params"]["kernel"], (stride,), [(k // 2, k // 2)],
        dimension_numbers=("NWC", "WIO", "NWC"),
    ) + params["params"]["bias"]
    assert y.shape == (3, math.ceil(length / stride), 5)
    np.testing.assert_allclose(y, ref, atol=1e-5)
    # A direct loop over taps, independent of both implementations.
    xp = np.pad(np.asarray(x), ((0, 0), (k // 2, k // 2), (0, 0)))
    w = np.asarray(params["params"]["kernel"])
    direct = np.stack(
        [sum(xp[:, t * stride + i] @ w[i] for i in range(k)) for t in range(y.shape[1])], axis=1
    ) + np.asarray(params["params"]["bias"])
    np.testing.assert_allclose(y, direct, atol=1e-4)


def test_noise_predictor_shapes_and_impls_agree(tiny):
    model, policy, params = tiny
    obs = example_obs(TINY, batch=3, num_points=10)
    obs = jax.tree.map(lambda o: jax.random.normal(jax.random.key(3), o.shape), obs)
    x = jax.random.normal(jax.random.key(4), (3, 8, 4))
    k = jnp.array([0, 50, 99])
    cfg_xla = dataclasses.replace(TINY, unet=dataclasses.replace(TINY.unet, conv_impl="xla"))

    @jax.jit  # one compile instead of hundreds of eager op compiles
    def run(p):
        return (
            model.apply({"params": p}, x, k, obs),
            NoisePredictor(cfg_xla).apply({"params": p}, x, k, obs),
            model.apply({"params": p}, x, jnp.array([1, 51, 98]), obs),
        )

    eps, eps_xla, eps_k = run(params)
    # The policy's apply is the same network.
    eps_policy = jax.jit(policy.apply)(params, {"obs": obs, "noisy_action": x, "k": k})
    np.testing.assert_array_equal(eps_policy, eps)
    assert eps.shape == (3, 8, 4) and eps.dtype == jnp.float32
    np.testing.assert_allclose(eps, eps_xla, atol=1e-4)
    # The step embedding matters: different k, different prediction.
    assert float(jnp.abs(eps_k - eps).max()) > 1e-4


def test_point_cloud_encoder_is_permutation_invariant():
    enc = PointCloudEncoder((8, 16), 8)
    pts = jax.random.normal(jax.random.key(5), (2, 3, 20, 3))
    params = jax.jit(enc.init)(jax.random.key(6), pts)
    perm = np.random.default_rng(7).permutation(20)
    a, b = jax.jit(lambda p: (enc.apply(p, pts), enc.apply(p, pts[:, :, perm])))(params)
    assert a.shape == (2, 3, 8)
    np.testing.assert_allclose(a, b, atol=1e-6)


def test_missing_obs_field_is_a_clear_error(tiny):
    model, _, params = tiny
    with pytest.raises(KeyError, match="missing fields"):
        model.apply({"params": params}, jnp.zeros((1, 8, 4)), jnp.zeros((1,), jnp.int32),
                    {"qpos": jnp.zeros((1, 2, 4))})


# ---------------------------------------------------------------- schedule and sampling


def test_squared_cosine_schedule():
    betas = squared_cosine_betas(100)
    assert betas.shape == (100,) and np.all(betas > 0) and betas.max() == pytest.approx(0.999)
    sched = make_schedule(100)
    abar = lambda t: math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    # The product telescopes: alphas_cumprod[k] = abar((k + 1) / K) / abar(0) until the cap.
    for k in (0, 10, 50, 90):
        assert float(sched.alphas_cumprod[k]) == pytest.approx(abar((k + 1) / 100) / abar(0), rel=1e-4)
    assert np.all(np.diff(np.asarray(sched.alphas_cumprod)) < 0)


def test_ddim_timesteps():
    np.testing.assert_array_equal(ddim_timesteps(100, 10), [90, 80, 70, 60, 50, 40, 30, 20, 10, 0])


def test_ddim_with_oracle_eps_recovers_x0():
    """If eps_fn returns the true noise of x_T = sqrt(abar) x0 + sqrt(1 - abar) eps, DDIM
    walks the deterministic path back to x0 exactly (up to float error)."""
    sched = make_schedule(100)
    x0 = jax.random.uniform(jax.random.key(8), (2, 8, 3), minval=-0.9, maxval=0.9)
    noise = jax.random.normal(jax.random.key(9), x0.shape)
    a = sched.alphas_cumprod[90]
    x_t = jnp.sqrt(a) * x0 + jnp.sqrt(1 - a) * noise
    out = ddim_loop(lambda x, k: noise, x_t, sched, 10)
    np.testing.assert_allclose(out, x0, atol=1e-4)


def test_ddim_with_oracle_sample_recovers_x0():
    """Sample-prediction: if the network returns the true x0, every DDIM update lands on the
    deterministic path of x0 and the loop ends at x0."""
    sched = make_schedule(100)
    x0 = jax.random.uniform(jax.random.key(8), (2, 8, 3), minval=-0.9, maxval=0.9)
    x_t = jax.random.normal(jax.random.key(9), x0.shape)
    out = ddim_loop(lambda x, k: x0, x_t, sched, 10, prediction="sample")
    np.testing.assert_allclose(out, x0, atol=1e-5)
    with pytest.raises(ValueError, match="prediction must be one of"):
        ddim_loop(lambda x, k: x0, x_t, sched, 10, prediction="v")
    with pytest.raises(ValueError, match="prediction must be one of"):
        DP3Config(action_dim=2, state_dim=2, prediction="x0")


def test_ddim_is_equivariant_for_an_equivariant_eps():
    sched = make_schedule(100)
    perm, signs = jnp.array([2, 3, 0, 1]), jnp.array([1.0, -1.0, 1.0, -1.0])
    s = lambda x: signs * x[..., perm]  # noqa: E731
    w = jax.random.normal(jax.random.key(10), (4, 4))

    def eps_fn(x, k):  # equivariant by construction: 0.5 (g(x) + S g(S x))
        g = lambda z: jnp.tanh(z @ w) * (1.0 + k[:, None, None] / 100.0)  # noqa: E731
        return 0.5 * (g(x) + s(g(s(x))))

    x_init = jax.random.normal(jax.random.key(11), (3, 8, 4))
    np.testing.assert_allclose(ddim_loop(eps_fn, s(x_init), sched, 10), s(ddim_loop(eps_fn, x_init, sched, 10)), atol=1e-5)


def test_sample_actions_shapes_and_determinism(tiny):
    model, policy, params = tiny
    obs = jax.tree.map(lambda o: o + 0.3, example_obs(TINY, batch=2, num_points=10))
    # Raw action = normalised / 2 + 1; observations pass through unchanged.
    norm = Normalizer({"action": FieldNormalizer(scale=jnp.full((4,), 2.0), offset=jnp.full((4,), -2.0))})

    @jax.jit
    def sample(p, o, key):
        return policy.sample(p, o, key, None), predict_action(policy, p, o, key, norm)

    a1, pred = sample(params, obs, jax.random.key(0))
    # The policy's sampler is DDIM on the training schedule.
    a_ddim = jax.jit(lambda p, o, key: ddim_sample(model, p, o, key, make_schedule(TINY.num_train_steps)))(
        params, obs, jax.random.key(0))
    np.testing.assert_allclose(a_ddim, a1, atol=1e-6)
    a2, _ = sample(params, obs, jax.random.key(0))
    a3, _ = sample(params, obs, jax.random.key(1))
    assert a1.shape == (2, TINY.pred_horizon, TINY.action_dim)
    np.testing.assert_array_equal(a1, a2)
    assert float(jnp.abs(a1 - a3).max()) > 1e-3
    assert float(jnp.abs(a1).max()) <= 1.0  # the last step returns the clipped x0
    np.testing.assert_allclose(pred["action_pred"], a1 / 2.0 + 1.0, atol=1e-6)
    # The executed window starts at the current frame, index To - 1 = 1.
    np.testing.assert_array_equal(pred["action"], pred["action_pred"][:, 1:5])


# ---------------------------------------------------------------- EMA


def test_ema_decay_values():
    cfg = EmaConfig(power=0.75, max_decay=0.9999)
    assert float(ema_decay(jnp.int32(0), cfg)) == 0.0
    assert float(ema_decay(jnp.int32(1), cfg)) == 0.0
    assert float(ema_decay(jnp.int32(2), cfg)) == pytest.approx(1 - 2 ** -0.75, rel=1e-6)
    assert float(ema_decay(jnp.int32(10**9), cfg)) == pytest.approx(0.9999)
    assert float(ema_decay(jnp.int32(5), EmaConfig(fixed_decay=0.99))) == pytest.approx(0.99)
    with pytest.raises(ValueError, match="fixed_decay"):
        EmaConfig(fixed_decay=1.0)


def test_ema_update():
    e = {"w": jnp.array([1.0, 2.0])}
    p = {"w": jnp.array([3.0, 6.0])}
    out = ema_update(e, p, 0.75)
    np.testing.assert_allclose(out["w"], [1.5, 3.0])
