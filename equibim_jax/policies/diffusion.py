"""Diffusion machinery shared by the diffusion policies: the noise predictor, the DDPM
training schedule and deterministic DDIM sampling.

Training is DDPM with a squared-cosine beta schedule; the network predicts the noise
(``"epsilon"``) or the clean sample (``"sample"``, as DP3 offers). Sampling is
deterministic DDIM (``eta = 0``, "leading" timestep spacing, final alpha 1, optional
clipping of the predicted ``x0`` to ``[-1, 1]``), written as one ``lax.scan``; given a key
it is deterministic.

Equivariance: if ``eps(S_a x, k, S O) == S_a eps(x, k, O)`` with ``S_a`` a signed
permutation, every DDIM update (affine in ``x`` and ``eps`` with scalar coefficients,
and clipping to the symmetric box ``[-1, 1]``) commutes with ``S_a``, so the sampler
maps mirrored observations and mirrored initial noise to mirrored actions.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax.policies.encoders import ObsEncoder
from equibim_jax.policies.unet1d import ConditionalUnet1D

Array = Any

__all__ = [
    "NoisePredictor",
    "DiffusionSchedule",
    "make_schedule",
    "squared_cosine_betas",
    "add_noise",
    "predict_x0",
    "eps_from_x0",
    "ddim_timesteps",
    "ddim_loop",
    "PREDICTIONS",
]

PREDICTIONS = ("epsilon", "sample")


class NoisePredictor(nn.Module):
    """``eps(a_k, k, O)``: observation encoder + conditional 1D U-Net.

    Attributes:
      config: a config with ``encoder`` (:class:`EncoderConfig`) and ``unet``
        (:class:`UNetConfig`) fields, e.g. ``DP3Config``.
    """

    config: Any

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


def predict_x0(schedule: DiffusionSchedule, a_k: Array, eps: Array, k: Array,
               clip: bool = True) -> Array:
    """The clean sample a noise prediction implies: ``(a_k - sqrt(1 - abar_k) eps) /
    sqrt(abar_k)``, clipped to ``[-1, 1]`` as DDIM clips it (``clip``).

    Args:
      a_k, eps: ``[B, ...]``. k: ``[B]`` int steps.
    Returns:
      ``[B, ...]``.
    """
    acp = schedule.alphas_cumprod[k].reshape((-1,) + (1,) * (a_k.ndim - 1))
    x0 = (a_k - jnp.sqrt(1.0 - acp) * eps) / jnp.sqrt(acp)
    return jnp.clip(x0, -1.0, 1.0) if clip else x0


def ddim_timesteps(num_train_steps: int, num_inference_steps: int) -> np.ndarray:
    """DDIM's "leading" timesteps, descending: ``[n]`` int32, e.g. 100/10 -> 90, 80, ..., 0."""
    ratio = num_train_steps // num_inference_steps
    return (np.arange(num_inference_steps) * ratio)[::-1].astype(np.int32)


def eps_from_x0(schedule: DiffusionSchedule, a_k: Array, x0: Array, k: Array) -> Array:
    """The noise a clean-sample prediction implies: ``(a_k - sqrt(abar_k) x0) /
    sqrt(1 - abar_k)``. ``a_k, x0``: ``[B, ...]``; ``k``: ``[B]`` int steps."""
    acp = schedule.alphas_cumprod[k].reshape((-1,) + (1,) * (a_k.ndim - 1))
    return (a_k - jnp.sqrt(acp) * x0) / jnp.sqrt(1.0 - acp)


def ddim_loop(
    eps_fn: Callable[[Array, Array], Array],
    x_init: Array,
    schedule: DiffusionSchedule,
    num_inference_steps: int,
    clip_sample: bool = True,
    prediction: str = "epsilon",
) -> Array:
    """Deterministic DDIM (``eta = 0``) from ``x_init`` down to ``x_0``, as a ``lax.scan``.

    Args:
      eps_fn: ``(x [B, ...], k [B]) -> [B, ...]``, the network's output: the noise
        (``prediction="epsilon"``) or the clean sample (``"sample"``).
      x_init: ``[B, ...]`` initial Gaussian noise.
      schedule: training schedule (``K`` steps).
      num_inference_steps: number of DDIM updates.
      clip_sample: clip the predicted ``x0`` to ``[-1, 1]``.
      prediction: what ``eps_fn`` predicts, one of :data:`PREDICTIONS`. For ``"sample"``
        the noise of the update is the one the unclipped prediction implies.
    Returns:
      ``[B, ...]`` denoised sample.
    """
    if prediction not in PREDICTIONS:
        raise ValueError(f"prediction must be one of {PREDICTIONS}, got {prediction!r}")
    num_train = schedule.alphas_cumprod.shape[0]
    ratio = num_train // num_inference_steps
    ts = jnp.asarray(ddim_timesteps(num_train, num_inference_steps))
    acp = schedule.alphas_cumprod

    def body(x, t):
        out = eps_fn(x, jnp.full((x.shape[0],), t, jnp.int32))
        a_t = acp[t]
        prev = t - ratio
        a_prev = jnp.where(prev >= 0, acp[jnp.maximum(prev, 0)], 1.0)
        if prediction == "epsilon":
            eps = out
            x0 = (x - jnp.sqrt(1.0 - a_t) * eps) / jnp.sqrt(a_t)
        else:
            x0 = out
            eps = (x - jnp.sqrt(a_t) * x0) / jnp.sqrt(1.0 - a_t)
        if clip_sample:
            x0 = jnp.clip(x0, -1.0, 1.0)
        return jnp.sqrt(a_prev) * x0 + jnp.sqrt(1.0 - a_prev) * eps, None

    x, _ = jax.lax.scan(body, x_init, ts)
    return x
