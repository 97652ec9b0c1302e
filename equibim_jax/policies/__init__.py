"""Policies: the diffusion policy (1D conditional U-Net) and observation encoders."""

from equibim_jax.policies.diffusion import (
    DiffusionSchedule,
    EmaConfig,
    NoisePredictor,
    PolicyApplyFn,
    PolicyConfig,
    add_noise,
    ddim_loop,
    ddim_timesteps,
    ema_decay,
    ema_update,
    example_obs,
    init_params,
    make_schedule,
    predict_action,
    sample_actions,
    squared_cosine_betas,
)
from equibim_jax.policies.encoders import EncoderConfig, ObsEncoder, PointCloudEncoder, StateEncoder
from equibim_jax.policies.unet1d import ConditionalUnet1D, Conv1d, UNetConfig, sinusoidal_embedding

__all__ = [
    "ConditionalUnet1D",
    "Conv1d",
    "DiffusionSchedule",
    "EmaConfig",
    "EncoderConfig",
    "NoisePredictor",
    "ObsEncoder",
    "PolicyApplyFn",
    "PointCloudEncoder",
    "PolicyConfig",
    "StateEncoder",
    "UNetConfig",
    "add_noise",
    "ddim_loop",
    "ddim_timesteps",
    "ema_decay",
    "ema_update",
    "example_obs",
    "init_params",
    "make_schedule",
    "predict_action",
    "sample_actions",
    "sinusoidal_embedding",
]
