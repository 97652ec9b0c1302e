"""PyTorch twins of the three policies' train steps, for ``benchmarks/train.py --vs-torch``.

Not part of the package (``pip install -e .[torch]`` brings torch 2.13.0). Each twin has
the architecture of its JAX policy at the default config, layer for layer, so the
parameter counts are equal (``benchmarks/train.py`` asserts it):

* ``dp3``: DP3 observation encoder (state MLP, per-point MLP with LayerNorm, max-pool,
  projection) and the conditional 1D U-Net (``equibim_jax/policies/unet1d.py``);
* ``dp``: one small GroupNorm ResNet per camera, spatial softmax, projection, a state MLP,
  and the same U-Net;
* ``act``: ResNet trunk tokens, pre-LN transformer encoder-decoder and the CVAE encoder.

The step does what ``equibim_jax.training.train_step`` does: draw ``B`` windows from the
frames in memory, ``prepare`` (noise and diffusion steps, random crops, CVAE ``eps``), one
forward pass over ``[B]`` (behaviour cloning) or over the concatenated ``[B + B]`` with the
mirrored batch (``L_sym`` in the same norm and with the same stop-gradient as the JAX
step), backward, ``torch.optim.AdamW`` with the same hyper-parameters and learning-rate
schedule, and an EMA update of a parameter copy. Eager mode; the caller sets the threads.

The mirror ops are written by hand: the action and ``qpos`` swap their halves with
per-joint signs, an image flips along its width, a point cloud negates ``y``.
"""

from __future__ import annotations

import math
import statistics
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

# --------------------------------------------------------------------- mirror ops


class Mirror:
    """``S`` in torch: signed permutation of the joint vectors, image W flip, pc y flip."""

    def __init__(self, perm: np.ndarray, signs: np.ndarray):
        self.perm = torch.as_tensor(np.asarray(perm), dtype=torch.long)
        self.signs = torch.as_tensor(np.asarray(signs), dtype=torch.float32)
        self.pc = torch.tensor([1.0, -1.0, 1.0])

    def joint(self, x):
        return self.signs * x[..., self.perm]

    def field(self, name: str, x):
        if name in ("qpos", "action"):
            return self.joint(x)
        if name == "image":  # [..., H, W, C]: flip W
            return torch.flip(x, dims=(-2,))
        if name == "point_cloud":
            return x * self.pc
        raise KeyError(name)


def sym_norm(e, norm: str):
    if norm == "mse":
        return torch.mean(e * e)
    e = e.reshape(e.shape[0], -1)
    sq = torch.sum(e * e, dim=-1)
    if norm == "rms":
        sq = sq / e.shape[1]
    return torch.mean(torch.sqrt(sq + 1e-12))


# --------------------------------------------------------------------- encoders


class StateEncoder(nn.Module):
    def __init__(self, d_in, hidden, out):
        super().__init__()
        layers, w0 = [], d_in
        for w in hidden:
            layers.append(nn.Linear(w0, w))
            w0 = w
        self.hidden = nn.ModuleList(layers)
        self.out = nn.Linear(w0, out)

    def forward(self, x):
        for lin in self.hidden:
            x = F.mish(lin(x))
        return self.out(x)


class PointCloudEncoder(nn.Module):
    def __init__(self, hidden, out):
        super().__init__()
        self.lins, self.lns, w0 = nn.ModuleList(), nn.ModuleList(), 3
        for w in hidden:
            self.lins.append(nn.Linear(w0, w))
            self.lns.append(nn.LayerNorm(w, eps=1e-6))
            w0 = w
        self.proj = nn.Linear(w0, out)
        self.ln = nn.LayerNorm(out, eps=1e-6)

    def forward(self, pts):  # [..., N, 3]
        lead, n = pts.shape[:-2], pts.shape[-2]
        h = pts.reshape(-1, 3)
        for lin, ln in zip(self.lins, self.lns):
            h = F.relu(ln(lin(h)))
        h = h.reshape(-1, n, h.shape[-1]).amax(dim=1)
        h = self.ln(self.proj(h))
        return h.reshape(*lead, -1)


class BasicBlock(nn.Module):
    def __init__(self, c_in, c, stride, groups):
        super().__init__()
        self.c1 = nn.Conv2d(c_in, c, 3, stride, padding=1, bias=False)
        self.g1 = nn.GroupNorm(groups, c, eps=1e-6)
        self.c2 = nn.Conv2d(c, c, 3, 1, padding=1, bias=False)
        self.g2 = nn.GroupNorm(groups, c, eps=1e-6)
        self.short = None
        if stride != 1 or c_in != c:
            self.short = nn.Sequential(nn.Conv2d(c_in, c, 1, stride, bias=False), nn.GroupNorm(groups, c, eps=1e-6))

    def forward(self, x):
        h = F.relu(self.g1(self.c1(x)))
        h = self.g2(self.c2(h))
        if self.short is not None:
            x = self.short(x)
        return F.relu(h + x)


class ResNetTrunk(nn.Module):
    """NCHW in, NCHW out."""

    def __init__(self, channels, groups, c_in=3):
        super().__init__()
        self.stem = nn.Conv2d(c_in, channels[0], 3, 2, padding=1, bias=False)
        self.gn = nn.GroupNorm(groups, channels[0], eps=1e-6)
        blocks, c0 = [], channels[0]
        for i, c in enumerate(channels):
            blocks.append(BasicBlock(c0, c, 1 if i == 0 else 2, groups))
            c0 = c
        self.blocks = nn.Sequential(*blocks)

    def forward(self, x):
        return self.blocks(F.relu(self.gn(self.stem(x))))


class ImageEncoder(nn.Module):
    """Trunk, spatial softmax (K keypoints), Dense: ``[N, H, W, C] -> [N, out]``."""

    def __init__(self, vision):
        super().__init__()
        self.trunk = ResNetTrunk(vision.channels, vision.groups)
        self.kp = nn.Conv2d(vision.channels[-1], vision.keypoints, 1)
        self.proj = nn.Linear(2 * vision.keypoints, vision.out)
        self.k = vision.keypoints

    def forward(self, x):
        f = self.trunk(x.permute(0, 3, 1, 2))
        logits = self.kp(f)  # [N, K, h, w]
        n, k, h, w = logits.shape
        attn = torch.softmax(logits.reshape(n, k, h * w), dim=-1)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
        grid = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # [hw, 2]
        kp = attn @ grid  # [N, K, 2]
        return self.proj(kp.reshape(n, 2 * k))


# --------------------------------------------------------------------- U-Net


def sinusoidal_embedding(k, dim):
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / max(half - 1, 1))
    ang = k.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(ang), torch.cos(ang)], dim=-1)


class Conv1dBlock(nn.Module):
    def __init__(self, c_in, c_out, k, groups):
        super().__init__()
        self.conv = nn.Conv1d(c_in, c_out, k, padding=k // 2)
        self.gn = nn.GroupNorm(groups, c_out, eps=1e-5)

    def forward(self, x):
        return F.mish(self.gn(self.conv(x)))


class CondResBlock1d(nn.Module):
    def __init__(self, c_in, c_out, cond_dim, k, groups):
        super().__init__()
        self.b1 = Conv1dBlock(c_in, c_out, k, groups)
        self.film = nn.Linear(cond_dim, 2 * c_out)
        self.b2 = Conv1dBlock(c_out, c_out, k, groups)
        self.res = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else None

    def forward(self, x, cond):  # x [B, C, T]
        out = self.b1(x)
        scale, bias = self.film(F.mish(cond))[:, :, None].chunk(2, dim=1)
        out = self.b2(scale * out + bias)
        return out + (self.res(x) if self.res is not None else x)


class ConditionalUnet1D(nn.Module):
    """Same blocks and wiring as ``equibim_jax.policies.unet1d.ConditionalUnet1D`` (the
    unused deepest-but-one skip included), channels-first as torch convolves."""

    def __init__(self, cfg, action_dim, global_dim):
        super().__init__()
        d, k, g, dims = cfg.step_embed_dim, cfg.kernel_size, cfg.n_groups, cfg.down_dims
        self.d = d
        self.emb1 = nn.Linear(d, 4 * d)
        self.emb2 = nn.Linear(4 * d, d)
        cd = d + global_dim
        self.down, self.downs = nn.ModuleList(), nn.ModuleList()
        c0 = action_dim
        for i, dim in enumerate(dims):
            self.down.append(nn.ModuleList([CondResBlock1d(c0, dim, cd, k, g), CondResBlock1d(dim, dim, cd, k, g)]))
            if i < len(dims) - 1:
                self.downs.append(nn.Conv1d(dim, dim, 3, stride=2, padding=1))
            c0 = dim
        self.mid = nn.ModuleList([CondResBlock1d(dims[-1], dims[-1], cd, k, g) for _ in range(2)])
        self.up, self.upconv = nn.ModuleList(), nn.ModuleList()
        c0 = dims[-1]
        for i in reversed(range(len(dims) - 1)):
            self.up.append(nn.ModuleList([CondResBlock1d(c0 + dims[i + 1], dims[i], cd, k, g),
                                          CondResBlock1d(dims[i], dims[i], cd, k, g)]))
            self.upconv.append(nn.Conv1d(dims[i], dims[i], 3, padding=1))
            c0 = dims[i]
        self.final = Conv1dBlock(dims[0], dims[0], k, g)
        self.out = nn.Conv1d(dims[0], action_dim, 1)
        self.n_levels = len(dims)

    def forward(self, x, k, global_cond):  # x [B, T, A]
        emb = self.emb2(F.mish(self.emb1(sinusoidal_embedding(k, self.d))))
        cond = torch.cat([emb, global_cond], dim=-1)
        h = x.transpose(1, 2)
        skips = []
        for i, (r1, r2) in enumerate(self.down):
            h = r2(r1(h, cond), cond)
            skips.append(h)
            if i < self.n_levels - 1:
                h = self.downs[i](h)
        for r in self.mid:
            h = r(h, cond)
        for j, i in enumerate(reversed(range(self.n_levels - 1))):
            h = torch.cat([h, skips[i + 1]], dim=1)
            r1, r2 = self.up[j]
            h = r2(r1(h, cond), cond)
            h = torch.repeat_interleave(h, 2, dim=2)
            h = self.upconv[j](h)
        return self.out(self.final(h)).transpose(1, 2)


class DiffusionNet(nn.Module):
    """Observation encoder + U-Net of ``dp`` (images + state) or ``dp3`` (state + point cloud)."""

    def __init__(self, name, cfg):
        super().__init__()
        self.name, self.cfg = name, cfg
        if name == "dp3":
            enc = cfg.encoder
            self.state = StateEncoder(cfg.state_dim, enc.state_hidden, enc.state_out)
            self.pc = PointCloudEncoder(enc.pc_hidden, enc.pc_out) if enc.pc_key else None
            per_frame = enc.state_out + (enc.pc_out if enc.pc_key else 0)
        else:
            enc = cfg.encoder
            self.state = StateEncoder(cfg.state_dim, enc.state_hidden, enc.state_out)
            self.image = ImageEncoder(enc.vision)
            per_frame = enc.state_out + enc.vision.out
        self.unet = ConditionalUnet1D(cfg.unet, cfg.action_dim, cfg.obs_horizon * per_frame)

    def encode(self, obs):
        feats = [self.state(obs["qpos"])]
        if self.name == "dp3":
            if self.pc is not None:
                feats.append(self.pc(obs["point_cloud"]))
        else:
            x = obs["image"]
            b, to = x.shape[:2]
            feats.append(self.image(x.reshape((b * to,) + x.shape[2:])).reshape(b, to, -1))
        f = torch.cat(feats, dim=-1)
        return f.reshape(f.shape[0], -1)

    def forward(self, inputs):
        return self.unet(inputs["noisy_action"], inputs["k"], self.encode(inputs["obs"]))


# --------------------------------------------------------------------- ACT


def sinusoid_1d(n, d):
    pos = np.arange(n, dtype=np.float64)[:, None]
    div = np.power(10000.0, np.arange(0, d, 2, dtype=np.float64) / d)
    t = np.zeros((n, d))
    t[:, 0::2] = np.sin(pos / div)
    t[:, 1::2] = np.cos(pos / div)
    return torch.as_tensor(t, dtype=torch.float32)


def sinusoid_2d(h, w, d):
    rows, cols = sinusoid_1d(h, d // 2), sinusoid_1d(w, d // 2)
    return torch.cat([rows[:, None].expand(h, w, d // 2), cols[None].expand(h, w, d // 2)], dim=-1)


class FeedForward(nn.Module):
    def __init__(self, d, ff):
        super().__init__()
        self.hidden, self.out = nn.Linear(d, ff), nn.Linear(ff, d)

    def forward(self, x):
        return self.out(F.relu(self.hidden(x)))


class EncoderLayer(nn.Module):
    def __init__(self, d, heads, ff):
        super().__init__()
        self.ln_attn, self.ln_ff = nn.LayerNorm(d, eps=1e-6), nn.LayerNorm(d, eps=1e-6)
        self.attn = nn.MultiheadAttention(d, heads, batch_first=True)
        self.ff = FeedForward(d, ff)

    def forward(self, x):
        h = self.ln_attn(x)
        x = x + self.attn(h, h, h, need_weights=False)[0]
        return x + self.ff(self.ln_ff(x))


class DecoderLayer(nn.Module):
    def __init__(self, d, heads, ff):
        super().__init__()
        self.ln_self, self.ln_cross, self.ln_ff = (nn.LayerNorm(d, eps=1e-6) for _ in range(3))
        self.self_attn = nn.MultiheadAttention(d, heads, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(d, heads, batch_first=True)
        self.ff = FeedForward(d, ff)

    def forward(self, q, memory):
        h = self.ln_self(q)
        q = q + self.self_attn(h, h, h, need_weights=False)[0]
        h = self.ln_cross(q)
        q = q + self.cross_attn(h, memory, memory, need_weights=False)[0]
        return q + self.ff(self.ln_ff(q))


class TransformerEncoder(nn.Module):
    def __init__(self, layers, d, heads, ff):
        super().__init__()
        self.layers = nn.ModuleList([EncoderLayer(d, heads, ff) for _ in range(layers)])
        self.ln_out = nn.LayerNorm(d, eps=1e-6)

    def forward(self, x):
        for layer in self.layers:
            x = layer(x)
        return self.ln_out(x)


class ACTNet(nn.Module):
    """``equibim_jax.policies.act.ACTNet`` at one camera (``image``) + ``qpos``, ``To = 1``
    (no frame embedding, as the JAX net has none for ``To = 1``)."""

    def __init__(self, cfg):
        super().__init__()
        assert cfg.obs_horizon == 1 and cfg.encoder.image_keys == ("image",) and cfg.use_cvae
        d, v = cfg.d_model, cfg.encoder.vision
        self.cfg = cfg
        # observation tokens
        self.state_proj = nn.Linear(cfg.state_dim, d)
        self.state_embed = nn.Parameter(0.02 * torch.randn(d))
        self.camera_embed = nn.Parameter(0.02 * torch.randn(1, d))
        self.trunk = ResNetTrunk(v.channels, v.groups)
        self.cam_proj = nn.Conv2d(v.channels[-1], d, 1)
        # CVAE encoder
        self.cls = nn.Parameter(0.02 * torch.randn(d))
        self.cvae_state_proj = nn.Linear(cfg.state_dim, d)
        self.cvae_action_proj = nn.Linear(cfg.action_dim, d)
        self.cvae_encoder = TransformerEncoder(cfg.cvae_layers, d, cfg.n_heads, cfg.ff_dim)
        self.cvae_latent = nn.Linear(d, 2 * cfg.latent_dim)
        nn.init.zeros_(self.cvae_latent.weight)
        nn.init.zeros_(self.cvae_latent.bias)
        # policy
        self.latent_proj = nn.Linear(cfg.latent_dim, d)
        self.latent_embed = nn.Parameter(0.02 * torch.randn(d))
        self.encoder = TransformerEncoder(cfg.enc_layers, d, cfg.n_heads, cfg.ff_dim)
        self.queries = nn.Parameter(0.02 * torch.randn(cfg.pred_horizon, d))
        self.decoder = nn.ModuleList([DecoderLayer(d, cfg.n_heads, cfg.ff_dim) for _ in range(cfg.dec_layers)])
        self.dec_norm = nn.LayerNorm(d, eps=1e-6)
        self.head = nn.Linear(d, cfg.action_dim)

    def obs_tokens(self, obs):
        d = self.cfg.d_model
        s = self.state_proj(obs["qpos"]) + self.state_embed  # [B, To, d]
        x = obs["image"]  # [B, To, h, w, C]
        b, to = x.shape[:2]
        f = self.cam_proj(self.trunk(x.reshape((b * to,) + x.shape[2:]).permute(0, 3, 1, 2)))
        n, _, hh, ww = f.shape
        f = f.permute(0, 2, 3, 1) + sinusoid_2d(hh, ww, d)
        t = f.reshape(b, to, hh * ww, d) + self.camera_embed[0]
        return torch.cat([s[:, :, None], t], dim=2).reshape(b, -1, d)

    def forward(self, obs, actions, eps):
        cfg, d = self.cfg, self.cfg.d_model
        b = actions.shape[0]
        toks = torch.cat([self.cls.expand(b, 1, d), self.cvae_state_proj(obs["qpos"][:, -1])[:, None],
                          self.cvae_action_proj(actions)], dim=1)
        toks = toks + sinusoid_1d(toks.shape[1], d)
        stats = self.cvae_latent(self.cvae_encoder(toks)[:, 0])
        mu, logvar = stats[:, : cfg.latent_dim], stats[:, cfg.latent_dim:]
        z = mu + torch.exp(0.5 * logvar) * eps
        tokens = self.obs_tokens(obs)
        zt = (self.latent_proj(z) + self.latent_embed)[:, None]
        memory = self.encoder(torch.cat([zt, tokens], dim=1))
        q = self.queries.expand(b, -1, -1)
        for layer in self.decoder:
            q = layer(q, memory)
        return {"action": self.head(self.dec_norm(q)), "mu": mu, "logvar": logvar}


# --------------------------------------------------------------------- training


def squared_cosine_alphas_cumprod(num_steps, max_beta=0.999):
    def abar(t):
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = np.array([min(1 - abar((i + 1) / num_steps) / abar(i / num_steps), max_beta) for i in range(num_steps)])
    return torch.as_tensor(np.cumprod(1.0 - betas), dtype=torch.float32)


def random_crop(x, hw, gen):
    """Random crop of every image ``[B, To, H, W, C] -> [B, To, h, w, C]`` (own offset each)."""
    b, to, hh, ww, c = x.shape
    h, w = hw
    flat = x.reshape(b * to, hh, ww, c)
    n = flat.shape[0]
    r = torch.randint(0, hh - h + 1, (n,), generator=gen)
    cc = torch.randint(0, ww - w + 1, (n,), generator=gen)
    rows = (r[:, None] + torch.arange(h))[:, :, None]
    cols = (cc[:, None] + torch.arange(w))[:, None, :]
    out = flat[torch.arange(n)[:, None, None], rows, cols]
    return out.reshape(b, to, h, w, c)


def n_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


class TorchTwin:
    """One twin's model, optimiser, EMA copy, data and step.

    Args:
      name: ``"dp"``, ``"dp3"`` or ``"act"``.
      cfg: the resolved JAX policy config (dims, horizons, widths are read from it).
      train: the JAX ``TrainConfig`` (batch, AdamW, schedule, EMA, ``L_sym`` settings).
      frames: ``{field: np.ndarray [F, ...]}`` normalised frames (same as the JAX dataset).
      obs_index, action_index: the JAX dataset's window tables (numpy).
      mirror: :class:`Mirror`.
    """

    def __init__(self, name, cfg, train, frames, obs_index, action_index, mirror, seed=0):
        torch.manual_seed(seed)
        self.name, self.cfg, self.tc, self.mirror = name, cfg, train, mirror
        self.model = ACTNet(cfg) if name == "act" else DiffusionNet(name, cfg)
        self.params = [p for p in self.model.parameters()]
        self.ema = [p.detach().clone() for p in self.params]
        self.opt = torch.optim.AdamW(self.params, lr=train.learning_rate, betas=(train.b1, train.b2),
                                     eps=train.adam_eps, weight_decay=train.weight_decay, foreach=True)
        warm, total = min(train.warmup_steps, train.total_steps - 1), train.total_steps

        def lr_lambda(step):
            if step < warm:
                return step / max(warm, 1)
            return 0.5 * (1 + math.cos(math.pi * min(step - warm, total - warm) / (total - warm)))

        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, lr_lambda)
        self.frames = {k: torch.as_tensor(v) for k, v in frames.items()}
        self.obs_index = torch.as_tensor(np.asarray(obs_index), dtype=torch.long)
        self.action_index = torch.as_tensor(np.asarray(action_index), dtype=torch.long)
        self.obs_keys = tuple(cfg.obs_keys)
        self.gen = torch.Generator().manual_seed(seed + 1)
        self.step_count = 0
        if name != "act":
            self.acp = squared_cosine_alphas_cumprod(cfg.num_train_steps)
        self.crop = cfg.crop_hw("image") if "image" in self.obs_keys else None

    @property
    def num_params(self) -> int:
        return n_params(self.model)

    def sample_batch(self):
        idx = torch.randint(0, self.obs_index.shape[0], (self.tc.batch_size,), generator=self.gen)
        batch = {k: self.frames[k][self.obs_index[idx]] for k in self.obs_keys}
        batch["action"] = self.frames["action"][self.action_index[idx]]
        return batch

    def prepare(self, batch):
        obs = {k: batch[k] for k in self.obs_keys}
        if self.crop is not None:
            obs["image"] = random_crop(obs["image"], self.crop, self.gen)
        a0 = batch["action"]
        if self.name == "act":
            eps = torch.randn((a0.shape[0], self.cfg.latent_dim), generator=self.gen)
            return {"obs": obs, "action": a0, "eps": eps}, {"action": a0}
        noise = torch.randn(a0.shape, generator=self.gen)
        k = torch.randint(0, self.cfg.num_train_steps, (a0.shape[0],), generator=self.gen)
        acp = self.acp[k][:, None, None]
        return {"obs": obs, "noisy_action": acp.sqrt() * a0 + (1 - acp).sqrt() * noise, "k": k}, {"noise": noise}

    def mirror_inputs(self, inputs):
        m = self.mirror
        out = {"obs": {f: m.field(f, v) for f, v in inputs["obs"].items()}}
        if self.name == "act":
            out.update(action=m.joint(inputs["action"]), eps=inputs["eps"])
        else:
            out.update(noisy_action=m.joint(inputs["noisy_action"]), k=inputs["k"])
        return out

    def apply(self, inputs):
        if self.name == "act":
            return self.model(inputs["obs"], inputs["action"], inputs["eps"])
        return self.model(inputs)

    def bc_loss(self, pred, targets, n=None):
        if self.name == "act":
            act, mu, logvar = pred["action"], pred["mu"], pred["logvar"]
            if n is not None:
                act, mu, logvar = act[:n], mu[:n], logvar[:n]
            kl = -0.5 * torch.sum(1 + logvar - mu * mu - torch.exp(logvar), dim=-1)
            return torch.mean(torch.abs(act - targets["action"])) + self.cfg.kl_weight * torch.mean(kl)
        p = pred if n is None else pred[:n]
        return torch.mean((p - targets["noise"]) ** 2)

    def view(self, pred):
        return pred["action"] if self.name == "act" else pred

    def loss(self, sym: bool):
        tc = self.tc
        inputs, targets = self.prepare(self.sample_batch())
        if not sym:
            return self.bc_loss(self.apply(inputs), targets)
        b = tc.batch_size
        n = b if tc.sym_batch_size is None else tc.sym_batch_size
        sub = {"obs": {f: v[:n] for f, v in inputs["obs"].items()},
               **{k: v[:n] for k, v in inputs.items() if k != "obs"}}
        m_inputs = self.mirror_inputs(sub)
        both = {"obs": {f: torch.cat([inputs["obs"][f], m_inputs["obs"][f]]) for f in inputs["obs"]},
                **{k: torch.cat([inputs[k], m_inputs[k]]) for k in inputs if k != "obs"}}
        pred = self.apply(both)
        bc = self.bc_loss(pred, targets, n=b)
        v = self.view(pred)
        target = self.mirror.joint(v[:n])
        if tc.sym_stop_gradient:
            target = target.detach()
        return bc + tc.sym_weight * sym_norm(v[b:] - target, tc.sym_norm)

    def ema_decay(self) -> float:
        e = self.tc.ema
        if e.fixed_decay is not None:
            return e.fixed_decay
        s = max(0, self.step_count - e.update_after_step - 1)
        if s <= 0:
            return 0.0
        return min(max(1.0 - (1.0 + s / e.inv_gamma) ** (-e.power), e.min_decay), e.max_decay)

    def step(self, sym: bool) -> float:
        loss = self.loss(sym)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.sched.step()
        with torch.no_grad():
            torch._foreach_lerp_(self.ema, self.params, 1.0 - self.ema_decay())
        self.step_count += 1
        return loss

    def time_steps(self, sym: bool, k: int, repeats: int) -> dict:
        """Median ms per step over ``repeats`` blocks of ``k`` steps (one warm-up block)."""
        for _ in range(max(2, k // 2)):
            self.step(sym)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            for _ in range(k):
                loss = self.step(sym)
            loss = loss.item()
            times.append((time.perf_counter() - t) / k)
        return {"ms": 1e3 * statistics.median(times), "all_ms": [1e3 * x for x in times],
                "final_loss": loss}
