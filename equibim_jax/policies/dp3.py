"""``dp3``: a DP3-style diffusion policy (state + optional point cloud, 1D conditional U-Net).

The observation encoder is DP3's (:class:`~equibim_jax.policies.encoders.ObsEncoder`: a
state MLP and a per-point MLP with max-pooling); the rest, training, sampling and what
``L_sym`` compares (``sym_target``), is the shared diffusion policy of
:func:`~equibim_jax.policies.diffusion.make_diffusion_policy`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax.numpy as jnp

from equibim_jax.policies.base import Policy, PolicyConfig
from equibim_jax.policies.diffusion import (
    PREDICTIONS,
    SYM_TARGETS,
    ddim_sample,
    make_diffusion_policy,
)
from equibim_jax.policies.encoders import EncoderConfig, ObsEncoder
from equibim_jax.policies.unet1d import UNetConfig

Array = Any

__all__ = ["DP3Config", "make_dp3", "ddim_sample", "SYM_TARGETS", "check_diffusion_fields"]


def check_diffusion_fields(config: Any) -> None:
    """Validate the diffusion fields every diffusion-policy config shares."""
    name = type(config).__name__
    config.unet.check_horizon(config.pred_horizon)
    if not 1 <= config.num_inference_steps <= config.num_train_steps:
        raise ValueError(
            f"{name}: need 1 <= num_inference_steps ({config.num_inference_steps}) "
            f"<= num_train_steps ({config.num_train_steps})"
        )
    if config.sym_target not in SYM_TARGETS:
        raise ValueError(f"{name}.sym_target must be one of {SYM_TARGETS}, got {config.sym_target!r}")
    if config.prediction not in PREDICTIONS:
        raise ValueError(f"{name}.prediction must be one of {PREDICTIONS}, got {config.prediction!r}")


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
      sym_target: what ``L_sym`` compares, ``"eps"`` or ``"x0"`` (see
        :func:`~equibim_jax.policies.diffusion.make_diffusion_policy`).
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
        check_diffusion_fields(self)

    @property
    def obs_keys(self) -> tuple[str, ...]:
        return self.encoder.keys

    @property
    def state_key(self) -> str:
        return self.encoder.state_key

    def make_encoder(self) -> ObsEncoder:
        """The observation encoder module, ``obs -> [B, To * (state_out + pc_out)]``."""
        return ObsEncoder(self.encoder)

    def example_obs(self, batch: int = 1, num_points: int = 16) -> dict[str, Array]:
        """Zero observations of the right shapes (the point count does not change the params)."""
        enc, to = self.encoder, self.obs_horizon
        obs = {enc.state_key: jnp.zeros((batch, to, self.state_dim), jnp.float32)}
        if enc.pc_key is not None:
            obs[enc.pc_key] = jnp.zeros((batch, to, num_points, 3), jnp.float32)
        return obs


def make_dp3(config: DP3Config) -> Policy:
    """The ``dp3`` :class:`~equibim_jax.policies.base.Policy` of a resolved config.

    ``inputs = {"obs": {field: [B, To, ...]}, "noisy_action": [B, Tp, A], "k": [B]}``;
    ``targets = {"noise": [B, Tp, A]}`` and ``pred`` the noise for epsilon-prediction,
    ``targets = {"sample": [B, Tp, A]}`` and ``pred`` the clean chunk for sample-prediction.
    """
    return make_diffusion_policy(config)
