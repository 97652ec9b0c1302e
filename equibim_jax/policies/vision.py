"""Image encoders and the random-crop augmentation of the image policies.

* :class:`Conv2d`: a 2-D convolution with ``flax.linen.Conv``'s parameter layout, run
  either as im2col plus one matmul (the default: on XLA:CPU a matmul and its transpose
  are much faster than the convolution's backward pass) or as ``lax.conv_general_dilated``.
* :class:`ResNetTrunk`: a small ResNet (GroupNorm instead of BatchNorm, as Diffusion
  Policy replaces it, so that the EMA and batch composition do not interact with batch
  statistics): a strided stem and one basic residual block per stage, each stage after
  the first halving the resolution. ``[N, H, W, C] -> [N, h, w, channels[-1]]``.
* :class:`SpatialSoftmax`: per-keypoint softmax over the feature map and the expected
  image coordinates, ``[N, h, w, C] -> [N, 2 K]`` (robomimic's and Diffusion Policy's
  replacement for global average pooling; it keeps *where* things are).
* :class:`ImageEncoder`: trunk, spatial softmax and a linear projection,
  ``[N, H, W, C] -> [N, out]``.
* Crops: :func:`random_crop_offsets`, :func:`crop_at`, :func:`center_crop`,
  :func:`mirror_crop_offsets`. A crop at column offset ``c`` of a ``W``-wide image,
  ``w`` wide, flipped left-right, is the crop of the flipped image at column offset
  ``W - w - c`` (same row), so a mirrored training sample built by applying ``S`` to the
  cropped images is exactly the mirror image of the same crop.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import flax.linen as nn
import jax
import jax.numpy as jnp

Array = Any
ConvImpl = Literal["im2col", "xla"]

__all__ = [
    "VisionConfig",
    "Conv2d",
    "ResNetTrunk",
    "SpatialSoftmax",
    "ImageEncoder",
    "crop_size",
    "random_crop_offsets",
    "crop_at",
    "center_crop",
    "mirror_crop_offsets",
]


@dataclasses.dataclass(frozen=True)
class VisionConfig:
    """One camera's image encoder (frozen, hashable).

    Attributes:
      channels: output channels of each ResNet stage; the stem (3x3 conv, stride 2) has
        ``channels[0]``, and every stage after the first starts with stride 2.
      groups: GroupNorm groups (each stage's channel count must be a multiple).
      keypoints: spatial-softmax keypoints ``K`` (features ``2 K`` before the projection).
      out: feature width per image.
      crop_ratio: side of the random training crop (and of the evaluation centre crop)
        as a fraction of the image side, in ``(0, 1]``; 1 turns cropping off.
      conv_impl: ``"im2col"`` or ``"xla"`` (see :class:`Conv2d`); the parameters are the
        same either way, so a checkpoint trained with one runs with the other.
    """

    channels: tuple[int, ...] = (16, 32, 64)
    groups: int = 8
    keypoints: int = 32
    out: int = 64
    crop_ratio: float = 0.875
    conv_impl: ConvImpl = "im2col"

    def __post_init__(self):
        ch = tuple(int(c) for c in self.channels)
        object.__setattr__(self, "channels", ch)
        if not ch or any(c <= 0 for c in ch):
            raise ValueError(f"VisionConfig.channels must be non-empty positive ints, got {ch}")
        if self.groups < 1 or any(c % self.groups for c in ch):
            raise ValueError(f"VisionConfig: every stage's channels {ch} must be a multiple of "
                             f"groups={self.groups}")
        if self.keypoints < 1 or self.out < 1:
            raise ValueError(f"VisionConfig: keypoints and out must be >= 1, got "
                             f"{self.keypoints}, {self.out}")
        if not 0.0 < self.crop_ratio <= 1.0:
            raise ValueError(f"VisionConfig.crop_ratio must be in (0, 1], got {self.crop_ratio}")
        if self.conv_impl not in ("im2col", "xla"):
            raise ValueError(f"VisionConfig.conv_impl must be 'im2col' or 'xla', got "
                             f"{self.conv_impl!r}")

    @property
    def downsample(self) -> int:
        """Total stride of the trunk."""
        return 2 ** len(self.channels)


def crop_size(side: int, ratio: float) -> int:
    """The crop side for an image side and a crop ratio (at least 1 pixel)."""
    return max(1, int(round(side * ratio)))


class Conv2d(nn.Module):
    """2-D convolution without bias, ``[N, H, W, C_in] -> [N, ceil(H/s), ceil(W/s), C_out]``
    for an odd ``k x k`` kernel with padding ``k // 2`` and stride ``s``.

    The parameter ``kernel [k, k, C_in, C_out]`` has the layout of ``flax.linen.Conv``.
    ``impl="im2col"`` gathers the ``k*k`` shifted views into ``[N, h, w, k*k*C_in]`` and
    multiplies by the reshaped kernel; ``impl="xla"`` calls ``lax.conv_general_dilated``.
    Both compute the same function.
    """

    features: int
    kernel_size: int = 3
    stride: int = 1
    impl: ConvImpl = "im2col"

    @nn.compact
    def __call__(self, x: Array) -> Array:
        k, s, c_in = self.kernel_size, self.stride, x.shape[-1]
        if k % 2 != 1:
            raise ValueError(f"Conv2d needs an odd kernel size, got {k}")
        kernel = self.param("kernel", nn.initializers.lecun_normal(),
                            (k, k, c_in, self.features), jnp.float32)
        pad = k // 2
        if self.impl == "xla":
            return jax.lax.conv_general_dilated(
                x, kernel, window_strides=(s, s), padding=[(pad, pad), (pad, pad)],
                dimension_numbers=("NHWC", "HWIO", "NHWC"))
        n, h, w, _ = x.shape
        ho, wo = -(-h // s), -(-w // s)
        if k == 1:
            cols = x[:, : s * (ho - 1) + 1 : s, : s * (wo - 1) + 1 : s]
        else:
            xp = jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
            # View (i, j) holds x[r*s + i - pad, c*s + j - pad]; the concatenation order
            # (i, j, c_in) matches kernel.reshape(k*k*C_in, C_out).
            views = [xp[:, i : i + s * (ho - 1) + 1 : s, j : j + s * (wo - 1) + 1 : s]
                     for i in range(k) for j in range(k)]
            cols = jnp.concatenate(views, axis=-1)
        return jnp.dot(cols.reshape(n * ho * wo, k * k * c_in),
                       kernel.reshape(k * k * c_in, self.features)).reshape(n, ho, wo, self.features)


class _BasicBlock(nn.Module):
    channels: int
    stride: int
    groups: int
    impl: ConvImpl = "im2col"

    @nn.compact
    def __call__(self, x: Array) -> Array:
        h = Conv2d(self.channels, 3, self.stride, self.impl)(x)
        h = jax.nn.relu(nn.GroupNorm(self.groups)(h))
        h = Conv2d(self.channels, 3, 1, self.impl)(h)
        h = nn.GroupNorm(self.groups)(h)
        if self.stride != 1 or x.shape[-1] != self.channels:
            x = nn.GroupNorm(self.groups)(Conv2d(self.channels, 1, self.stride, self.impl)(x))
        return jax.nn.relu(h + x)


class ResNetTrunk(nn.Module):
    """ResNet-style feature extractor with GroupNorm: ``[N, H, W, C] -> [N, h, w, C']``
    with ``h = ceil(H / 2**len(channels))`` and ``C' = channels[-1]``."""

    channels: tuple[int, ...]
    groups: int
    impl: ConvImpl = "im2col"

    @nn.compact
    def __call__(self, x: Array) -> Array:
        x = Conv2d(self.channels[0], 3, 2, self.impl)(x)
        x = jax.nn.relu(nn.GroupNorm(self.groups)(x))
        for i, c in enumerate(self.channels):
            x = _BasicBlock(c, 1 if i == 0 else 2, self.groups, self.impl)(x)
        return x


class SpatialSoftmax(nn.Module):
    """Expected image coordinates of ``K`` learned keypoints: ``[N, h, w, C] -> [N, 2 K]``.

    Coordinates are in ``[-1, 1]``, x (column, left to right) then y (row, top to bottom)
    per keypoint.
    """

    keypoints: int

    @nn.compact
    def __call__(self, feat: Array) -> Array:
        n, h, w, _ = feat.shape
        logits = nn.Dense(self.keypoints, name="logits")(feat).reshape(n, h * w, self.keypoints)
        attn = jax.nn.softmax(logits, axis=1)  # [N, hw, K]
        ys, xs = jnp.meshgrid(jnp.linspace(-1.0, 1.0, h), jnp.linspace(-1.0, 1.0, w), indexing="ij")
        grid = jnp.stack([xs.reshape(-1), ys.reshape(-1)], axis=-1)  # [hw, 2]
        kp = jnp.einsum("npk,pd->nkd", attn, grid)
        return kp.reshape(n, 2 * self.keypoints)


class ImageEncoder(nn.Module):
    """One camera's encoder: ResNet trunk, spatial softmax, Dense.

    ``[..., H, W, C] -> [..., out]`` (leading axes flattened for the convolutions).
    """

    config: VisionConfig

    @nn.compact
    def __call__(self, images: Array) -> Array:
        cfg = self.config
        lead = images.shape[:-3]
        x = images.reshape((-1,) + images.shape[-3:])
        x = ResNetTrunk(cfg.channels, cfg.groups, cfg.conv_impl, name="trunk")(x)
        x = SpatialSoftmax(cfg.keypoints, name="keypoints")(x)
        x = nn.Dense(cfg.out, name="proj")(x)
        return x.reshape(lead + (cfg.out,))


def random_crop_offsets(key: Array, lead: tuple[int, ...], image_hw: tuple[int, int],
                        crop_hw: tuple[int, int]) -> Array:
    """Uniform crop offsets, one per image: int32 ``[*lead, 2]`` (row, column), each in
    ``[0, H - h]`` and ``[0, W - w]``."""
    (hh, ww), (ch, cw) = image_hw, crop_hw
    if not (1 <= ch <= hh and 1 <= cw <= ww):
        raise ValueError(f"crop {crop_hw} does not fit in images {image_hw}")
    hi = jnp.asarray([hh - ch + 1, ww - cw + 1], jnp.int32)
    return jax.random.randint(key, tuple(lead) + (2,), 0, hi, jnp.int32)


def crop_at(images: Array, offsets: Array, crop_hw: tuple[int, int]) -> Array:
    """Crop every image at its own offset.

    Args:
      images: ``[*lead, H, W, C]``.
      offsets: int ``[*lead, 2]`` (row, column) of each crop's top-left pixel.
      crop_hw: ``(h, w)``.
    Returns:
      ``[*lead, h, w, C]``.
    """
    lead = images.shape[:-3]
    if offsets.shape != lead + (2,):
        raise ValueError(f"crop offsets {offsets.shape} do not match images {images.shape}")
    flat = images.reshape((-1,) + images.shape[-3:])
    offs = offsets.reshape(-1, 2)
    c = images.shape[-1]

    def one(img, o):
        return jax.lax.dynamic_slice(img, (o[0], o[1], 0), (crop_hw[0], crop_hw[1], c))

    return jax.vmap(one)(flat, offs).reshape(lead + (crop_hw[0], crop_hw[1], c))


def center_crop(images: Array, crop_hw: tuple[int, int]) -> Array:
    """The centre crop ``[..., H, W, C] -> [..., h, w, C]``. For even ``H - h`` and
    ``W - w`` it is its own mirror image (it commutes with a left-right flip)."""
    hh, ww = images.shape[-3:-1]
    r, c = (hh - crop_hw[0]) // 2, (ww - crop_hw[1]) // 2
    return images[..., r : r + crop_hw[0], c : c + crop_hw[1], :]


def mirror_crop_offsets(offsets: Array, image_w: int, crop_w: int) -> Array:
    """Offsets of the crops that, in the left-right flipped images, show the flipped
    crops: ``(r, c) -> (r, W - w - c)``."""
    return offsets.at[..., 1].set(image_w - crop_w - offsets[..., 1])
