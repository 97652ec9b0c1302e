"""Exponential moving average of the parameters, as Diffusion Policy's EMAModel."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

Array = Any

__all__ = ["EmaConfig", "ema_decay", "ema_update"]


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
