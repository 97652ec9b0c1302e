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

import functools
import math
from collections.abc import Callable, Mapping
from typing import Any

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

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
    "SYM_TARGETS",
    "ddim_sample",
    "make_diffusion_policy",
]

PREDICTIONS = ("epsilon", "sample")
SYM_TARGETS = ("eps", "x0")


class NoisePredictor(nn.Module):
    """``eps(a_k, k, O)``: observation encoder + conditional 1D U-Net.

    Attributes:
      config: a diffusion-policy config (``DP3Config``, ``DPConfig``): a ``unet``
        (:class:`UNetConfig`) field and a ``make_encoder()`` method returning the
        observation encoder module (``obs -> [B, D_cond]``).
    """

    config: Any

    def setup(self):
        self.encoder = self.config.make_encoder()
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


@functools.partial(jax.jit, static_argnums=0)
def _init(config: Any, key: Array) -> Any:
    # Jitted: op-by-op initialisation of the U-Net dispatches hundreds of small ops.
    x = jnp.zeros((1, config.pred_horizon, config.action_dim), jnp.float32)
    k = jnp.zeros((1,), jnp.int32)
    return NoisePredictor(config).init(key, x, k, config.example_obs())["params"]


def ddim_sample(model: NoisePredictor, params: Any, obs: Mapping[str, Array], key: Array,
                schedule: DiffusionSchedule, noise_op: Callable[[Array], Array] | None = None) -> Array:
    """Sample normalised action chunks with DDIM.

    Args:
      model: the :class:`NoisePredictor` of a diffusion-policy config.
      params: its ``"params"`` collection.
      obs: ``{field: [B, To, ...]}`` normalised observations, as the encoder reads them.
      key: PRNG key of the initial noise; same key, same output.
      schedule: the training schedule.
      noise_op: applied to the initial noise ``[B, Tp, A]`` drawn from ``key`` (e.g. the
        action mirror ``S_a``, a signed permutation, so the noise stays ``N(0, I)``).
    Returns:
      ``[B, Tp, A]`` normalised actions.
    """
    cfg = model.config
    variables = {"params": params}
    cond = model.apply(variables, obs, method=NoisePredictor.encode)
    x_init = jax.random.normal(key, (cond.shape[0], cfg.pred_horizon, cfg.action_dim), jnp.float32)
    if noise_op is not None:
        x_init = noise_op(x_init)

    def eps_fn(x, k):
        return model.apply(variables, x, k, cond, method=NoisePredictor.denoise)

    return ddim_loop(eps_fn, x_init, schedule, cfg.num_inference_steps, cfg.clip_sample, cfg.prediction)


def make_diffusion_policy(
    config: Any,
    augment: Callable[[dict, Array], dict] | None = None,
    eval_obs: Callable[[dict], dict] | None = None,
):
    """A diffusion :class:`~equibim_jax.policies.base.Policy` (DDPM training, DDIM sampling).

    The network reads a noisy normalised action chunk ``a_k``, the step ``k`` and the
    observations, and predicts the noise (``config.prediction == "epsilon"``) or the clean
    chunk (``"sample"``); the BC loss is the mean squared error against that target. What
    ``L_sym`` compares (``config.sym_target``):

    * ``"eps"``: the noise, ``eps(S_a a_k, k, S O)`` against ``S_a eps(a_k, k, O)`` at the
      same ``k`` and with the same noise mirrored (``S_a a_k`` is the noisy mirrored action
      because ``S_a`` is linear in normalised space); with sample-prediction, the noise the
      predicted sample implies;
    * ``"x0"``: the clean actions, clipped to ``[-1, 1]`` as DDIM clips them: implied by the
      noise prediction (:func:`predict_x0`) or predicted directly. For unclipped entries
      the ``x0`` residual is the ``eps`` residual times ``sqrt((1 - abar_k) / abar_k)``, so
      it weighs the high-noise steps far more.

    Args:
      config: a resolved config with the horizons, ``action_key``, ``obs_keys``, ``unet``,
        ``num_train_steps``, ``num_inference_steps``, ``clip_sample``, ``sym_target``,
        ``prediction``, ``make_encoder()`` and ``example_obs()``.
      augment: ``(obs, key) -> obs``, the training-time observation augmentation (drawn in
        ``prepare``, so the mirrored branch sees ``S`` of the augmented sample).
      eval_obs: ``obs -> obs`` applied before sampling (e.g. the centre crop).
    Returns:
      the policy: ``inputs = {"obs": {field: [B, To, ...]}, "noisy_action": [B, Tp, A],
      "k": [B]}``; ``targets = {"noise"}`` (epsilon) or ``{"sample"}``, ``[B, Tp, A]``;
      ``pred [B, Tp, A]``.
    """
    from equibim_jax.policies.base import Policy

    model = NoisePredictor(config)
    schedule = make_schedule(config.num_train_steps)
    akey = config.action_key
    eps_mode = config.prediction == "epsilon"
    tkey = "noise" if eps_mode else "sample"

    def init(key):
        return _init(config, key)

    def prepare(batch, key):
        if augment is not None:  # split only then: augmentation-free streams stay as they were
            key, k_aug = jax.random.split(key)
        k_noise, k_step = jax.random.split(key)
        a0 = batch[akey]
        noise = jax.random.normal(k_noise, a0.shape, a0.dtype)
        k = jax.random.randint(k_step, (a0.shape[0],), 0, config.num_train_steps)
        obs = {f: batch[f] for f in config.obs_keys}
        if augment is not None:
            obs = augment(obs, k_aug)
        inputs = {"obs": obs, "noisy_action": add_noise(schedule, a0, noise, k), "k": k}
        return inputs, {tkey: noise if eps_mode else a0}

    def apply(params, inputs):
        return model.apply({"params": params}, inputs["noisy_action"], inputs["k"], inputs["obs"])

    def bc_loss(pred, targets):
        return jnp.mean(jnp.square(pred - targets[tkey]))

    def mirror_inputs(sym, inputs):
        # Same k, same noise mirrored: S_a a_k == add_noise(S_a a0, S_a noise, k), S_a linear.
        return {"obs": {f: sym[f](v) for f, v in inputs["obs"].items()},
                "noisy_action": sym[akey](inputs["noisy_action"]), "k": inputs["k"]}

    def mirror_targets(sym, targets):
        return {tkey: sym[akey](targets[tkey])}

    def sym_view(inputs, pred):
        # S_a is a signed permutation in normalised space: it commutes with the clip.
        if eps_mode:
            if config.sym_target == "eps":
                return pred
            return predict_x0(schedule, inputs["noisy_action"], pred, inputs["k"])
        if config.sym_target == "eps":
            return eps_from_x0(schedule, inputs["noisy_action"], pred, inputs["k"])
        return jnp.clip(pred, -1.0, 1.0)

    def mirror_view(sym, view):
        return sym[akey](view)

    def sample(params, obs, key, noise_op=None):
        obs = {f: obs[f] for f in config.obs_keys}
        if eval_obs is not None:
            obs = eval_obs(obs)
        return ddim_sample(model, params, obs, key, schedule, noise_op)

    return Policy(config=config, init=init, prepare=prepare, apply=apply, bc_loss=bc_loss,
                  mirror_inputs=mirror_inputs, mirror_targets=mirror_targets, sym_view=sym_view,
                  mirror_view=mirror_view, sample=sample)
