"""Every registered policy behind the one interface: shapes in both action widths, ``L_sym``
(zero for a policy symmetrised by construction, positive for a generic one, finite
gradients), a short training run lowering the equivariance error, exact checkpoint resume
and the config's JSON round trip.

Tiny sizes; the data are synthetic and carry every observation field a policy may read.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.config import config_from_dict, config_to_dict
from equibim_jax.data import fit_normalizer, make_dataset, normalized_symmetry
from equibim_jax.policies import (
    DP3Config,
    DPConfig,
    EncoderConfig,
    ImageObsConfig,
    PolicyConfig,
    UNetConfig,
    VisionConfig,
    make_policy,
    policy_names,
)
from equibim_jax.symmetry import JointMap, Mirror, Symmetry, image_op, point_cloud_op
from equibim_jax.training import (
    TrainConfig,
    base_key,
    create_train_state,
    equivariance_error,
    make_train_loop,
    restore_checkpoint,
    save_checkpoint,
    sym_loss,
)

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)

N_ARM = 6
IMG = 16
# Per arm: waist (yaw, flips), shoulder, elbow (pitch, keep), forearm roll (flips), wrist
# angle (keeps), wrist rotate (flips), gripper opening (keeps); the arms swap.
_SIGNS = [-1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0]
JOINT = JointMap(list(range(7, 14)) + list(range(7)), _SIGNS * 2, [0.0] * 14)
# A 20-wide "ee" action: per arm 3 + 6 + 1, reflected in y (signs on y and on the 6-D
# rotation's y components are a stand-in with the right structure: a signed permutation).
_EE_SIGNS = [1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, 1.0]
EE = JointMap(list(range(10, 20)) + list(range(10)), _EE_SIGNS * 2, [0.0] * 20)


def _pair_op(x):
    """Two cameras mirrored into each other: swap the views, flip each image."""
    return jnp.flip(jnp.flip(x, axis=-4), axis=-2)


def raw_symmetry(action_dim):
    return Symmetry({
        "qpos": JOINT,
        "action": JOINT if action_dim == 14 else EE,
        "point_cloud": point_cloud_op(Mirror.from_axis("y")),
        "image": image_op("HWC"),
        "wrist_image": _pair_op,
    })


def _tiny_unet():
    return UNetConfig(down_dims=(16,), kernel_size=3, n_groups=4, step_embed_dim=16)


_VISION = VisionConfig(channels=(8,), groups=4, keypoints=4, out=8, crop_ratio=0.75)
CONFIGS = {
    "dp3": DP3Config(obs_horizon=2, pred_horizon=8, action_horizon=4, unet=_tiny_unet(),
                     encoder=EncoderConfig(state_hidden=(16,), state_out=8, pc_hidden=(8, 16), pc_out=8)),
    "dp": DPConfig(obs_horizon=2, pred_horizon=8, action_horizon=4, unet=_tiny_unet(),
                   encoder=ImageObsConfig(image_keys=("image",), vision=_VISION, state_hidden=(16,),
                                          state_out=8)),
    "dp_wrist": DPConfig(obs_horizon=1, pred_horizon=8, action_horizon=4, unet=_tiny_unet(),
                         encoder=ImageObsConfig(image_keys=("image", "wrist_image"), vision=_VISION,
                                                state_hidden=(16,), state_out=8)),
}
if "act" in policy_names():
    from equibim_jax.policies import ACTConfig

    CONFIGS["act"] = ACTConfig(
        obs_horizon=1, pred_horizon=8, action_horizon=4, d_model=32, n_heads=2, enc_layers=1,
        dec_layers=1, ff_dim=64, latent_dim=8, cvae_layers=1,
        encoder=ImageObsConfig(image_keys=("image",), vision=_VISION, state_hidden=(16,), state_out=8))


def frames(action_dim=14, episodes=6, length=24, seed=0):
    """Synthetic demos: smooth joint trajectories (the action is the next state, or a fixed
    linear read-out of it for 20-wide actions), and images and clouds that depend on the
    state, so the observations carry the information the action needs."""
    rng = np.random.default_rng(seed)
    t = np.arange(length) / length
    qs = [np.sin(2 * np.pi * t[:, None] * rng.uniform(0.5, 1.5, 14) + rng.uniform(0, 6.3, 14))
          for _ in range(episodes)]
    q = np.concatenate(qs).astype(np.float32)
    act = np.roll(q, -1, axis=0)
    if action_dim == 20:
        act = (act @ rng.normal(size=(14, 20)) / 4).astype(np.float32)
    f = len(q)
    base = rng.uniform(0, 255, (IMG, IMG, 3))
    shift = (np.abs(q[:, :1]) * 40).astype(np.float32)[:, :, None, None]
    img = np.clip(base[None] * 0.5 + shift, 0, 255).astype(np.uint8)
    wrist = np.stack([img, np.clip(img.astype(np.int32) + (q[:, 7:8, None, None] * 60).astype(np.int32),
                                   0, 255).astype(np.uint8)], axis=1)
    pc = (rng.normal(size=(f, 16, 3)) * 0.2 + q[:, None, :3]).astype(np.float32)
    data = {"qpos": q, "action": act, "image": img, "wrist_image": wrist, "point_cloud": pc}
    return data, np.arange(1, episodes + 1) * length


def prepared(name, action_dim=14):
    """``(policy, normalised-space S, on-device dataset)`` of a tiny config."""
    base = CONFIGS[name]
    data, ends = frames(action_dim)
    fields = tuple(base.obs_keys)
    raw = {k: v for k, v in data.items() if k in fields + ("action",)}
    sym_raw = {k: raw_symmetry(action_dim).ops[k] for k in raw}
    norm = fit_normalizer(raw, sym_raw)
    cfg = base.with_data(action_dim, {f: raw[f].shape[-1] for f in fields},
                         {f: raw[f].shape[1:] for f in fields})
    policy = make_policy(cfg.name, cfg)
    return policy, normalized_symmetry(sym_raw, norm), make_dataset(norm.normalize(raw), ends, cfg), norm


def fixed_batch(dataset, n=6, seed=3):
    idx = jnp.arange(n) * 7 % dataset.num_windows
    batch = {k: dataset.frames[k][dataset.obs_index[idx]] for k in dataset.obs_keys}
    batch[dataset.action_key] = dataset.frames[dataset.action_key][dataset.action_index[idx]]
    return batch, jax.random.key(seed)


def symmetrised(policy, sym):
    """``policy`` with its network replaced by ``0.5 (f(x) + S f(S x))``: equivariant by
    construction (``S`` is an involution), whatever the parameters."""

    def mirror_pred(pred):
        if isinstance(pred, dict):
            return {**pred, "action": policy.mirror_view(sym, pred["action"])}
        return policy.mirror_view(sym, pred)

    def apply(params, inputs):
        p = policy.apply(params, inputs)
        pm = mirror_pred(policy.apply(params, policy.mirror_inputs(sym, inputs)))
        return jax.tree.map(lambda a, b: 0.5 * (a + b), p, pm)

    return policy._replace(apply=apply)


# ---------------------------------------------------------------- tests


def test_every_registered_policy_is_covered():
    assert set(policy_names()) <= {c.name for c in CONFIGS.values()}


@pytest.mark.parametrize("name,action_dim", [(n, 14) for n in sorted(CONFIGS)] + [("dp3", 20)] + [
    pytest.param(n, 20, marks=pytest.mark.slow) for n in sorted(CONFIGS) if n != "dp3"])
def test_shapes_and_finite_outputs(name, action_dim):
    policy, sym, dataset, _ = prepared(name, action_dim)
    params = policy.init(jax.random.key(0))
    batch, key = fixed_batch(dataset, n=3)
    inputs, targets = policy.prepare(batch, key)
    pred = jax.jit(policy.apply)(params, inputs)
    view = policy.sym_view(inputs, pred)
    assert view.shape == (3, policy.config.pred_horizon, action_dim)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(pred))
    assert np.isfinite(float(policy.bc_loss(pred, targets)))
    obs = {k: batch[k] for k in policy.config.obs_keys}
    a = jax.jit(policy.sample)(params, obs, jax.random.key(1))
    assert a.shape == (3, policy.config.pred_horizon, action_dim)
    assert bool(jnp.all(jnp.isfinite(a)))


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_sym_loss_zero_when_symmetrised_positive_otherwise_finite_gradient(name):
    policy, sym, dataset, _ = prepared(name)
    params = policy.init(jax.random.key(1))
    batch, key = fixed_batch(dataset)
    equi = symmetrised(policy, sym)

    @jax.jit
    def run(p):
        generic = sym_loss(policy, p, batch, key, sym)
        grad = jax.grad(lambda q: sym_loss(policy, q, batch, key, sym, norm="rms"))(p)
        return generic, sym_loss(equi, p, batch, key, sym), grad

    generic, zero, grad = run(params)
    assert float(generic) > 1e-3
    assert float(zero) < 1e-10 * max(1.0, float(generic))
    leaves = jax.tree.leaves(grad)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
    assert sum(float(jnp.sum(jnp.abs(g))) for g in leaves) > 0


def _train(policy, dataset, sym, sym_weight, steps=150):
    tc = TrainConfig(batch_size=16, learning_rate=3e-3, warmup_steps=10, total_steps=steps,
                     sym_weight=sym_weight, steps_per_dispatch=steps, seed=0)
    state = create_train_state(policy, tc)
    state, metrics = make_train_loop(tc, dataset, sym if sym_weight > 0 else None)(state, base_key(tc))
    return state, metrics


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(set(CONFIGS) - {"dp_wrist"}))  # dp covers dp_wrist's code
def test_short_training_with_sym_loss_lowers_equivariance_error(name):
    policy, sym, dataset, _ = prepared(name)
    batch, key = fixed_batch(dataset, n=16, seed=11)
    errs = {}
    for w in (0.0, 1.0):
        state, metrics = _train(policy, dataset, sym, w)
        assert np.isfinite(np.asarray(metrics["total"])).all()
        errs[w] = float(equivariance_error(policy, state.params, batch, key, sym))
    assert errs[1.0] < 0.7 * errs[0.0], errs


@pytest.mark.slow  # dp3's exact resume is in test_training.py
@pytest.mark.parametrize("name", sorted(set(CONFIGS) - {"dp3", "dp_wrist"}))
def test_checkpoint_resume_is_exact(name, tmp_path):
    policy, sym, dataset, norm = prepared(name)
    tc = TrainConfig(batch_size=8, total_steps=20, warmup_steps=2, steps_per_dispatch=5, seed=0)
    loop = make_train_loop(tc, dataset, sym)
    key = base_key(tc)
    straight = create_train_state(policy, tc)
    for _ in range(2):
        straight, _ = loop(straight, key)
    half, _ = loop(create_train_state(policy, tc), key)
    config = {"policy": policy.config, "train": tc}
    save_checkpoint(tmp_path, half, norm, config)
    restored, _, saved = restore_checkpoint(tmp_path, create_train_state(policy, tc), expected_config=config)
    resumed, _ = loop(restored, key)
    for a, b in zip(jax.tree.leaves((resumed.params, resumed.ema_params, resumed.opt_state)),
                    jax.tree.leaves((straight.params, straight.ema_params, straight.opt_state))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert config_from_dict(PolicyConfig, saved["policy"]) == policy.config


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_config_json_round_trip_and_unresolved_dims(name):
    policy, *_ = prepared(name)
    d = json.loads(json.dumps(config_to_dict({"policy": policy.config})))
    assert config_from_dict(PolicyConfig, d["policy"]) == policy.config
    with pytest.raises(ValueError, match="unresolved"):
        make_policy(policy.config.name, CONFIGS[name])
    with pytest.raises(ValueError, match="do not have"):
        CONFIGS[name].with_data(14, {"nothing": 3}, {"nothing": (3,)})
