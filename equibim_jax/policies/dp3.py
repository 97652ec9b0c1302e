"""``dp3``: a DP3-style diffusion policy (state + optional point cloud, 1D conditional U-Net).

The network reads a noisy normalised action chunk ``a_k`` of a DDPM forward process, the
step ``k`` and the observations, and predicts either the noise (``prediction="epsilon"``,
the default) or the clean chunk (``prediction="sample"``, DP3's other option); the BC
loss is the mean squared error against that target. Sampling is deterministic DDIM from
Gaussian noise. What ``L_sym`` compares (``DP3Config.sym_target``):

* ``"eps"``: the noise, ``eps(S_a a_k, k, S O)`` against ``S_a eps(a_k, k, O)`` at the
  same ``k`` and with the same noise mirrored (``S_a a_k`` is the noisy mirrored action
  because ``S_a`` is linear in normalised space); with sample-prediction, the noise the
  predicted sample implies;
* ``"x0"``: the clean actions, clipped to ``[-1, 1]`` as DDIM clips them: implied by the
  noise prediction (:func:`~equibim_jax.policies.diffusion.predict_x0`) or predicted
  directly. For unclipped entries the ``x0`` residual is the ``eps`` residual times
  ``sqrt((1 - abar_k) / abar_k)``, so it weights the high-noise steps far more.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import jax
import jax.numpy as jnp

from equibim_jax.policies.base import Policy, PolicyConfig
from equibim_jax.policies.diffusion import (
    PREDICTIONS,
    DiffusionSchedule,
    NoisePredictor,
    add_noise,
    ddim_loop,
    eps_from_x0,
    make_schedule,
    predict_x0,
)
from equibim_jax.policies.encoders import EncoderConfig
from equibim_jax.policies.unet1d import UNetConfig

Array = Any

__all__ = ["DP3Config", "make_dp3", "ddim_sample", "SYM_TARGETS"]

SYM_TARGETS = ("eps", "x0")


@dataclasses.dataclass(frozen=True)
class DP3Config(PolicyConfig):
    """The ``dp3`` policy (hashable; see :class:`~equibim_jax.policies.base.PolicyConfig`
    for the horizon and dims fields).

    Attributes:
      encoder: which observation fields are read and how wide the encoders are.
      unet: the conditional 1D U-Net.
      num_train_steps: DDPM steps ``K`` (noise levels seen in training).
      num_inference_steps: DDIM steps at sampling time.
      clip_sample: clip DDIM's predicted ``x0`` to ``[-1, 1]`` (the normalised range).
      sym_target: what ``L_sym`` compares, ``"eps"`` or ``"x0"`` (module docstring).
      prediction: what the network predicts, ``"epsilon"`` (the noise) or ``"sample"``
        (the clean action chunk).
    """

    name: ClassVar[str] = "dp3"
    encoder: EncoderConfig = EncoderConfig()
    unet: UNetConfig = UNetConfig()
    num_train_steps: int = 100
    num_inference_steps: int = 10
    clip_sample: bool = True
    sym_target: str = "eps"
    prediction: str = "epsilon"

    def __post_init__(self):
        super().__post_init__()
        self.unet.check_horizon(self.pred_horizon)
        if not 1 <= self.num_inference_steps <= self.num_train_steps:
            raise ValueError(
                f"DP3Config: need 1 <= num_inference_steps ({self.num_inference_steps}) "
                f"<= num_train_steps ({self.num_train_steps})"
            )
        if self.sym_target not in SYM_TARGETS:
            raise ValueError(f"DP3Config.sym_target must be one of {SYM_TARGETS}, got {self.sym_target!r}")
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"DP3Config.prediction must be one of {PREDICTIONS}, got {self.prediction!r}")

    @property
    def obs_keys(self) -> tuple[str, ...]:
        return self.encoder.keys

    @property
    def state_key(self) -> str:
        return self.encoder.state_key


def _example_obs(config: DP3Config, batch: int = 1, num_points: int = 16) -> dict[str, Array]:
    """Zero observations of the right shapes (the point count does not change the params)."""
    enc, to = config.encoder, config.obs_horizon
    obs = {enc.state_key: jnp.zeros((batch, to, config.state_dim), jnp.float32)}
    if enc.pc_key is not None:
        obs[enc.pc_key] = jnp.zeros((batch, to, num_points, 3), jnp.float32)
    return obs


@functools.partial(jax.jit, static_argnums=0)
def _init(config: DP3Config, key: Array) -> Any:
    # Jitted: op-by-op initialisation of the U-Net dispatches hundreds of small ops.
    x = jnp.zeros((1, config.pred_horizon, config.action_dim), jnp.float32)
    k = jnp.zeros((1,), jnp.int32)
    return NoisePredictor(config).init(key, x, k, _example_obs(config))["params"]


def ddim_sample(model: NoisePredictor, params: Any, obs: Mapping[str, Array], key: Array,
                schedule: DiffusionSchedule, noise_op: Callable[[Array], Array] | None = None) -> Array:
    """Sample normalised action chunks with DDIM.

    Args:
      model: the :class:`NoisePredictor` (its ``config`` is a :class:`DP3Config`).
      params: its ``"params"`` collection.
      obs: ``{field: [B, To, ...]}`` normalised observations.
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


def make_dp3(config: DP3Config) -> Policy:
    """The ``dp3`` :class:`~equibim_jax.policies.base.Policy` of a resolved config.

    ``inputs = {"obs": {field: [B, To, ...]}, "noisy_action": [B, Tp, A], "k": [B]}``;
    ``targets = {"noise": [B, Tp, A]}`` and ``pred`` the noise for epsilon-prediction,
    ``targets = {"sample": [B, Tp, A]}`` and ``pred`` the clean chunk for sample-prediction.
    """
    model = NoisePredictor(config)
    schedule = make_schedule(config.num_train_steps)
    akey = config.action_key
    eps_mode = config.prediction == "epsilon"
    tkey = "noise" if eps_mode else "sample"

    def init(key):
        return _init(config, key)

    def prepare(batch, key):
        k_noise, k_step = jax.random.split(key)
        a0 = batch[akey]
        noise = jax.random.normal(k_noise, a0.shape, a0.dtype)
        k = jax.random.randint(k_step, (a0.shape[0],), 0, config.num_train_steps)
        inputs = {"obs": {f: batch[f] for f in config.obs_keys},
                  "noisy_action": add_noise(schedule, a0, noise, k), "k": k}
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
        return ddim_sample(model, params, obs, key, schedule, noise_op)

    return Policy(config=config, init=init, prepare=prepare, apply=apply, bc_loss=bc_loss,
                  mirror_inputs=mirror_inputs, mirror_targets=mirror_targets, sym_view=sym_view,
                  mirror_view=mirror_view, sample=sample)
