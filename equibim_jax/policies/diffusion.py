"""Diffusion policy: config, ε-predictor, DDPM training schedule, DDIM sampling, EMA.

Training is DDPM ε-prediction with a squared-cosine beta schedule (100 steps by
default). Sampling is deterministic DDIM (``eta = 0``, "leading" timestep spacing, final
alpha 1, optional clipping of the predicted ``x0`` to ``[-1, 1]``), written as one
``lax.scan``; given a key it is deterministic.

Equivariance note: if ``eps(S_a x, k, S O) == S_a eps(x, k, O)`` with ``S_a`` a signed
permutation, every DDIM update (affine in ``x`` and ``eps`` with scalar coefficients,
and clipping to the symmetric box ``[-1, 1]``) commutes with ``S_a``, so the sampler
maps mirrored observations and mirrored initial noise to mirrored actions.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Mapping
from typing import Any

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax.policies.encoders import EncoderConfig, ObsEncoder
from equibim_jax.policies.unet1d import ConditionalUnet1D, UNetConfig

Array = Any

__all__ = [
    "PolicyConfig",
    "EmaConfig",
    "NoisePredictor",
    "PolicyApplyFn",
    "DiffusionSchedule",
    "make_schedule",
    "squared_cosine_betas",
    "add_noise",
    "ddim_timesteps",
    "ddim_loop",
    "sample_actions",
    "predict_action",
    "init_params",
    "example_obs",
    "ema_decay",
    "ema_update",
]


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """Diffusion-policy configuration (hashable, usable as a static argument).

    Attributes:
      action_dim: ``A``, joint-action width.
      state_dim: width of the state field read by the encoder.
      obs_horizon: ``To``, observation frames fed to the encoder.
      pred_horizon: ``Tp``, predicted action steps (divisible by the U-Net's halvings).
      action_horizon: ``Ta``, steps executed per prediction, starting at index ``To - 1``.
      action_key: name of the action field in batches.
      encoder: :class:`EncoderConfig`. unet: :class:`UNetConfig`.
      num_train_steps: DDPM steps ``K`` (noise levels seen in training).
      num_inference_steps: DDIM steps at sampling time.
      clip_sample: clip DDIM's predicted ``x0`` to ``[-1, 1]`` (the normalised range).
    """

    action_dim: int
    state_dim: int
    obs_horizon: int = 2
    pred_horizon: int = 16
    action_horizon: int = 8
    action_key: str = "action"
    encoder: EncoderConfig = EncoderConfig()
    unet: UNetConfig = UNetConfig()
    num_train_steps: int = 100
    num_inference_steps: int = 10
    clip_sample: bool = True

    def __post_init__(self):
        for name in ("action_dim", "state_dim", "obs_horizon", "pred_horizon", "action_horizon"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"PolicyConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.obs_horizon - 1 + self.action_horizon > self.pred_horizon:
            raise ValueError(
                f"PolicyConfig: obs_horizon - 1 + action_horizon = "
                f"{self.obs_horizon - 1 + self.action_horizon} exceeds pred_horizon="
                f"{self.pred_horizon}; the executed actions must lie inside the prediction"
            )
        self.unet.check_horizon(self.pred_horizon)
        if not 1 <= self.num_inference_steps <= self.num_train_steps:
            raise ValueError(
                f"PolicyConfig: need 1 <= num_inference_steps ({self.num_inference_steps}) "
                f"<= num_train_steps ({self.num_train_steps})"
            )
        if self.action_key in self.encoder.keys:
            raise ValueError(f"PolicyConfig.action_key {self.action_key!r} is also an observation key")


@dataclasses.dataclass(frozen=True)
class EmaConfig:
    """EMA of parameters.

    With ``fixed_decay=None`` the decay warms up as in Diffusion Policy's EMAModel:
    ``1 - (1 + s / inv_gamma) ** -power`` with ``s = step - update_after_step - 1``
    (0 for ``s <= 0``), clipped to ``[min_decay, max_decay]``. Otherwise it is constant.
    """

    power: float = 0.75
    inv_gamma: float = 1.0
    min_decay: float = 0.0
    max_decay: float = 0.9999
    update_after_step: int = 0
    fixed_decay: float | None = None

    def __post_init__(self):
        if self.fixed_decay is not None and not 0.0 <= self.fixed_decay < 1.0:
            raise ValueError(f"EmaConfig.fixed_decay must be in [0, 1), got {self.fixed_decay}")
        if self.power <= 0 or self.inv_gamma <= 0:
            raise ValueError("EmaConfig.power and inv_gamma must be positive")
        if not 0.0 <= self.min_decay <= self.max_decay < 1.0:
            raise ValueError(
                f"EmaConfig: need 0 <= min_decay ({self.min_decay}) <= max_decay "
                f"({self.max_decay}) < 1"
            )


class NoisePredictor(nn.Module):
    """``eps(a_k, k, O)``: observation encoder + conditional 1D U-Net.

    Attributes:
      config: :class:`PolicyConfig`.
    """

    config: PolicyConfig

    def setup(self):
        self.encoder = ObsEncoder(self.config.encoder)
        self.unet = ConditionalUnet1D(self.config.unet)

    def __call__(self, noisy_actions: Array, k: Array, obs: Mapping[str, Array]) -> Array:
        """Args:
          noisy_actions: ``[B, Tp, A]``. k: ``[B]`` int steps.
          obs: ``{field: [B, To, ...]}`` normalised observations (extra fields ignored).
        Returns:
          ``[B, Tp, A]`` predicted noise.
        """
        return self.unet(noisy_actions, k, self.encoder(obs))

    def encode(self, obs: Mapping[str, Array]) -> Array:
        """``obs -> [B, D_cond]`` conditioning vector (computed once per sampling)."""
        return self.encoder(obs)

    def denoise(self, noisy_actions: Array, k: Array, cond: Array) -> Array:
        """``([B, Tp, A], [B], [B, D_cond]) -> [B, Tp, A]`` predicted noise."""
        return self.unet(noisy_actions, k, cond)


@dataclasses.dataclass(frozen=True)
class PolicyApplyFn:
    """``apply_fn(params, noisy_actions, k, obs) -> eps`` for a config; hashable.

    Being a frozen dataclass of the config (rather than a fresh closure), two instances
    built from equal configs compare equal, so a :class:`TrainState` holding one as a
    static field keeps the same tree structure across restarts and jit caches hit.
    """

    config: PolicyConfig

    def __call__(self, params: Any, noisy_actions: Array, k: Array, obs: Mapping[str, Array]):
        """``([B, Tp, A], [B], {field: [B, To, ...]}) -> [B, Tp, A]`` predicted noise."""
        return NoisePredictor(self.config).apply({"params": params}, noisy_actions, k, obs)


def example_obs(config: PolicyConfig, batch: int = 1, num_points: int = 16) -> dict[str, Array]:
    """Zero observations of the right shapes: ``{state: [B, To, D], pc: [B, To, N, 3]}``."""
    enc, to = config.encoder, config.obs_horizon
    obs = {enc.state_key: jnp.zeros((batch, to, config.state_dim), jnp.float32)}
    if enc.pc_key is not None:
        obs[enc.pc_key] = jnp.zeros((batch, to, num_points, 3), jnp.float32)
    return obs


def init_params(config: PolicyConfig, key: Array) -> tuple[NoisePredictor, Any]:
    """Build the module and initialise its parameters.

    Args:
      config: policy config. key: a ``jax.random.key``.
    Returns:
      ``(model, params)`` with ``params`` the ``"params"`` collection; call the network
      as ``model.apply({"params": params}, noisy_actions, k, obs)``.
    """
    return NoisePredictor(config), _init_params_jit(config, key)


@functools.partial(jax.jit, static_argnums=0)
def _init_params_jit(config: PolicyConfig, key: Array) -> Any:
    # Jitted (and cached per config): op-by-op initialisation of the U-Net dispatches
    # hundreds of small ops.
    x = jnp.zeros((1, config.pred_horizon, config.action_dim), jnp.float32)
    k = jnp.zeros((1,), jnp.int32)
    return NoisePredictor(config).init(key, x, k, example_obs(config))["params"]


def squared_cosine_betas(num_steps: int, max_beta: float = 0.999) -> np.ndarray:
    """Squared-cosine ("squaredcos_cap_v2") betas of Nichol & Dhariwal.

    Returns ``[num_steps]`` float64 with ``beta_i = min(1 - abar((i+1)/K) / abar(i/K),
    max_beta)``, ``abar(t) = cos((t + 0.008) / 1.008 * pi / 2) ** 2``.
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")

    def abar(t):
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    return np.array(
        [min(1 - abar((i + 1) / num_steps) / abar(i / num_steps), max_beta) for i in range(num_steps)]
    )


@flax.struct.dataclass
class DiffusionSchedule:
    """Noise schedule arrays. ``betas, alphas_cumprod: [K]`` float32."""

    betas: Array
    alphas_cumprod: Array


def make_schedule(num_train_steps: int) -> DiffusionSchedule:
    """Squared-cosine DDPM schedule with ``num_train_steps`` steps."""
    betas = squared_cosine_betas(num_train_steps)
    acp = np.cumprod(1.0 - betas)
    return DiffusionSchedule(jnp.asarray(betas, jnp.float32), jnp.asarray(acp, jnp.float32))


def add_noise(schedule: DiffusionSchedule, x0: Array, noise: Array, k: Array) -> Array:
    """Forward process ``q(x_k | x_0)``: ``sqrt(abar_k) x0 + sqrt(1 - abar_k) noise``.

    Args:
      x0, noise: ``[B, ...]``. k: ``[B]`` int steps in ``[0, K)``.
    Returns:
      ``[B, ...]`` noisy samples.
    """
    acp = schedule.alphas_cumprod[k].reshape((-1,) + (1,) * (x0.ndim - 1))
    return jnp.sqrt(acp) * x0 + jnp.sqrt(1.0 - acp) * noise


def ddim_timesteps(num_train_steps: int, num_inference_steps: int) -> np.ndarray:
    """DDIM's "leading" timesteps, descending: ``[n]`` int32, e.g. 100/10 -> 90, 80, ..., 0."""
    ratio = num_train_steps // num_inference_steps
    return (np.arange(num_inference_steps) * ratio)[::-1].astype(np.int32)


def ddim_loop(
    eps_fn: Callable[[Array, Array], Array],
    x_init: Array,
    schedule: DiffusionSchedule,
    num_inference_steps: int,
    clip_sample: bool = True,
) -> Array:
    """Deterministic DDIM (``eta = 0``) from ``x_init`` down to ``x_0``, as a ``lax.scan``.

    Args:
      eps_fn: ``(x [B, ...], k [B]) -> eps [B, ...]``.
      x_init: ``[B, ...]`` initial Gaussian noise.
      schedule: training schedule (``K`` steps).
      num_inference_steps: number of DDIM updates.
      clip_sample: clip the predicted ``x0`` to ``[-1, 1]``.
    Returns:
      ``[B, ...]`` denoised sample.
    """
    num_train = schedule.alphas_cumprod.shape[0]
    ratio = num_train // num_inference_steps
    ts = jnp.asarray(ddim_timesteps(num_train, num_inference_steps))
    acp = schedule.alphas_cumprod

    def body(x, t):
        eps = eps_fn(x, jnp.full((x.shape[0],), t, jnp.int32))
        a_t = acp[t]
        prev = t - ratio
        a_prev = jnp.where(prev >= 0, acp[jnp.maximum(prev, 0)], 1.0)
        x0 = (x - jnp.sqrt(1.0 - a_t) * eps) / jnp.sqrt(a_t)
        if clip_sample:
            x0 = jnp.clip(x0, -1.0, 1.0)
        return jnp.sqrt(a_prev) * x0 + jnp.sqrt(1.0 - a_prev) * eps, None

    x, _ = jax.lax.scan(body, x_init, ts)
    return x


def sample_actions(
    model: NoisePredictor,
    params: Any,
    obs: Mapping[str, Array],
    key: Array,
    schedule: DiffusionSchedule | None = None,
    noise_op: Callable[[Array], Array] | None = None,
) -> Array:
    """Sample normalised action sequences with DDIM.

    Args:
      model: the :class:`NoisePredictor`. params: its ``"params"`` collection.
      obs: ``{field: [B, To, ...]}`` normalised observations.
      key: PRNG key for the initial noise; same key, same output.
      schedule: defaults to ``make_schedule(config.num_train_steps)``.
      noise_op: applied to the initial noise ``[B, Tp, A]`` drawn from ``key``, e.g. the
        action mirror ``S_a`` (a signed permutation, so the noise stays ``N(0, I)``): an
        equivariant network then gives ``S_a`` of the sample from the mirrored inputs.
    Returns:
      ``[B, Tp, A]`` normalised actions.
    """
    cfg = model.config
    schedule = schedule if schedule is not None else make_schedule(cfg.num_train_steps)
    variables = {"params": params}
    cond = model.apply(variables, obs, method=NoisePredictor.encode)
    x_init = jax.random.normal(key, (cond.shape[0], cfg.pred_horizon, cfg.action_dim), jnp.float32)
    if noise_op is not None:
        x_init = noise_op(x_init)

    def eps_fn(x, k):
        return model.apply(variables, x, k, cond, method=NoisePredictor.denoise)

    return ddim_loop(eps_fn, x_init, schedule, cfg.num_inference_steps, cfg.clip_sample)


def predict_action(
    model: NoisePredictor,
    params: Any,
    obs_raw: Mapping[str, Array],
    key: Array,
    normalizer: Any,
    schedule: DiffusionSchedule | None = None,
    noise_op: Callable[[Array], Array] | None = None,
) -> dict[str, Array]:
    """Closed-loop inference: normalise, sample, unnormalise, cut the executed window.

    Args:
      obs_raw: ``{field: [B, To, ...]}`` raw observations.
      normalizer: an ``equibim_jax.data.Normalizer`` holding the action and obs fields.
      noise_op: see :func:`sample_actions` (in normalised action space).
    Returns:
      ``{"action_pred": [B, Tp, A], "action": [B, Ta, A]}`` raw-space actions;
      ``"action"`` starts at index ``To - 1`` (the current frame).
    """
    cfg = model.config
    obs = normalizer.normalize(obs_raw)
    a = sample_actions(model, params, obs, key, schedule, noise_op)
    a = normalizer.fields[cfg.action_key].unnormalize(a)
    start = cfg.obs_horizon - 1
    return {"action_pred": a, "action": a[:, start : start + cfg.action_horizon]}


def ema_decay(step: Array, config: EmaConfig) -> Array:
    """EMA decay to use at optimisation step ``step`` (int scalar) -> float32 scalar."""
    if config.fixed_decay is not None:
        return jnp.asarray(config.fixed_decay, jnp.float32)
    s = jnp.maximum(0, step - config.update_after_step - 1).astype(jnp.float32)
    value = 1.0 - (1.0 + s / config.inv_gamma) ** (-config.power)
    value = jnp.clip(value, config.min_decay, config.max_decay)
    return jnp.where(s <= 0, 0.0, value)


def ema_update(ema_params: Any, params: Any, decay: Array) -> Any:
    """``ema <- decay * ema + (1 - decay) * params``, leaf by leaf (same tree structure)."""
    return jax.tree.map(lambda e, p: decay * e + (1.0 - decay) * p, ema_params, params)
