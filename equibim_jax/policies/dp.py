"""``dp``: Diffusion Policy on images (the CNN variant of Chi et al.).

Each camera has its own :class:`~equibim_jax.policies.vision.ImageEncoder` (a small
ResNet with GroupNorm and a spatial softmax); a state MLP reads the proprioception. The
per-frame features of the ``To`` observation frames are concatenated into the global
condition of the 1D conditional U-Net, and training and sampling are the shared
diffusion policy's (:func:`~equibim_jax.policies.diffusion.make_diffusion_policy`).

Image fields hold one camera, ``[To, H, W, C]`` per sample, or several, ``[To, V, H, W, C]``
(e.g. the left and right wrist cameras); each view gets its own encoder.

Augmentation: during training every image is randomly cropped (its own offset per
sample, frame and view) to ``crop_ratio`` of its side; at inference the centre crop is
taken. The crop is drawn in ``prepare`` and the mirrored branch applies ``S`` to the
*cropped* images, which equals cropping the mirrored images at the mirrored offsets
(:func:`~equibim_jax.policies.vision.mirror_crop_offsets`), so ``L_sym`` compares the
policy on one crop and on exactly its mirror image, never on two different crops.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import tyro

from equibim_jax.policies.base import Policy, PolicyConfig
from equibim_jax.policies.diffusion import make_diffusion_policy
from equibim_jax.policies.dp3 import check_diffusion_fields
from equibim_jax.policies.encoders import StateEncoder
from equibim_jax.policies.unet1d import UNetConfig
from equibim_jax.policies.vision import (
    ImageEncoder,
    VisionConfig,
    center_crop,
    crop_at,
    crop_size,
    random_crop_offsets,
)

Array = Any

__all__ = ["DPConfig", "ImageObsConfig", "ImageFieldsMixin", "ImageObsEncoder", "make_dp",
           "augment_images", "eval_images"]


@dataclasses.dataclass(frozen=True)
class ImageObsConfig:
    """Which fields an image policy reads, and its encoders.

    Attributes:
      image_keys: image fields, ``[To, H, W, C]`` or ``[To, V, H, W, C]`` per sample.
      state_key: proprioception field ``[To, D]``, or ``None`` for images only.
      vision: the per-camera image encoder.
      state_hidden, state_out: the state MLP.
    """

    image_keys: tuple[str, ...] = ("image",)
    state_key: str | None = "qpos"
    vision: VisionConfig = VisionConfig()
    state_hidden: tuple[int, ...] = (64,)
    state_out: int = 64

    def __post_init__(self):
        keys = tuple(self.image_keys)
        object.__setattr__(self, "image_keys", keys)
        object.__setattr__(self, "state_hidden", tuple(int(w) for w in self.state_hidden))
        if len(set(keys)) != len(keys) or not all(isinstance(k, str) and k for k in keys):
            raise ValueError(f"ImageObsConfig.image_keys must be distinct non-empty names, got {keys}")
        if not keys and self.state_key is None:
            raise ValueError("ImageObsConfig reads nothing: give image_keys or a state_key")
        if self.state_key in keys:
            raise ValueError(f"ImageObsConfig: {self.state_key!r} is both the state and an image field")
        if any(w <= 0 for w in self.state_hidden) or self.state_out <= 0:
            raise ValueError("ImageObsConfig: state_hidden and state_out must be positive")

    @property
    def keys(self) -> tuple[str, ...]:
        return ((self.state_key,) if self.state_key is not None else ()) + self.image_keys


class ImageFieldsMixin:
    """Image-field handling shared by the image policies' configs (``dp``, ``act``).

    The config class declares ``encoder: ImageObsConfig`` and ``image_shapes`` (set by
    :meth:`with_data`: per image field the shape of one frame, ``(H, W, C)`` or
    ``(V, H, W, C)``).
    """

    def _check_image_shapes(self):
        if self.image_shapes is None:
            return
        shapes = tuple(tuple(int(d) for d in s) for s in self.image_shapes)
        object.__setattr__(self, "image_shapes", shapes)
        keys = self.encoder.image_keys
        if len(shapes) != len(keys):
            raise ValueError(f"{type(self).__name__}.image_shapes {shapes} must give one shape "
                             f"per image field {keys}")
        for k, s in zip(keys, shapes):
            if len(s) not in (3, 4) or min(s) < 1:
                raise ValueError(f"image field {k!r} must be [H, W, C] or [V, H, W, C] per "
                                 f"frame, got {s}")

    @property
    def obs_keys(self) -> tuple[str, ...]:
        return self.encoder.keys

    @property
    def state_key(self) -> str | None:
        return self.encoder.state_key

    def unresolved(self) -> list[str]:
        return super().unresolved() + (["image_shapes"] if self.image_shapes is None else [])

    def with_data(self, action_dim, obs_dims, obs_shapes=None):
        cfg = super().with_data(action_dim, obs_dims, obs_shapes)
        if obs_shapes is None:
            raise ValueError(f"the {self.name} policy needs the image shapes: "
                             f"with_data(..., obs_shapes)")
        return dataclasses.replace(cfg, image_shapes=tuple(tuple(obs_shapes[k])
                                                           for k in self.encoder.image_keys))

    def crop_hw(self, key: str) -> tuple[int, int]:
        """The crop size ``(h, w)`` of image field ``key`` (even margins, so that the
        centre crop is its own mirror image)."""
        s = self.image_shapes[self.encoder.image_keys.index(key)]
        r = self.encoder.vision.crop_ratio
        h, w = s[-3], s[-2]
        return h - 2 * ((h - crop_size(h, r)) // 2), w - 2 * ((w - crop_size(w, r)) // 2)

    def example_obs(self, batch: int = 1) -> dict[str, Array]:
        """Zero observations of the shapes the network reads (images cropped)."""
        to = self.obs_horizon
        obs = {}
        if self.state_key is not None:
            obs[self.state_key] = jnp.zeros((batch, to, self.state_dim), jnp.float32)
        for k, s in zip(self.encoder.image_keys, self.image_shapes):
            h, w = self.crop_hw(k)
            obs[k] = jnp.zeros((batch, to) + s[:-3] + (h, w, s[-1]), jnp.float32)
        return obs


@dataclasses.dataclass(frozen=True)
class DPConfig(ImageFieldsMixin, PolicyConfig):
    """The ``dp`` policy (hashable; see :class:`~equibim_jax.policies.base.PolicyConfig`
    for the horizon and dims fields, and ``DP3Config`` for the diffusion fields).

    Attributes:
      encoder: image and state fields and their encoders.
      unet: the conditional 1D U-Net.
      num_train_steps, num_inference_steps, clip_sample, sym_target, prediction: as for
        ``dp3``.
      image_shapes: per image field, the shape of one frame (``(H, W, C)`` or
        ``(V, H, W, C)``); set from the data by :meth:`with_data`.
    """

    name: ClassVar[str] = "dp"
    encoder: ImageObsConfig = ImageObsConfig()
    unet: UNetConfig = UNetConfig()
    num_train_steps: int = 100
    num_inference_steps: int = 10
    clip_sample: bool = True
    sym_target: str = "eps"
    prediction: str = "epsilon"
    image_shapes: Annotated[tuple[tuple[int, ...], ...] | None, tyro.conf.Suppress] = None

    def __post_init__(self):
        super().__post_init__()
        check_diffusion_fields(self)
        if not self.encoder.image_keys:
            raise ValueError("DPConfig.encoder.image_keys is empty; dp is an image policy "
                             "(dp3 reads the state alone)")
        self._check_image_shapes()

    def make_encoder(self) -> "ImageObsEncoder":
        """The observation encoder module, ``obs -> [B, To * F]``."""
        return ImageObsEncoder(self)


class ImageObsEncoder(nn.Module):
    """Encode ``{state: [B, To, D], image field: [B, To, (V,) h, w, C]}`` into
    ``[B, To * (state_out + sum over cameras of vision.out)]``; one encoder per camera
    (named ``<field>`` or ``<field>_<view>``)."""

    config: DPConfig

    @nn.compact
    def __call__(self, obs: Mapping[str, Array]) -> Array:
        cfg = self.config
        enc = cfg.encoder
        missing = [k for k in enc.keys if k not in obs]
        if missing:
            raise KeyError(f"ImageObsEncoder: observation is missing fields {missing}; has {list(obs)}")
        feats = []
        if enc.state_key is not None:
            feats.append(StateEncoder(enc.state_hidden, enc.state_out, name="state")(obs[enc.state_key]))
        for k, s in zip(enc.image_keys, cfg.image_shapes):
            x = obs[k]
            if len(s) == 3:
                feats.append(ImageEncoder(enc.vision, name=k)(x))
            else:
                for v in range(s[0]):
                    feats.append(ImageEncoder(enc.vision, name=f"{k}_{v}")(x[:, :, v]))
        f = jnp.concatenate(feats, axis=-1)  # [B, To, F]
        return f.reshape(f.shape[0], -1)


def augment_images(config: Any, obs: Mapping[str, Array], key: Array) -> tuple[dict, dict]:
    """Random crops of every image field (one offset per sample, frame and view).

    Args:
      config: an image policy's config (``encoder.image_keys``, ``crop_hw``).
      obs: ``{field: [B, To, ...]}``; the image fields are ``[B, To, (V,) H, W, C]``.
      key: PRNG key (split over the image fields in ``image_keys`` order).
    Returns:
      ``(obs with cropped images, {field: int offsets [B, To, (V,) 2]})``.
    """
    out, offsets = dict(obs), {}
    keys = jax.random.split(key, len(config.encoder.image_keys))
    for kk, f in zip(keys, config.encoder.image_keys):
        x = obs[f]
        hw = config.crop_hw(f)
        off = random_crop_offsets(kk, x.shape[:-3], x.shape[-3:-1], hw)
        out[f], offsets[f] = crop_at(x, off, hw), off
    return out, offsets


def eval_images(config: Any, obs: Mapping[str, Array]) -> dict:
    """The centre crop of every image field (inference)."""
    out = dict(obs)
    for f in config.encoder.image_keys:
        out[f] = center_crop(obs[f], config.crop_hw(f))
    return out


def make_dp(config: DPConfig) -> Policy:
    """The ``dp`` :class:`~equibim_jax.policies.base.Policy` of a resolved config.

    Inputs, targets and predictions as for ``dp3``
    (:func:`~equibim_jax.policies.diffusion.make_diffusion_policy`), with the image fields
    of ``inputs["obs"]`` cropped: ``[B, To, (V,) h, w, C]``. ``prepare`` splits its key
    into ``(rest, crop key)`` and crops with :func:`augment_images` on the crop key.
    """
    return make_diffusion_policy(
        config,
        augment=lambda obs, key: augment_images(config, obs, key)[0],
        eval_obs=lambda obs: eval_images(config, obs),
    )
