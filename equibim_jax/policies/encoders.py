"""Observation encoders: a state MLP and a DP3-style point-cloud encoder.

Both act per observation frame; :class:`ObsEncoder` concatenates the per-frame features
over the observation horizon ``To`` into one global conditioning vector, as DP3 does.
The point-cloud encoder (per-point MLP with LayerNorm, max-pool over points, projection)
is invariant to the order of points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

Array = Any

__all__ = ["EncoderConfig", "StateEncoder", "PointCloudEncoder", "ObsEncoder"]


@dataclasses.dataclass(frozen=True)
class EncoderConfig:
    """Which observation fields are encoded, and how wide.

    Attributes:
      state_key: field of ``[B, To, D_state]`` proprioception (e.g. joint positions).
      pc_key: field of ``[B, To, N, 3]`` point clouds, or ``None`` for state only.
      state_hidden: hidden widths of the state MLP.
      state_out: state feature width per frame.
      pc_hidden: hidden widths of the per-point MLP (DP3 itself uses ``(64, 128, 256)``;
        half of that is the CPU-sized default).
      pc_out: point-cloud feature width per frame after max-pool and projection.
    """

    state_key: str = "qpos"
    pc_key: str | None = "point_cloud"
    state_hidden: tuple[int, ...] = (64,)
    state_out: int = 64
    pc_hidden: tuple[int, ...] = (32, 64, 128)
    pc_out: int = 64

    def __post_init__(self):
        for name in ("state_hidden", "pc_hidden"):
            v = tuple(getattr(self, name))
            object.__setattr__(self, name, v)
            if any(int(w) <= 0 for w in v):
                raise ValueError(f"EncoderConfig.{name} must be positive ints, got {v}")
        if self.pc_key is not None and not self.pc_hidden:
            raise ValueError("EncoderConfig.pc_hidden must be non-empty when pc_key is set")
        for name in ("state_out", "pc_out"):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"EncoderConfig.{name} must be positive, got {getattr(self, name)}")
        if not self.state_key:
            raise ValueError("EncoderConfig.state_key must be a non-empty field name")
        if self.pc_key == self.state_key:
            raise ValueError(f"EncoderConfig.pc_key and state_key are both {self.state_key!r}")

    @property
    def keys(self) -> tuple[str, ...]:
        """Observation fields the encoder reads."""
        return (self.state_key,) + ((self.pc_key,) if self.pc_key is not None else ())

    def feature_dim(self, obs_horizon: int) -> int:
        """Width of the global conditioning vector for ``obs_horizon`` frames."""
        per_frame = self.state_out + (self.pc_out if self.pc_key is not None else 0)
        return obs_horizon * per_frame


class StateEncoder(nn.Module):
    """MLP on a state vector: ``[..., D_state] -> [..., out]``."""

    hidden: tuple[int, ...]
    out: int

    @nn.compact
    def __call__(self, x: Array) -> Array:
        for w in self.hidden:
            x = jax.nn.mish(nn.Dense(w)(x))
        return nn.Dense(self.out)(x)


class PointCloudEncoder(nn.Module):
    """DP3 encoder: per-point (Dense, LayerNorm, ReLU) stack, max-pool, Dense, LayerNorm.

    ``[..., N, 3] -> [..., out]``; invariant to permutations of the ``N`` points.
    """

    hidden: tuple[int, ...]
    out: int

    @nn.compact
    def __call__(self, points: Array) -> Array:
        lead, n = points.shape[:-2], points.shape[-2]
        # The per-point MLP on a 2-D [rows, C] array: XLA:CPU runs the weight gradient of a
        # Dense over [..., N, C] (several contracting dims) about 10x slower.
        h = points.reshape(-1, points.shape[-1])
        for w in self.hidden:
            h = jax.nn.relu(nn.LayerNorm()(nn.Dense(w)(h)))
        h = jnp.max(h.reshape(-1, n, h.shape[-1]), axis=1)
        h = nn.LayerNorm()(nn.Dense(self.out)(h))
        return h.reshape(*lead, self.out)


class ObsEncoder(nn.Module):
    """Encode an observation window into one conditioning vector.

    Attributes:
      config: :class:`EncoderConfig`.
    """

    config: EncoderConfig

    @nn.compact
    def __call__(self, obs: Mapping[str, Array]) -> Array:
        """Args:
          obs: ``{state_key: [B, To, D_state], pc_key: [B, To, N, 3]}`` (normalised).
        Returns:
          ``[B, To * (state_out + pc_out)]`` float32.
        """
        cfg = self.config
        missing = [k for k in cfg.keys if k not in obs]
        if missing:
            raise KeyError(f"ObsEncoder: observation is missing fields {missing}; has {list(obs)}")
        state = obs[cfg.state_key]
        feats = [StateEncoder(cfg.state_hidden, cfg.state_out, name="state")(state)]
        if cfg.pc_key is not None:
            feats.append(PointCloudEncoder(cfg.pc_hidden, cfg.pc_out, name="pc")(obs[cfg.pc_key]))
        f = jnp.concatenate(feats, axis=-1)  # [B, To, F]
        return f.reshape(f.shape[0], -1)
