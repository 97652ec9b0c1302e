"""The image Diffusion Policy (``dp``): crops that commute with ``S``, per-camera encoders,
config errors, and DDIM reproducing a fitted toy distribution."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.policies import DPConfig, ImageObsConfig, VisionConfig, make_policy
from equibim_jax.policies.dp import augment_images, eval_images
from equibim_jax.policies.vision import (
    Conv2d,
    center_crop,
    crop_at,
    mirror_crop_offsets,
    random_crop_offsets,
)
from equibim_jax.training import sym_loss
from test_policies import CONFIGS, fixed_batch, prepared, symmetrised


def flip(x):
    return jnp.flip(x, axis=-2)


@pytest.mark.parametrize("k,stride,hw", [(3, 1, (9, 7)), (3, 2, (9, 8)), (1, 2, (7, 6)), (5, 2, (11, 10))])
def test_im2col_conv_is_lax_conv(k, stride, hw):
    x = jax.random.normal(jax.random.key(1), (2,) + hw + (3,))
    a, b = Conv2d(4, k, stride, "im2col"), Conv2d(4, k, stride, "xla")
    params = a.init(jax.random.key(2), x)
    ya, yb = a.apply(params, x), b.apply(params, x)
    assert ya.shape == (2, -(-hw[0] // stride), -(-hw[1] // stride), 4)
    np.testing.assert_allclose(ya, yb, atol=1e-5)
    ga = jax.grad(lambda p: jnp.sum(jnp.sin(a.apply(p, x))))(params)
    gb = jax.grad(lambda p: jnp.sum(jnp.sin(b.apply(p, x))))(params)
    np.testing.assert_allclose(ga["params"]["kernel"], gb["params"]["kernel"], atol=1e-4)
    with pytest.raises(ValueError, match="odd kernel"):
        Conv2d(4, 2).init(jax.random.key(0), x)


def test_a_mirrored_crop_is_the_crop_at_the_mirrored_offset():
    x = jax.random.uniform(jax.random.key(0), (5, 3, 20, 24, 3))
    off = random_crop_offsets(jax.random.key(1), (5, 3), (20, 24), (16, 18))
    assert off.shape == (5, 3, 2)
    assert int(off[..., 0].max()) <= 4 and int(off[..., 1].max()) <= 6 and int(off.min()) >= 0
    crops = crop_at(x, off, (16, 18))
    assert crops.shape == (5, 3, 16, 18, 3)
    np.testing.assert_array_equal(crops[2, 1], x[2, 1, off[2, 1, 0]:off[2, 1, 0] + 16,
                                                  off[2, 1, 1]:off[2, 1, 1] + 18])
    np.testing.assert_array_equal(flip(crops), crop_at(flip(x), mirror_crop_offsets(off, 24, 18), (16, 18)))
    # The centre crop (even margins) is its own mirror image.
    np.testing.assert_array_equal(flip(center_crop(x, (16, 18))), center_crop(flip(x), (16, 18)))
    with pytest.raises(ValueError, match="does not fit"):
        random_crop_offsets(jax.random.key(1), (2,), (8, 8), (9, 8))


@pytest.mark.parametrize("name", ["dp", "dp_wrist"])
def test_the_mirrored_branch_sees_the_mirror_of_the_same_crop(name):
    policy, sym, dataset, _ = prepared(name)
    cfg = policy.config
    batch, key = fixed_batch(dataset)
    inputs, _ = policy.prepare(batch, key)
    mirrored = policy.mirror_inputs(sym, inputs)
    # prepare splits its key into (rest, crop key) and crops with augment_images.
    obs = {k: batch[k] for k in cfg.obs_keys}
    cropped, offsets = augment_images(cfg, obs, jax.random.split(key)[1])
    for f in cfg.encoder.image_keys:
        np.testing.assert_array_equal(inputs["obs"][f], cropped[f])
        h, w = cfg.crop_hw(f)
        m_off = mirror_crop_offsets(offsets[f], batch[f].shape[-2], w)
        if f == "wrist_image":  # the views swap, and each carries its offset along
            m_off = jnp.flip(m_off, axis=-2)
        expect = crop_at(sym[f](batch[f]), m_off, (h, w))
        np.testing.assert_allclose(mirrored["obs"][f], expect, rtol=0, atol=0)
        assert not np.array_equal(np.asarray(offsets[f][..., 1]), np.asarray(m_off[..., 1]))


def test_fresh_crops_on_the_mirrored_batch_would_penalise_the_crop():
    """The symmetrised policy has L_sym = 0 with the crops mirrored; if the mirrored branch
    drew its own crops of S(batch) instead, L_sym would be far from 0 for the same network."""
    policy, sym, dataset, _ = prepared("dp")
    cfg = policy.config
    params = policy.init(jax.random.key(0))
    equi = symmetrised(policy, sym)
    batch, key = fixed_batch(dataset)

    def fresh_crop_mirror(s, inputs):
        out = policy.mirror_inputs(s, inputs)
        m_obs = {k: s[k](batch[k]) for k in cfg.obs_keys}
        out["obs"] = augment_images(cfg, m_obs, jax.random.key(99))[0]
        return out

    wrong = policy._replace(mirror_inputs=fresh_crop_mirror)
    wrong_equi = symmetrised(policy, sym)._replace(mirror_inputs=fresh_crop_mirror)
    right = float(sym_loss(equi, params, batch, key, sym))
    assert right < 1e-10
    assert float(sym_loss(wrong_equi, params, batch, key, sym)) > 1e-4
    assert float(sym_loss(wrong, params, batch, key, sym)) > 1e-4


def test_one_encoder_per_camera_and_the_eval_crop():
    policy, sym, dataset, _ = prepared("dp_wrist")
    params = policy.init(jax.random.key(0))
    names = set(params["encoder"])
    assert {"state", "image", "wrist_image_0", "wrist_image_1"} <= names
    cfg = policy.config
    assert cfg.crop_hw("image") == (12, 12)  # 16 * 0.75, even margins
    batch, _ = fixed_batch(dataset, n=2)
    ev = eval_images(cfg, {k: batch[k] for k in cfg.obs_keys})
    assert ev["wrist_image"].shape == (2, 1, 2, 12, 12, 3)
    np.testing.assert_array_equal(ev["image"], batch["image"][..., 2:14, 2:14, :])
    # The centre crop commutes with S: the policy at inference sees the mirror image of
    # what it sees on the mirrored scene.
    m_ev = eval_images(cfg, {k: sym[k](batch[k]) for k in cfg.obs_keys})
    for f in cfg.encoder.image_keys:
        np.testing.assert_array_equal(m_ev[f], sym[f](ev[f]))


def test_config_errors():
    with pytest.raises(ValueError, match="conv_impl"):
        VisionConfig(conv_impl="fft")
    with pytest.raises(ValueError, match="image policy"):
        DPConfig(encoder=ImageObsConfig(image_keys=()))
    with pytest.raises(ValueError, match="reads nothing"):
        ImageObsConfig(image_keys=(), state_key=None)
    with pytest.raises(ValueError, match="crop_ratio"):
        VisionConfig(crop_ratio=0.0)
    with pytest.raises(ValueError, match="multiple of groups"):
        VisionConfig(channels=(12, 16), groups=8)
    with pytest.raises(ValueError, match=r"\[H, W, C\] or \[V, H, W, C\]"):
        DPConfig(image_shapes=((16, 16),))
    with pytest.raises(ValueError, match="both the state and an image"):
        ImageObsConfig(image_keys=("qpos",))
    with pytest.raises(ValueError, match="image shapes"):
        DPConfig().with_data(14, {"qpos": 14, "image": 3})


def test_ddim_reproduces_a_fitted_bimodal_distribution():
    """Fit the diffusion policy to actions that are +c or -c (probability 0.7 / 0.3) for
    the same observation; DDIM samples must land on the two modes in those proportions."""
    from equibim_jax.data import make_dataset
    from equibim_jax.training import TrainConfig, base_key, create_train_state, make_train_loop

    cfg = dataclasses.replace(CONFIGS["dp3"], encoder=dataclasses.replace(CONFIGS["dp3"].encoder, pc_key=None))
    cfg = cfg.with_data(2, {"qpos": 2})
    policy = make_policy("dp3", cfg)
    rng = np.random.default_rng(0)
    n_ep, length = 200, 8
    sign = np.where(rng.uniform(size=n_ep) < 0.7, 1.0, -1.0)
    mode = np.array([0.6, -0.3], np.float32)
    act = np.repeat(sign[:, None, None] * mode, length, axis=1).reshape(-1, 2).astype(np.float32)
    data = {"qpos": np.zeros_like(act), "action": act}
    ds = make_dataset(data, np.arange(1, n_ep + 1) * length, cfg)
    tc = TrainConfig(batch_size=64, learning_rate=3e-3, warmup_steps=20, total_steps=1000,
                     sym_weight=0.0, steps_per_dispatch=1000, seed=0)
    state, _ = make_train_loop(tc, ds)(create_train_state(policy, tc), base_key(tc))
    a = policy.sample(state.params, {"qpos": jnp.zeros((400, cfg.obs_horizon, 2))}, jax.random.key(5))
    a = np.asarray(a)  # [400, Tp, 2]
    # Each sampled chunk sits on one mode (its mean within 0.1 of +-mode for 80 % of the
    # chunks: the tiny one-level U-Net leaves a tail), and the modes keep their weights.
    mean = a.mean(axis=1)
    d_pos, d_neg = np.linalg.norm(mean - mode, axis=-1), np.linalg.norm(mean + mode, axis=-1)
    near = np.minimum(d_pos, d_neg)
    assert np.quantile(near, 0.8) < 0.1, np.quantile(near, [0.5, 0.8, 0.9])
    data_frac = float(np.mean(sign > 0))
    assert abs(np.mean(d_pos < d_neg) - data_frac) < 0.08, (np.mean(d_pos < d_neg), data_frac)
