"""``act``: Action Chunking with Transformers (ACT, Zhao et al. 2023).

A conditional VAE over action chunks. The decoder (the policy) is a transformer
encoder-decoder: the encoder reads one token per ResNet feature-map cell of every camera,
one proprioception token and one latent-style token ``z``; the decoder's ``Tp`` learned
queries attend to that memory and a linear head maps each to an action, giving the chunk
``[Tp, A]`` in one pass (no iterative sampling). During training a second transformer
encoder (the CVAE encoder) reads ``[CLS, state of the current frame, the Tp normalised
actions]`` and gives ``q(z | a, o) = N(mu, diag(exp(logvar)))``; ``z = mu + exp(logvar / 2)
* eps`` with ``eps ~ N(0, I)`` drawn in ``prepare``. At inference ``z = 0`` (the prior's
mean), so ``sample`` is deterministic. The loss is ACT's: mean L1 of the chunk plus
``kl_weight`` times the KL to ``N(0, I)`` (summed over latent dims, mean over the batch).

Layout of the encoder's tokens (``d_model`` wide), per sample::

    [z token, frame 0: (state token, camera 0's h*w tokens, camera 1's, ...), frame 1: ...]

* a camera token is the 1x1-conv projection of one cell of the camera's ResNet feature
  map (:class:`~equibim_jax.policies.vision.ResNetTrunk`, one trunk per camera, named
  ``<field>`` or ``<field>_<view>`` as ``ImageObsEncoder`` names them) plus a fixed 2-D
  sinusoidal embedding of the cell (row and column, ``d_model / 2`` each) plus a learned
  embedding of the camera;
* the state token is a Dense of the state plus a learned embedding; the z token a Dense
  of ``z`` plus a learned embedding;
* with ``To > 1`` every frame contributes its tokens and a learned per-frame embedding is
  added to all of them (the z token belongs to no frame).

All transformer layers are **pre-LN** (``x + f(LayerNorm(x))``, with a final LayerNorm on
each stack's output): it trains stably without the long learning-rate warmup post-LN
(ACT's DETR layers) needs. Positions are added to the tokens once, at the input. There is
no dropout: the :class:`~equibim_jax.policies.base.Policy` interface's ``apply`` takes no
RNG, and every random draw of the loss happens in ``prepare``.

Mirroring (``L_sym``): ``mirror_inputs`` mirrors the observations field by field **and the
CVAE encoder's action input** (``S_a`` of the chunk), with the same ``eps``. The paper's
public code leaves the CVAE's action input unmirrored; we mirror it because the mirrored
sample's actions *are* the mirror of the original's: ``(S O, S_a a)`` is the mirrored
training pair, so an equivariant CVAE (encoder and decoder) maps it to ``S_a`` of the
original prediction, and ``L_sym`` then measures exactly the equivariance of the whole
training-time network rather than comparing it against an inconsistent input.

Image fields hold one camera, ``[To, H, W, C]`` per sample, or several,
``[To, V, H, W, C]``; training crops them at random (drawn in ``prepare``, as ``dp`` does)
and inference takes the centre crop. ``ImageObsConfig.vision`` supplies ``channels``,
``groups`` and ``crop_ratio``; its spatial-softmax fields and ``state_hidden`` /
``state_out`` are not used by ACT.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import tyro

from equibim_jax.policies.base import Policy, PolicyConfig
from equibim_jax.policies.dp import ImageFieldsMixin, ImageObsConfig, augment_images, eval_images
from equibim_jax.policies.vision import ResNetTrunk

Array = Any

__all__ = ["ACTConfig", "ACTNet", "make_act", "sinusoid_1d", "sinusoid_2d", "act_kl"]


@dataclasses.dataclass(frozen=True)
class ACTConfig(ImageFieldsMixin, PolicyConfig):
    """The ``act`` policy (frozen, hashable; horizons and dims as in
    :class:`~equibim_jax.policies.base.PolicyConfig`, defaults ``To = 1``, ``Tp = 16``,
    ``Ta = 8``).

    Attributes:
      encoder: image and state fields; ``image_keys`` may be ``()`` for a state-only policy.
        Only ``vision.channels``, ``vision.groups`` and ``vision.crop_ratio`` are used.
      d_model: token width (a multiple of 4, for the 2-D sinusoidal embedding, and of
        ``n_heads``).
      n_heads: attention heads of every layer.
      enc_layers, dec_layers: layers of the policy's transformer encoder and decoder.
      ff_dim: hidden width of every feed-forward block.
      latent_dim: ``L``, width of the CVAE latent ``z``.
      cvae_layers: layers of the CVAE encoder.
      kl_weight: weight of the KL term in the BC loss.
      use_cvae: ``False``: no CVAE encoder, ``z = 0`` always (and no KL).
      image_shapes: per image field, the shape of one frame (``(H, W, C)`` or
        ``(V, H, W, C)``); set from the data by :meth:`with_data`.
    """

    name: ClassVar[str] = "act"
    obs_horizon: int = 1
    pred_horizon: int = 16
    action_horizon: int = 8
    encoder: ImageObsConfig = ImageObsConfig()
    d_model: int = 128
    n_heads: int = 4
    enc_layers: int = 2
    dec_layers: int = 2
    ff_dim: int = 512
    latent_dim: int = 32
    cvae_layers: int = 2
    kl_weight: float = 10.0
    use_cvae: bool = True
    image_shapes: Annotated[tuple[tuple[int, ...], ...] | None, tyro.conf.Suppress] = None

    def __post_init__(self):
        cls = type(self).__name__
        if not isinstance(self.encoder, ImageObsConfig):  # before the base reads obs_keys
            raise ValueError(f"{cls}.encoder must be an ImageObsConfig, got {type(self.encoder).__name__}")
        super().__post_init__()
        for name in ("d_model", "n_heads", "enc_layers", "dec_layers", "ff_dim", "latent_dim",
                     "cvae_layers"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{cls}.{name} must be an int >= 1, got {v!r}")
        if self.d_model % self.n_heads:
            raise ValueError(f"{cls}.d_model={self.d_model} must be a multiple of n_heads={self.n_heads}")
        if self.d_model % 4:
            raise ValueError(f"{cls}.d_model={self.d_model} must be a multiple of 4 (the 2-D "
                             f"sinusoidal embedding uses d_model / 2 per axis, sin and cos)")
        kw = self.kl_weight
        if isinstance(kw, bool) or not isinstance(kw, (int, float, np.floating, np.integer)) \
                or not math.isfinite(kw) or kw < 0:
            raise ValueError(f"{cls}.kl_weight must be a finite number >= 0, got {kw!r}")
        if not isinstance(self.use_cvae, (bool, np.bool_)):
            raise ValueError(f"{cls}.use_cvae must be a bool, got {self.use_cvae!r}")
        self._check_image_shapes()

    def with_data(self, action_dim, obs_dims, obs_shapes=None):
        """As :meth:`ImageFieldsMixin.with_data`; a state-only config (no image fields)
        needs no ``obs_shapes``."""
        if obs_shapes is None and not self.encoder.image_keys:
            obs_shapes = {}
        return super().with_data(action_dim, obs_dims, obs_shapes)

    def make_net(self) -> "ACTNet":
        """The network module (:class:`ACTNet`)."""
        return ACTNet(self)


# ---------------------------------------------------------------- embeddings


def sinusoid_1d(n: int, d: int) -> Array:
    """Fixed sinusoidal position table ``[n, d]`` (``d`` even): column ``2 j`` is
    ``sin(p / 10000^(2 j / d))``, column ``2 j + 1`` the cosine (Vaswani et al.)."""
    pos = np.arange(n, dtype=np.float64)[:, None]
    div = np.power(10000.0, np.arange(0, d, 2, dtype=np.float64) / d)
    table = np.zeros((n, d))
    table[:, 0::2] = np.sin(pos / div)
    table[:, 1::2] = np.cos(pos / div)
    return jnp.asarray(table, jnp.float32)


def sinusoid_2d(h: int, w: int, d: int) -> Array:
    """Fixed 2-D sinusoidal embedding ``[h, w, d]`` (``d`` a multiple of 4): the first
    ``d / 2`` channels embed the row, the others the column (each as :func:`sinusoid_1d`)."""
    rows = sinusoid_1d(h, d // 2)  # [h, d/2]
    cols = sinusoid_1d(w, d // 2)  # [w, d/2]
    return jnp.concatenate([jnp.broadcast_to(rows[:, None], (h, w, d // 2)),
                            jnp.broadcast_to(cols[None, :], (h, w, d // 2))], axis=-1)


# ---------------------------------------------------------------- layers


class _FeedForward(nn.Module):
    ff_dim: int

    @nn.compact
    def __call__(self, x: Array) -> Array:
        d = x.shape[-1]
        return nn.Dense(d, name="out")(jax.nn.relu(nn.Dense(self.ff_dim, name="hidden")(x)))


class EncoderLayer(nn.Module):
    """Pre-LN transformer encoder layer, ``[B, N, d] -> [B, N, d]``: self-attention then
    feed-forward, each as ``x + f(LayerNorm(x))``."""

    n_heads: int
    ff_dim: int

    @nn.compact
    def __call__(self, x: Array) -> Array:
        h = nn.LayerNorm(name="ln_attn")(x)
        x = x + nn.MultiHeadDotProductAttention(self.n_heads, name="attn")(h, h)
        return x + _FeedForward(self.ff_dim, name="ff")(nn.LayerNorm(name="ln_ff")(x))


class DecoderLayer(nn.Module):
    """Pre-LN transformer decoder layer: self-attention over the queries ``[B, Q, d]``,
    cross-attention to ``memory [B, N, d]``, feed-forward; returns ``[B, Q, d]``."""

    n_heads: int
    ff_dim: int

    @nn.compact
    def __call__(self, q: Array, memory: Array) -> Array:
        h = nn.LayerNorm(name="ln_self")(q)
        q = q + nn.MultiHeadDotProductAttention(self.n_heads, name="self_attn")(h, h)
        h = nn.LayerNorm(name="ln_cross")(q)
        q = q + nn.MultiHeadDotProductAttention(self.n_heads, name="cross_attn")(h, memory)
        return q + _FeedForward(self.ff_dim, name="ff")(nn.LayerNorm(name="ln_ff")(q))


class TransformerEncoder(nn.Module):
    """``layers`` pre-LN encoder layers and a final LayerNorm, ``[B, N, d] -> [B, N, d]``."""

    layers: int
    n_heads: int
    ff_dim: int

    @nn.compact
    def __call__(self, x: Array) -> Array:
        for i in range(self.layers):
            x = EncoderLayer(self.n_heads, self.ff_dim, name=f"layer_{i}")(x)
        return nn.LayerNorm(name="ln_out")(x)


class CameraTokens(nn.Module):
    """One camera's tokens: ResNet trunk, 1x1 conv to ``d_model``, 2-D sinusoidal cell
    positions. ``[N, h, w, C] -> [N, h' * w', d_model]`` (``h' = ceil(h / 2**stages)``)."""

    channels: tuple[int, ...]
    groups: int
    d_model: int

    @nn.compact
    def __call__(self, images: Array) -> Array:
        f = ResNetTrunk(self.channels, self.groups, name="trunk")(images)
        f = nn.Dense(self.d_model, name="proj")(f)  # [N, h', w', d]
        n, hh, ww, d = f.shape
        f = f + sinusoid_2d(hh, ww, d)[None]
        return f.reshape(n, hh * ww, d)


class ObsTokens(nn.Module):
    """The policy encoder's observation tokens, ``obs -> [B, To * n_frame, d_model]`` with
    per frame ``n_frame = [state] + sum over cameras of h' * w'`` tokens, frame-major (see
    the module docstring for the layout and embeddings)."""

    config: ACTConfig

    @nn.compact
    def __call__(self, obs: Mapping[str, Array]) -> Array:
        cfg = self.config
        enc, d = cfg.encoder, cfg.d_model
        missing = [k for k in enc.keys if k not in obs]
        if missing:
            raise KeyError(f"ACT: observation is missing fields {missing}; has {list(obs)}")
        per_frame = []  # each [B, To, n, d]
        if enc.state_key is not None:
            s = nn.Dense(d, name="state_proj")(obs[enc.state_key])  # [B, To, d]
            s = s + self.param("state_embed", nn.initializers.normal(0.02), (d,))
            per_frame.append(s[:, :, None])
        cams = []
        for k, shape in zip(enc.image_keys, cfg.image_shapes):
            if len(shape) == 3:
                cams.append((k, obs[k]))
            else:
                cams.extend((f"{k}_{v}", obs[k][:, :, v]) for v in range(shape[0]))
        if cams:
            cam_embed = self.param("camera_embed", nn.initializers.normal(0.02), (len(cams), d))
        for c, (name, x) in enumerate(cams):  # x: [B, To, h, w, C]
            b, to = x.shape[:2]
            t = CameraTokens(enc.vision.channels, enc.vision.groups, d, name=name)(
                x.reshape((b * to,) + x.shape[2:]))
            per_frame.append(t.reshape(b, to, t.shape[1], d) + cam_embed[c])
        tokens = jnp.concatenate(per_frame, axis=2)  # [B, To, n_frame, d]
        if cfg.obs_horizon > 1:
            frame = self.param("frame_embed", nn.initializers.normal(0.02), (cfg.obs_horizon, d))
            tokens = tokens + frame[None, :, None]
        return tokens.reshape(tokens.shape[0], -1, d)


class CVAEEncoder(nn.Module):
    """``q(z | a, o)``: ``(state [B, D] or None, actions [B, Tp, A]) -> (mu, logvar)``,
    each ``[B, L]``. Tokens ``[CLS, state, Tp action tokens]`` plus a 1-D sinusoidal table
    over their positions, a pre-LN encoder, and a Dense of the CLS output."""

    config: ACTConfig

    @nn.compact
    def __call__(self, state: Array | None, actions: Array) -> tuple[Array, Array]:
        cfg = self.config
        d, b = cfg.d_model, actions.shape[0]
        cls = self.param("cls", nn.initializers.normal(0.02), (d,))
        toks = [jnp.broadcast_to(cls, (b, 1, d))]
        if state is not None:
            toks.append(nn.Dense(d, name="state_proj")(state)[:, None])
        toks.append(nn.Dense(d, name="action_proj")(actions))  # [B, Tp, d]
        x = jnp.concatenate(toks, axis=1)
        x = x + sinusoid_1d(x.shape[1], d)[None]
        x = TransformerEncoder(cfg.cvae_layers, cfg.n_heads, cfg.ff_dim, name="encoder")(x)
        # Zero init: q(z | a, o) starts at N(0, I), so the KL term starts at 0.
        stats = nn.Dense(2 * cfg.latent_dim, kernel_init=nn.initializers.zeros,
                         name="latent_proj")(x[:, 0])
        return stats[:, : cfg.latent_dim], stats[:, cfg.latent_dim :]


class ACTNet(nn.Module):
    """The ACT network: CVAE encoder (training) and the transformer policy.

    ``__call__(obs, actions, eps)`` (training): ``obs = {field: [B, To, ...]}`` (images
    cropped), ``actions [B, Tp, A]`` normalised (the CVAE input), ``eps [B, L]`` ->
    ``{"action": [B, Tp, A], "mu": [B, L], "logvar": [B, L]}``. ``infer(obs)``: the chunk
    ``[B, Tp, A]`` at ``z = 0``.
    """

    config: ACTConfig

    def setup(self):
        cfg = self.config
        self.obs_tokens = ObsTokens(cfg)
        if cfg.use_cvae:
            self.cvae = CVAEEncoder(cfg)
        self.latent_proj = nn.Dense(cfg.d_model)
        self.latent_embed = self.param("latent_embed", nn.initializers.normal(0.02), (cfg.d_model,))
        self.encoder = TransformerEncoder(cfg.enc_layers, cfg.n_heads, cfg.ff_dim)
        self.queries = self.param("queries", nn.initializers.normal(0.02),
                                  (cfg.pred_horizon, cfg.d_model))
        self.decoder = [DecoderLayer(cfg.n_heads, cfg.ff_dim) for _ in range(cfg.dec_layers)]
        self.dec_norm = nn.LayerNorm()
        self.head = nn.Dense(cfg.action_dim)

    def decode(self, obs: Mapping[str, Array], z: Array) -> Array:
        """``(obs, z [B, L]) -> [B, Tp, A]``."""
        tokens = self.obs_tokens(obs)  # [B, N, d]
        b = tokens.shape[0]
        zt = (self.latent_proj(z) + self.latent_embed)[:, None]
        memory = self.encoder(jnp.concatenate([zt, tokens], axis=1))
        q = jnp.broadcast_to(self.queries, (b,) + self.queries.shape)
        for layer in self.decoder:
            q = layer(q, memory)
        return self.head(self.dec_norm(q))

    def __call__(self, obs: Mapping[str, Array], actions: Array, eps: Array) -> dict[str, Array]:
        cfg = self.config
        b = actions.shape[0]
        if cfg.use_cvae:
            state = None if cfg.state_key is None else obs[cfg.state_key][:, -1]
            mu, logvar = self.cvae(state, actions)
            z = mu + jnp.exp(0.5 * logvar) * eps
        else:
            mu = logvar = jnp.zeros((b, cfg.latent_dim), actions.dtype)
            z = mu
        return {"action": self.decode(obs, z), "mu": mu, "logvar": logvar}

    def infer(self, obs: Mapping[str, Array]) -> Array:
        """The chunk at the prior mean ``z = 0``: ``obs -> [B, Tp, A]``."""
        b = jax.tree.leaves(obs)[0].shape[0]
        return self.decode(obs, jnp.zeros((b, self.config.latent_dim), jnp.float32))


def act_kl(mu: Array, logvar: Array) -> Array:
    """``KL(N(mu, exp(logvar)) || N(0, I))`` summed over the last axis: ``[B, L] -> [B]``."""
    return -0.5 * jnp.sum(1.0 + logvar - jnp.square(mu) - jnp.exp(logvar), axis=-1)


@functools.partial(jax.jit, static_argnums=0)
def _init(config: ACTConfig, key: Array) -> Any:
    # Jitted: op-by-op initialisation dispatches many small ops.
    obs = config.example_obs()
    a = jnp.zeros((1, config.pred_horizon, config.action_dim), jnp.float32)
    eps = jnp.zeros((1, config.latent_dim), jnp.float32)
    return ACTNet(config).init(key, obs, a, eps)["params"]


def make_act(config: ACTConfig) -> Policy:
    """The ``act`` :class:`~equibim_jax.policies.base.Policy` of a resolved config.

    * ``prepare(batch, key)``: ``key -> (eps key, crop key)``; ``inputs = {"obs": {field:
      [B, To, ...]} (images randomly cropped), "action": [B, Tp, A] (the CVAE encoder's
      input), "eps": [B, L]}``, ``targets = {"action": [B, Tp, A]}``.
    * ``apply(params, inputs) -> {"action": [B, Tp, A], "mu": [B, L], "logvar": [B, L]}``.
    * ``bc_loss``: mean L1 of the chunk ``+ kl_weight * mean_B sum_L KL``.
    * ``mirror_inputs``: observations mirrored field by field, the CVAE's action input by
      ``S_a``, ``eps`` unchanged (same latent noise); ``sym_view`` is ``pred["action"]``.
    * ``sample(params, obs, key, noise_op=None)``: centre crops, ``z = 0``, one pass:
      deterministic, ``key`` and ``noise_op`` unused (nothing is drawn).
    """
    net = ACTNet(config)
    akey = config.action_key
    has_images = bool(config.encoder.image_keys)

    def init(key):
        return _init(config, key)

    def prepare(batch, key):
        k_eps, k_crop = jax.random.split(key)
        obs = {f: batch[f] for f in config.obs_keys}
        if has_images:
            obs = augment_images(config, obs, k_crop)[0]
        a = batch[akey]
        eps = jax.random.normal(k_eps, (a.shape[0], config.latent_dim), jnp.float32)
        return {"obs": obs, "action": a, "eps": eps}, {"action": a}

    def apply(params, inputs):
        return net.apply({"params": params}, inputs["obs"], inputs["action"], inputs["eps"])

    def bc_loss(pred, targets):
        l1 = jnp.mean(jnp.abs(pred["action"] - targets["action"]))
        return l1 + config.kl_weight * jnp.mean(act_kl(pred["mu"], pred["logvar"]))

    def mirror_inputs(sym, inputs):
        return {"obs": {f: sym[f](v) for f, v in inputs["obs"].items()},
                "action": sym[akey](inputs["action"]), "eps": inputs["eps"]}

    def mirror_targets(sym, targets):
        return {"action": sym[akey](targets["action"])}

    def sym_view(inputs, pred):
        return pred["action"]

    def mirror_view(sym, view):
        return sym[akey](view)

    def sample(params, obs, key=None, noise_op=None):
        del key, noise_op  # z = 0: nothing is drawn
        obs = {f: obs[f] for f in config.obs_keys}
        if has_images:
            obs = eval_images(config, obs)
        return net.apply({"params": params}, obs, method=ACTNet.infer)

    return Policy(config=config, init=init, prepare=prepare, apply=apply, bc_loss=bc_loss,
                  mirror_inputs=mirror_inputs, mirror_targets=mirror_targets, sym_view=sym_view,
                  mirror_view=mirror_view, sample=sample)
