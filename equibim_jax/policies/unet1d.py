"""Conditional 1D U-Net noise predictor (Chi et al.'s ConditionalUnet1D, channels-last).

Layout is ``[B, T, C]`` throughout. Convolutions default to im2col (pad, stack the ``k``
shifted views, one matmul), which XLA on CPU runs several times faster than
``lax.conv_general_dilated`` (what ``flax.linen.Conv`` calls) inside a whole train step;
``conv_impl="xla"`` selects the latter with the *same* parameters, for comparison.
Upsampling is nearest repeat followed by a conv: transposed convs are very slow on XLA
CPU. Downsampling is a stride-2, kernel-3 conv.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal

import flax.linen as nn
import jax
import jax.numpy as jnp

Array = Any
ConvImpl = Literal["im2col", "xla"]

__all__ = ["UNetConfig", "Conv1d", "ConditionalUnet1D", "sinusoidal_embedding"]


@dataclasses.dataclass(frozen=True)
class UNetConfig:
    """Shape of the conditional U-Net.

    Attributes:
      down_dims: channel widths per level (Diffusion Policy uses ``(256, 512, 1024)``; the
        default is CPU-sized); the sequence is
        halved between consecutive levels, so the horizon must be divisible by
        ``2 ** (len(down_dims) - 1)``.
      kernel_size: odd temporal kernel of the residual blocks (5 in the paper setup).
      n_groups: GroupNorm groups; must divide every width in ``down_dims``.
      step_embed_dim: width of the diffusion-step embedding.
      conv_impl: ``"im2col"`` (fast on CPU) or ``"xla"`` (``lax.conv_general_dilated``).
    """

    down_dims: tuple[int, ...] = (32, 64, 128)
    kernel_size: int = 5
    n_groups: int = 8
    step_embed_dim: int = 128
    conv_impl: ConvImpl = "im2col"

    def __post_init__(self):
        dims = tuple(self.down_dims)
        object.__setattr__(self, "down_dims", dims)
        if not dims or any(int(d) <= 0 for d in dims):
            raise ValueError(f"UNetConfig.down_dims must be non-empty positive ints, got {dims}")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ValueError(f"UNetConfig.kernel_size must be odd and >= 1, got {self.kernel_size}")
        if self.n_groups < 1 or any(d % self.n_groups for d in dims):
            raise ValueError(
                f"UNetConfig.n_groups={self.n_groups} must divide every down_dim {dims}"
            )
        if self.step_embed_dim < 2 or self.step_embed_dim % 2:
            raise ValueError(
                f"UNetConfig.step_embed_dim must be even and >= 2, got {self.step_embed_dim}"
            )
        if self.conv_impl not in ("im2col", "xla"):
            raise ValueError(f"UNetConfig.conv_impl must be 'im2col' or 'xla', got {self.conv_impl!r}")

    def check_horizon(self, horizon: int) -> None:
        """Raise ValueError unless ``horizon`` survives the U-Net's halvings."""
        factor = 2 ** (len(self.down_dims) - 1)
        if horizon % factor:
            raise ValueError(
                f"prediction horizon {horizon} must be divisible by {factor} "
                f"(2 ** (len(down_dims) - 1) with down_dims={self.down_dims})"
            )


def sinusoidal_embedding(k: Array, dim: int) -> Array:
    """Transformer-style sinusoidal embedding of diffusion steps.

    Args:
      k: ``[B]`` int or float steps. dim: even embedding width.
    Returns:
      ``[B, dim]`` float32, ``[sin(k w_j), cos(k w_j)]``.
    """
    half = dim // 2
    freqs = jnp.exp(-math.log(10000.0) * jnp.arange(half, dtype=jnp.float32) / max(half - 1, 1))
    ang = k.astype(jnp.float32)[:, None] * freqs[None, :]
    return jnp.concatenate([jnp.sin(ang), jnp.cos(ang)], axis=-1)


class Conv1d(nn.Module):
    """1D convolution over ``[B, T, C]`` with 'same'-style padding ``k // 2``.

    Parameters ``kernel [k, C_in, C_out]`` and ``bias [C_out]`` have the layout of
    ``flax.linen.Conv``, whichever ``impl`` runs, so both impls are interchangeable.

    Attributes:
      features: output channels. kernel_size: odd ``k``. stride: 1 or 2.
      impl: ``"im2col"`` or ``"xla"``.
    """

    features: int
    kernel_size: int
    stride: int = 1
    impl: ConvImpl = "im2col"

    @nn.compact
    def __call__(self, x: Array) -> Array:
        """``x [B, T, C_in] -> [B, ceil(T / stride), C_out]``."""
        k, c_in = self.kernel_size, x.shape[-1]
        kernel = self.param(
            "kernel", nn.initializers.lecun_normal(), (k, c_in, self.features), jnp.float32
        )
        bias = self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32)
        pad = k // 2
        if self.impl == "xla":
            y = jax.lax.conv_general_dilated(
                x,
                kernel,
                window_strides=(self.stride,),
                padding=[(pad, pad)],
                dimension_numbers=("NWC", "WIO", "NWC"),
            )
            return y + bias
        t = x.shape[1]
        t_out = -(-t // self.stride)
        xp = jnp.pad(x, ((0, 0), (pad, pad), (0, 0)))
        # View i holds x[t * stride + i - pad]; stacking gives [B, T_out, k, C_in], whose
        # flattening (i * C_in + c) matches kernel.reshape(k * C_in, C_out).
        views = [xp[:, i : i + self.stride * (t_out - 1) + 1 : self.stride] for i in range(k)]
        cols = jnp.stack(views, axis=2).reshape(x.shape[0], t_out, k * c_in)
        # One 2-D matmul: XLA:CPU runs the weight gradient of a dot with several
        # contracting dims (here B and T) about 10x slower than the 2-D form.
        y = cols.reshape(-1, k * c_in) @ kernel.reshape(k * c_in, self.features)
        return y.reshape(x.shape[0], t_out, self.features) + bias


class Conv1dBlock(nn.Module):
    """Conv -> GroupNorm -> Mish. ``[B, T, C_in] -> [B, T, features]``."""

    features: int
    kernel_size: int
    n_groups: int
    impl: ConvImpl

    @nn.compact
    def __call__(self, x: Array) -> Array:
        x = Conv1d(self.features, self.kernel_size, impl=self.impl)(x)
        x = nn.GroupNorm(num_groups=self.n_groups, epsilon=1e-5)(x)
        return jax.nn.mish(x)


class CondResBlock1d(nn.Module):
    """Residual block with FiLM conditioning (per-channel scale and bias from ``cond``).

    ``x [B, T, C_in], cond [B, D_cond] -> [B, T, features]``.
    """

    features: int
    kernel_size: int
    n_groups: int
    impl: ConvImpl

    @nn.compact
    def __call__(self, x: Array, cond: Array) -> Array:
        out = Conv1dBlock(self.features, self.kernel_size, self.n_groups, self.impl)(x)
        film = nn.Dense(2 * self.features)(jax.nn.mish(cond))
        scale, bias = jnp.split(film[:, None, :], 2, axis=-1)
        out = scale * out + bias
        out = Conv1dBlock(self.features, self.kernel_size, self.n_groups, self.impl)(out)
        if x.shape[-1] != self.features:
            x = Conv1d(self.features, 1, impl=self.impl)(x)
        return out + x


class ConditionalUnet1D(nn.Module):
    """ε-predictor ``eps(a_k, k, cond)`` over action sequences.

    Attributes:
      config: :class:`UNetConfig`.
    """

    config: UNetConfig

    @nn.compact
    def __call__(self, x: Array, k: Array, global_cond: Array) -> Array:
        """Predict the noise in ``x``.

        Args:
          x: ``[B, Tp, A]`` noisy normalised actions.
          k: ``[B]`` diffusion steps (int).
          global_cond: ``[B, D_obs]`` observation embedding.
        Returns:
          ``[B, Tp, A]`` predicted noise.
        """
        cfg = self.config
        cfg.check_horizon(x.shape[1])
        kw = dict(kernel_size=cfg.kernel_size, n_groups=cfg.n_groups, impl=cfg.conv_impl)
        d = cfg.step_embed_dim
        emb = sinusoidal_embedding(k, d)
        emb = nn.Dense(4 * d)(emb)
        emb = nn.Dense(d)(jax.nn.mish(emb))
        cond = jnp.concatenate([emb, global_cond], axis=-1)

        dims = cfg.down_dims
        skips = []
        h = x
        for i, dim in enumerate(dims):
            h = CondResBlock1d(dim, **kw)(h, cond)
            h = CondResBlock1d(dim, **kw)(h, cond)
            skips.append(h)
            if i < len(dims) - 1:
                h = Conv1d(dim, 3, stride=2, impl=cfg.conv_impl)(h)
        for _ in range(2):
            h = CondResBlock1d(dims[-1], **kw)(h, cond)
        # Up path: levels len-2 .. 0; the deepest skip pairs with the mid output.
        for i in reversed(range(len(dims) - 1)):
            h = jnp.concatenate([h, skips[i + 1]], axis=-1)
            h = CondResBlock1d(dims[i], **kw)(h, cond)
            h = CondResBlock1d(dims[i], **kw)(h, cond)
            h = jnp.repeat(h, 2, axis=1)
            h = Conv1d(dims[i], 3, impl=cfg.conv_impl)(h)
        h = Conv1dBlock(dims[0], cfg.kernel_size, cfg.n_groups, cfg.conv_impl)(h)
        return Conv1d(x.shape[-1], 1, impl=cfg.conv_impl)(h)
