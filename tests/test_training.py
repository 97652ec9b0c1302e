"""Losses (BC, L_sym), the jitted train step/loop, and checkpoints (exact resume)."""

import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from orbax.checkpoint._src.path.atomicity import AtomicRenameTemporaryPath

from equibim_jax.config import ConfigError, config_from_dict, config_to_dict
from equibim_jax.data import fit_normalizer, make_dataset, normalized_symmetry, sample_batch, window_indices
from equibim_jax.policies import DP3Config, EncoderConfig, PolicyConfig, UNetConfig, make_policy
from equibim_jax.policies.diffusion import NoisePredictor, add_noise, make_schedule, predict_x0
from equibim_jax.symmetry import JointMap, Mirror, Symmetry, point_cloud_op
from equibim_jax.training import (
    CheckpointError,
    TrainConfig,
    base_key,
    create_train_state,
    latest_step,
    make_joint_train_loop,
    make_optimizer,
    make_train_loop,
    policy_loss,
    restore_checkpoint,
    save_checkpoint,
    sym_loss,
    sym_ramp,
    sym_residual_norm,
)

A = 4
POLICY = DP3Config(
    action_dim=A,
    state_dim=A,
    obs_horizon=2,
    pred_horizon=8,
    action_horizon=4,
    encoder=EncoderConfig(state_hidden=(16,), state_out=8, pc_hidden=(8, 16), pc_out=8),
    # One U-Net level keeps compile times short; the full down/up path is covered in
    # test_policy.py and benchmarks/train.py.
    unet=UNetConfig(down_dims=(16,), kernel_size=5, n_groups=4, step_embed_dim=16),
)
DP3 = make_policy("dp3", POLICY)
TRAIN = TrainConfig(
    batch_size=16,
    learning_rate=1e-3,
    warmup_steps=10,
    total_steps=400,
    sym_weight=0.1,
    # The loss form these tests were written for (no longer the defaults).
    sym_stop_gradient=False,
    sym_norm="mse",
    steps_per_dispatch=25,
    seed=0,
)
# Arm A = joints (0, 1), arm B = joints (2, 3); the second joint of each arm flips sign.
JM = JointMap([2, 3, 0, 1], [1, -1, 1, -1], [0.0, 0.0, 0.0, 0.0])
RAW_SYM = Symmetry({"qpos": JM, "action": JM, "point_cloud": point_cloud_op(Mirror.from_axis("y"))})


def _with_net(fn, policy=DP3):
    """``policy`` (its prepare, BC loss, mirrors and sym view) with the network replaced by
    ``fn(params, noisy_actions [B, Tp, A], k [B], obs) -> eps [B, Tp, A]``."""
    return policy._replace(apply=lambda params, inputs: fn(params, inputs["noisy_action"], inputs["k"],
                                                           inputs["obs"]))


def g(params, x, k, obs):
    """The dp3 network, ``(params, a_k, k, obs) -> eps``."""
    return NoisePredictor(POLICY).apply({"params": params}, x, k, obs)


def _frames(episodes=8, length=20, seed=0):
    """Smooth joint trajectories; the action is the next state; a noisy cloud per frame."""
    rng = np.random.default_rng(seed)
    t = np.arange(length) / length
    qs = []
    for _ in range(episodes):
        phase = rng.uniform(0, 2 * np.pi, A)
        qs.append(np.sin(2 * np.pi * t[:, None] + phase) * [1.0, 0.5, 2.0, 0.3] + [0.5, 0.0, 1.0, 0.0])
    q = np.concatenate(qs).astype(np.float32)
    pc = rng.normal(size=(len(q), 16, 3)).astype(np.float32) * 0.2 + q[:, None, :3]
    return {"qpos": q, "action": np.roll(q, -1, axis=0), "point_cloud": pc}, np.arange(1, episodes + 1) * length


@pytest.fixture(scope="module")
def setup():
    frames, ends = _frames()
    norm = fit_normalizer(frames, RAW_SYM)
    sym = normalized_symmetry(RAW_SYM, norm)
    dataset = make_dataset(norm.normalize(frames), ends, POLICY)
    loop = make_train_loop(TRAIN, dataset, sym)
    return dict(norm=norm, sym=sym, dataset=dataset, loop=loop)


# ---------------------------------------------------------------- L_sym


def _inputs(b=3, seed=0):
    """A batch ``{action: [b, Tp, A], qpos: [b, To, A], point_cloud: [b, To, 12, 3]}`` and a
    key for ``policy.prepare`` (which draws the noise and the diffusion steps)."""
    ks = jax.random.split(jax.random.key(seed), 4)
    batch = {
        "action": jax.random.normal(ks[0], (b, POLICY.pred_horizon, A)),
        "qpos": jax.random.normal(ks[2], (b, POLICY.obs_horizon, A)),
        "point_cloud": jax.random.normal(ks[3], (b, POLICY.obs_horizon, 12, 3)),
    }
    return batch, ks[1]


def test_sym_loss_zero_for_equivariant_model_positive_otherwise(setup):
    sym = setup["sym"]
    params = DP3.init(jax.random.key(1))
    s_a = sym["action"]

    def symmetrised(p, x, k, obs):  # f = 0.5 (g(x, O) + S_a g(S_a x, S O)): equivariant
        mirrored_obs = {f: sym[f](v) for f, v in obs.items()}
        return 0.5 * (g(p, x, k, obs) + s_a(g(p, s_a(x), k, mirrored_obs)))

    batch, key = _inputs()

    @jax.jit  # one compile for both models
    def both(p):
        return sym_loss(DP3, p, batch, key, sym), sym_loss(_with_net(symmetrised), p, batch, key, sym)

    generic, equivariant = (float(v) for v in both(params))
    assert equivariant < 1e-10
    assert generic > 1e-3


def _small_apply(params, x, k, obs):
    """A generic (not equivariant) ε-model that is cheap to compile: [B, Tp, A] -> same."""
    feat = jnp.concatenate(
        [obs["qpos"].reshape(x.shape[0], -1), obs["point_cloud"].mean(axis=(1, 2)), k[:, None] / 100.0],
        axis=-1,
    )
    h = jnp.tanh(x @ params["w"] + (feat @ params["c"])[:, None, :])
    return h @ params["v"]


def _small_params(feat_dim=POLICY.obs_horizon * A + 3 + 1):
    ks = jax.random.split(jax.random.key(5), 3)
    return {
        "w": jax.random.normal(ks[0], (A, 8)),
        "c": jax.random.normal(ks[1], (feat_dim, 8)),
        "v": jax.random.normal(ks[2], (8, A)),
    }


SMALL = _with_net(_small_apply)


def test_sym_loss_stop_gradient_changes_gradients(setup):
    sym = setup["sym"]
    batch, key = _inputs()
    params = _small_params()
    grad = jax.grad(lambda p, sg: sym_loss(SMALL, p, batch, key, sym, stop_gradient=sg))
    g_both, g_stop = grad(params, False), grad(params, True)
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(g_stop))
    assert max(float(jnp.abs(g_both[n] - g_stop[n]).max()) for n in params) > 1e-6
    # The loss value itself does not depend on the flag.
    assert float(sym_loss(SMALL, params, batch, key, sym, stop_gradient=True)) == pytest.approx(
        float(sym_loss(SMALL, params, batch, key, sym)), rel=1e-6
    )


def test_diffusion_loss_terms(setup):
    sym, ds = setup["sym"], setup["dataset"]
    params = _small_params()
    batch = sample_batch(ds, jax.random.key(2), 8)
    assert batch["action"].shape == (8, 8, A) and batch["point_cloud"].shape == (8, 2, 16, 3)
    total, terms = policy_loss(SMALL, params, batch, jax.random.key(3), sym, sym_weight=0.5)
    assert set(terms) == {"bc", "sym", "total"}
    assert float(total) == pytest.approx(float(terms["bc"] + 0.5 * terms["sym"]), rel=1e-6)
    assert float(terms["sym"]) > 0
    plain, plain_terms = policy_loss(SMALL, params, batch, jax.random.key(3))
    # Same key -> same noise and k: BC of the original branch does not depend on the mirror.
    assert float(plain_terms["bc"]) == pytest.approx(float(terms["bc"]), rel=1e-5)
    assert float(plain_terms["sym"]) == 0.0
    # Mirror augmentation averages BC over both branches.
    _, aug = policy_loss(SMALL, params, batch, jax.random.key(3), sym, mirror_augment=True)
    assert float(aug["bc"]) != pytest.approx(float(terms["bc"]), rel=1e-4)
    with pytest.raises(ValueError, match="needs a symmetry"):
        policy_loss(SMALL, params, batch, jax.random.key(3), None, sym_weight=0.5)


def test_sym_loss_in_x0_space(setup):
    """sym_target="x0" compares the clean actions the eps predictions imply (clipped as in
    DDIM): 0 for an equivariant model, and for unclipped elements the eps residual times
    sqrt((1 - abar_k) / abar_k), checked against an unclipped hand computation."""
    sym, ds = setup["sym"], setup["dataset"]
    s_a = sym["action"]
    x0_policy = make_policy("dp3", dataclasses.replace(POLICY, sym_target="x0"))
    params = jax.tree.map(lambda w: 0.05 * w, _small_params())  # small outputs: nothing clipped
    batch = sample_batch(ds, jax.random.key(2), 8)
    sched = make_schedule(100)
    key = jax.random.key(3)

    def symmetrised(p, x, k, obs):
        mirrored_obs = {f: sym[f](v) for f, v in obs.items()}
        return 0.5 * (_small_apply(p, x, k, obs) + s_a(_small_apply(p, s_a(x), k, mirrored_obs)))

    _, eq = policy_loss(_with_net(symmetrised, x0_policy), params, batch, key, sym, sym_weight=0.5)
    assert float(eq["sym"]) < 1e-6
    small_x0 = _with_net(_small_apply, x0_policy)
    _, t = policy_loss(small_x0, params, batch, key, sym, sym_weight=0.5, norm="mse")
    k_noise, k_step = jax.random.split(key)
    a0 = batch["action"]
    noise = jax.random.normal(k_noise, a0.shape, a0.dtype)
    k = jax.random.randint(k_step, (8,), 0, 100)
    a_k = add_noise(sched, a0, noise, k)
    obs = {f: v for f, v in batch.items() if f != "action"}
    e = _small_apply(params, s_a(a_k), k, {f: sym[f](v) for f, v in obs.items()}) - s_a(_small_apply(params, a_k, k, obs))
    acp = sched.alphas_cumprod[k][:, None, None]
    eps, eps_m = _small_apply(params, a_k, k, obs), _small_apply(params, s_a(a_k), k, {f: sym[f](v) for f, v in obs.items()})
    # Unclipped, the x0 residual is the eps residual scaled by -sqrt((1 - abar) / abar).
    r = predict_x0(sched, s_a(a_k), eps_m, k, clip=False) - s_a(predict_x0(sched, a_k, eps, k, clip=False))
    np.testing.assert_allclose(np.asarray(r), np.asarray(-e * jnp.sqrt((1 - acp) / acp)), rtol=1e-3, atol=1e-4)
    # The loss uses the clipped x0 of both branches (the mirrored one at S_a a_k).
    want = jnp.mean(jnp.square(predict_x0(sched, s_a(a_k), eps_m, k) - s_a(predict_x0(sched, a_k, eps, k))))
    assert float(t["sym"]) == pytest.approx(float(want), rel=1e-5)
    assert float(t["sym"]) > 1e-6
    _, t_eps = policy_loss(SMALL, params, batch, key, sym, sym_weight=0.5, norm="mse")
    assert float(t["sym"]) != pytest.approx(float(t_eps["sym"]), rel=1e-2)
    # What L_sym compares is the policy's choice now (DP3Config.sym_target), checked there.
    with pytest.raises(ValueError, match="sym_target"):
        dataclasses.replace(POLICY, sym_target="a0")


def test_sample_prediction_targets_and_sym_loss(setup):
    """prediction="sample": the BC target is the clean chunk, and L_sym is 0 for an
    equivariant sample-predictor and > 0 for a generic one, in both sym_target views."""
    sym, ds = setup["sym"], setup["dataset"]
    s_a = sym["action"]
    params = jax.tree.map(lambda w: 0.05 * w, _small_params())
    batch = sample_batch(ds, jax.random.key(2), 8)
    key = jax.random.key(3)

    def symmetrised(p, x, k, obs):
        mirrored_obs = {f: sym[f](v) for f, v in obs.items()}
        return 0.5 * (_small_apply(p, x, k, obs) + s_a(_small_apply(p, s_a(x), k, mirrored_obs)))

    for view in ("eps", "x0"):
        pol = make_policy("dp3", dataclasses.replace(POLICY, prediction="sample", sym_target=view))
        inputs, targets = pol.prepare(batch, key)
        np.testing.assert_array_equal(np.asarray(targets["sample"]), np.asarray(batch["action"]))
        pred = _small_apply(params, inputs["noisy_action"], inputs["k"], inputs["obs"])
        want = jnp.mean(jnp.square(pred - batch["action"]))
        assert float(pol.bc_loss(pred, targets)) == pytest.approx(float(want), rel=1e-6)
        _, eq = policy_loss(_with_net(symmetrised, pol), params, batch, key, sym, sym_weight=0.5)
        _, gen = policy_loss(_with_net(_small_apply, pol), params, batch, key, sym, sym_weight=0.5)
        assert float(eq["sym"]) < 1e-6, view
        assert float(gen["sym"]) > 1e-6, view
        assert np.isfinite(float(gen["total"]))


def test_sym_loss_on_a_sub_batch(setup):
    """sym_batch=n: BC still over all B samples, L_sym the mean over the first n of them."""
    sym, ds = setup["sym"], setup["dataset"]
    s_a = sym["action"]
    params = _small_params()
    batch = sample_batch(ds, jax.random.key(2), 8)
    sched = make_schedule(100)
    key = jax.random.key(3)
    # "rms" is the per-sample RMS form (what "l2" was called before).
    _, full = policy_loss(SMALL, params, batch, key, sym, sym_weight=0.5, norm="rms")
    total, sub = policy_loss(SMALL, params, batch, key, sym, sym_weight=0.5, norm="rms", sym_batch=3)
    assert float(sub["bc"]) == pytest.approx(float(full["bc"]), rel=1e-5)
    assert float(total) == pytest.approx(float(sub["bc"] + 0.5 * sub["sym"]), rel=1e-6)
    # The same noise and diffusion steps as inside policy_loss, then L_sym on 3 samples.
    k_noise, k_step = jax.random.split(key)
    a0 = batch["action"]
    noise = jax.random.normal(k_noise, a0.shape, a0.dtype)
    k = jax.random.randint(k_step, (8,), 0, 100)
    a_k = add_noise(sched, a0, noise, k)
    a3, k3 = a_k[:3], k[:3]
    obs3 = {f: v[:3] for f, v in batch.items() if f != "action"}
    e = np.asarray(_small_apply(params, s_a(a3), k3, {f: sym[f](v) for f, v in obs3.items()})
                   - s_a(_small_apply(params, a3, k3, obs3))).reshape(3, -1)
    want = np.mean(np.linalg.norm(e, axis=1) / np.sqrt(e.shape[1]))
    assert float(sub["sym"]) == pytest.approx(float(want), rel=1e-5)
    assert float(sub["sym"]) != pytest.approx(float(full["sym"]), rel=1e-3)
    _, all8 = policy_loss(SMALL, params, batch, key, sym, sym_weight=0.5, norm="rms", sym_batch=8)
    assert float(all8["sym"]) == pytest.approx(float(full["sym"]), rel=1e-6)
    with pytest.raises(ValueError, match="sym_batch_size"):
        TrainConfig(batch_size=16, sym_batch_size=17)
    for bad in (0, 9):
        with pytest.raises(ValueError, match="sym_batch"):
            policy_loss(SMALL, params, batch, key, sym, sym_weight=0.5, sym_batch=bad)


def test_sym_loss_rms_and_l2_norms_are_per_sample_norms(setup):
    """norm="rms" is the paper's unsquared ||.||_2 per sample scaled by 1/sqrt(D), averaged
    (what norm="l2" meant before); norm="l2" is the unscaled per-sample norm, averaged."""
    sym = setup["sym"]
    batch, key = _inputs(b=5)
    params = _small_params()
    s_a = sym["action"]
    inputs, _ = SMALL.prepare(batch, key)
    x, k, obs = inputs["noisy_action"], inputs["k"], inputs["obs"]
    # jitted, not eager: op by op, the network's forward and backward compile hundreds of programs
    e = np.asarray(jax.jit(lambda q: _small_apply(q, s_a(x), k, {f: sym[f](v) for f, v in obs.items()})
                           - s_a(_small_apply(q, x, k, obs)))(params)).reshape(5, -1)
    want = np.mean(np.linalg.norm(e, axis=1) / np.sqrt(e.shape[1]))
    loss = jax.jit(lambda q, norm: sym_loss(SMALL, q, batch, key, sym, **({} if norm is None else {"norm": norm})),
                   static_argnums=1)
    assert float(loss(params, "rms")) == pytest.approx(want, rel=1e-5)
    assert float(loss(params, "l2")) == pytest.approx(np.mean(np.linalg.norm(e, axis=1)), rel=1e-5)
    assert float(loss(params, None)) == pytest.approx(np.mean(e**2), rel=1e-5)
    # Scaling the model by c scales d(residual)/d(params) by c; on top of that the MSE's
    # gradient shrinks with the residual (c^2 overall), the unsquared norm's does not (c).
    p = DP3.init(jax.random.key(1))

    def scaled(c):
        return _with_net(lambda p_, x_, k_, o_: c * g(p_, x_, k_, o_))

    @functools.partial(jax.jit, static_argnums=1)
    def grad_norm(c, norm):
        return optax.tree.norm(jax.grad(lambda q: sym_loss(scaled(c), q, batch, key, sym, norm=norm))(p))

    def gnorm(c, norm):
        return float(grad_norm(jnp.float32(c), norm))

    assert gnorm(1e-3, "rms") == pytest.approx(1e-3 * gnorm(1.0, "rms"), rel=1e-3)
    assert gnorm(1e-3, "mse") == pytest.approx(1e-6 * gnorm(1.0, "mse"), rel=1e-3)
    with pytest.raises(ValueError, match="sym norm"):
        sym_loss(SMALL, params, batch, key, sym, norm="l1")


def test_sym_residual_norm_forms_by_hand():
    """The three L_sym forms on a residual with known entries, N = 2 samples, D = 4."""
    e = jnp.array([[3.0, 4.0, 0.0, 0.0],    # ||e_0||^2 = 25, ||e_0|| = 5
                   [1.0, 1.0, 1.0, 1.0]])   # ||e_1||^2 = 4,  ||e_1|| = 2
    # mse: mean of the 8 squares = (25 + 4) / 8
    assert float(sym_residual_norm(e, "mse")) == pytest.approx(29 / 8, rel=1e-6)
    # rms: mean over samples of ||e_i|| / sqrt(D) = (5 / 2 + 2 / 2) / 2
    assert float(sym_residual_norm(e, "rms")) == pytest.approx(1.75, rel=1e-6)
    # l2: mean over samples of ||e_i|| = (5 + 2) / 2
    assert float(sym_residual_norm(e, "l2")) == pytest.approx(3.5, rel=1e-6)
    assert float(sym_residual_norm(e, "l2")) == pytest.approx(2.0 * float(sym_residual_norm(e, "rms")), rel=1e-6)
    # Trailing axes are flattened per sample: [2, 2, 2] is the same residual.
    assert float(sym_residual_norm(e.reshape(2, 2, 2), "l2")) == pytest.approx(3.5, rel=1e-6)
    with pytest.raises(ValueError, match="sym norm"):
        sym_residual_norm(e, "l1")


def _cheap_policy():
    """The dp3 policy with the cheap network ``_small_apply`` (and its params as init)."""
    return SMALL._replace(init=lambda key: _small_params())


def test_sym_weight_warmup(setup):
    assert float(sym_ramp(jnp.int32(0), 0)) == 1.0
    assert [float(sym_ramp(jnp.int32(s), 4)) for s in (0, 1, 3, 10)] == [0.25, 0.5, 1.0, 1.0]
    # A delayed start: 0 before start_step, then the ramp from there.
    assert [float(sym_ramp(jnp.int32(s), 0, 3)) for s in (0, 2, 3, 9)] == [0.0, 0.0, 1.0, 1.0]
    assert [float(sym_ramp(jnp.int32(s), 2, 3)) for s in (2, 3, 4, 9)] == [0.0, 0.5, 1.0, 1.0]
    with pytest.raises(ValueError, match="sym_start_step"):
        dataclasses.replace(TRAIN, sym_start_step=TRAIN.total_steps)
    # In the train loop the lambda in effect is logged per step and ramps as scheduled.
    cfg = dataclasses.replace(TRAIN, sym_warmup_steps=50, steps_per_dispatch=25)
    loop = make_train_loop(cfg, setup["dataset"], setup["sym"])
    state = create_train_state(DP3, cfg)
    _, m = loop(state, base_key(cfg))
    np.testing.assert_allclose(np.asarray(m["sym_weight"]), 0.1 * np.arange(1, 26) / 50, rtol=1e-6)
    # sym_warmup_steps > total_steps is no longer refused: the ramp is clamped to the run
    # (here 50 steps), checked on a cheap network.
    cfg = TrainConfig(batch_size=16, warmup_steps=10, sym_warmup_steps=500, total_steps=50, sym_weight=0.1,
                      steps_per_dispatch=25)
    _, m = make_train_loop(cfg, setup["dataset"], setup["sym"])(create_train_state(_cheap_policy(), cfg),
                                                                 base_key(cfg))
    np.testing.assert_allclose(np.asarray(m["sym_weight"]), 0.1 * np.arange(1, 26) / 50, rtol=1e-6)
    with pytest.raises(ValueError, match="sym_warmup_steps"):
        TrainConfig(sym_warmup_steps=-1)
    with pytest.raises(ValueError, match="sym_norm"):
        TrainConfig(sym_norm="huber")


# ---------------------------------------------------------------- data windows


def test_window_indices_by_hand():
    obs, act = window_indices([5, 8], obs_horizon=2, pred_horizon=4, pad_before=1, pad_after=1)
    # Episode 0 (frames 0-4): starts t = -1..2; episode 1 (frames 5-7): t = 4..5.
    np.testing.assert_array_equal(obs[:4], [[0, 0], [0, 1], [1, 2], [2, 3]])
    np.testing.assert_array_equal(act[0], [0, 0, 1, 2])
    np.testing.assert_array_equal(act[3], [2, 3, 4, 4])
    np.testing.assert_array_equal(act[4:], [[5, 5, 6, 7], [5, 6, 7, 7]])
    assert obs.shape == (6, 2) and act.shape == (6, 4)
    with pytest.raises(ValueError, match="no training window"):
        window_indices([2], 2, 8)
    with pytest.raises(ValueError, match="strictly increasing"):
        window_indices([5, 5], 2, 4)


# ---------------------------------------------------------------- training


def test_tiny_training_run_decreases_loss(setup):
    state = create_train_state(DP3, TRAIN)
    key = base_key(TRAIN)
    totals = []
    for _ in range(8):  # 200 steps, 25 per dispatch
        state, metrics = setup["loop"](state, key)
        assert metrics["total"].shape == (TRAIN.steps_per_dispatch,)
        totals.append(float(metrics["bc"].mean()))
    assert int(state.step) == 200
    assert np.isfinite(totals).all()
    assert totals[-1] < 0.7 * totals[0], totals
    # The EMA trails the parameters but has moved away from the initial values.
    init_state = create_train_state(DP3, TRAIN)
    w0 = jax.tree.leaves(init_state.params)[0]
    we = jax.tree.leaves(state.ema_params)[0]
    assert float(jnp.abs(we - w0).max()) > 0


def _assert_trees_equal(a, b):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_exact_resume(setup, tmp_path, monkeypatch):
    loop, key, norm = setup["loop"], base_key(TRAIN), setup["norm"]
    config = {"policy": POLICY, "train": TRAIN}
    straight = create_train_state(DP3, TRAIN)
    for _ in range(2):
        straight, _ = loop(straight, key)

    half = create_train_state(DP3, TRAIN)
    half, _ = loop(half, key)
    # Orbax writes into a temporary folder and renames it into place on finalize.
    finalized = []
    original = AtomicRenameTemporaryPath.finalize

    async def spy(self, *a, **kw):
        finalized.append((self.get(), self.get_final(), self.get().exists()))
        return await original(self, *a, **kw)

    monkeypatch.setattr(AtomicRenameTemporaryPath, "finalize", spy)
    save_checkpoint(tmp_path, half, norm, config)
    assert all(".orbax-checkpoint-tmp" in tmp.name and existed for tmp, _, existed in finalized)
    step_dir = [(tmp, final) for tmp, final, _ in finalized if str(final) == str(tmp_path / str(TRAIN.steps_per_dispatch))]
    assert len(step_dir) == 1, finalized  # the step folder itself was renamed into place
    assert not step_dir[0][0].exists() and step_dir[0][1].is_dir()
    assert latest_step(tmp_path) == TRAIN.steps_per_dispatch
    assert not [p for p in tmp_path.iterdir() if "tmp" in p.name]  # renamed into place
    fresh = create_train_state(DP3, TRAIN)
    restored, norm2, saved = restore_checkpoint(tmp_path, fresh, expected_config=config)
    resumed, _ = loop(restored, key)

    assert int(resumed.step) == int(straight.step) == 2 * TRAIN.steps_per_dispatch
    _assert_trees_equal(resumed.params, straight.params)
    _assert_trees_equal(resumed.ema_params, straight.ema_params)
    _assert_trees_equal(resumed.opt_state, straight.opt_state)
    _assert_trees_equal(norm2, norm)
    assert config_from_dict(PolicyConfig, saved["policy"]) == POLICY
    assert config_from_dict(TrainConfig, saved["train"]) == TRAIN


def test_joint_loop_gives_each_run_its_own_steps(setup):
    """Baseline and +EquiBim in one program take the steps each takes alone."""
    base = dataclasses.replace(TRAIN, sym_weight=0.0, seed=0)
    sym = dataclasses.replace(TRAIN, seed=1)
    alone = []
    for tc in (base, sym):
        st = create_train_state(DP3, tc)
        st, m = make_train_loop(tc, setup["dataset"], setup["sym"] if tc.uses_mirror else None)(st, base_key(tc))
        alone.append((st, m))
    joint = make_joint_train_loop((base, sym), setup["dataset"], (None, setup["sym"]))
    states, metrics = joint((create_train_state(DP3, base), create_train_state(DP3, sym)), (base_key(base), base_key(sym)))
    for (st, m), st2, m2 in zip(alone, states, metrics):
        assert int(st2.step) == int(st.step) == TRAIN.steps_per_dispatch
        for x, y in zip(jax.tree.leaves(st.params), jax.tree.leaves(st2.params)):
            np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(m2["total"], m["total"], rtol=1e-5)
    assert float(metrics[0]["sym"].max()) == 0.0 < float(metrics[1]["sym"].min())
    # the runs really differ (else the comparison above says nothing)
    assert not np.allclose(np.asarray(jax.tree.leaves(states[0].params)[0]),
                           np.asarray(jax.tree.leaves(states[1].params)[0]))
    with pytest.raises(ValueError, match="one symmetry per train config"):
        make_joint_train_loop((base, sym), setup["dataset"], (None,))


def test_checkpoint_errors(setup, tmp_path):
    norm = setup["norm"]
    config = {"policy": POLICY, "train": TRAIN}
    state = create_train_state(DP3, TRAIN)
    with pytest.raises(FileNotFoundError, match="no completed checkpoint"):
        restore_checkpoint(tmp_path / "nothing", state)
    save_checkpoint(tmp_path, state, norm, config, step=3)
    with pytest.raises(CheckpointError, match="already exists"):
        save_checkpoint(tmp_path, state, norm, config, step=3)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        restore_checkpoint(tmp_path, state, step=4)
    other = {"policy": POLICY, "train": dataclasses.replace(TRAIN, sym_weight=0.3)}
    with pytest.raises(CheckpointError, match=r"train\.sym_weight: expected 0\.3"):
        restore_checkpoint(tmp_path, state, expected_config=other)
    restore_checkpoint(tmp_path, state, expected_config=other, ignore_config_keys=("train.sym_weight",))

    # A half-written checkpoint (orbax's temporary folder) is not a completed step.
    (tmp_path / "9.orbax-checkpoint-tmp-123").mkdir()
    assert latest_step(tmp_path) == 3

    # A model of another shape cannot be restored into.
    wider = jax.tree.map(lambda p: jnp.zeros(p.shape[:-1] + (p.shape[-1] + 1,)), state.params)
    with pytest.raises(CheckpointError, match=r"(?s)arrays do not match the template.*\['encoder'\]\['pc'\]"):
        restore_checkpoint(tmp_path, state.replace(params=wider, ema_params=wider))

    # Corrupt: garbage in the state's tree metadata. (Truncating the array data files
    # also raises CheckpointError, but orbax/tensorstore then leave callbacks on a closed
    # event loop that pytest reports as unraisable-exception warnings in later tests.)
    (tmp_path / "3" / "state" / "_METADATA").write_text("{not json")
    with pytest.raises(CheckpointError, match="cannot restore"):
        restore_checkpoint(tmp_path, state)
    (tmp_path / "3" / "config").rename(tmp_path / "3" / "config_gone")
    with pytest.raises(CheckpointError, match="cannot read config"):
        restore_checkpoint(tmp_path, state)


def test_config_json_round_trip():
    d = config_to_dict({"policy": POLICY, "train": TRAIN})
    d2 = json.loads(json.dumps(d))
    assert config_from_dict(PolicyConfig, d2["policy"]) == POLICY
    assert config_from_dict(DP3Config, d2["policy"]) == POLICY
    assert config_from_dict(TrainConfig, d2["train"]) == TRAIN
    with pytest.raises(ConfigError, match="unknown config fields"):
        config_from_dict(TrainConfig, {**d2["train"], "lr": 1.0})
    with pytest.raises(ConfigError, match="sym_weight"):
        config_from_dict(TrainConfig, {**d2["train"], "sym_weight": -1.0})


def test_train_config_errors():
    with pytest.raises(ValueError, match="warmup_steps"):
        TrainConfig(warmup_steps=-1)
    # warmup_steps > total_steps is no longer refused but clamped: the learning rate warms
    # up over the whole run, and the optimiser can be built and stepped.
    cfg = TrainConfig(warmup_steps=10, total_steps=5, steps_per_dispatch=5)
    tx = make_optimizer(cfg)
    w = {"w": jnp.ones(3)}
    opt_state = tx.init(w)
    for _ in range(3):
        updates, opt_state = tx.update({"w": jnp.ones(3)}, opt_state, w)
        w = optax.apply_updates(w, updates)
    assert np.all(np.isfinite(np.asarray(w["w"]))) and float(w["w"][0]) < 1.0
    with pytest.raises(ValueError, match="steps_per_dispatch"):
        TrainConfig(total_steps=60, steps_per_dispatch=50)
    with pytest.raises(ValueError, match="batch_size"):
        TrainConfig(batch_size=0)
    with pytest.raises(ValueError, match="needs a symmetry"):
        make_train_loop(TrainConfig(sym_weight=1.0), None, None)


# slow: it compares the tuned and plain train steps at XLA's default optimisation level,
# which the slow suite keeps (the default suite compiles at level 0; tests/conftest.py).
@pytest.mark.slow
def test_train_compiler_options(monkeypatch, setup):
    """The train step's XLA:CPU options are on by default, off with EQUIBIM_JAX_XLA_TUNING=0,
    and change speed, not results."""
    from equibim_jax._xla_options import TRAIN_CPU_OPTIONS, train_compiler_options

    assert train_compiler_options() == (TRAIN_CPU_OPTIONS if jax.default_backend() == "cpu" else None)
    cfg = dataclasses.replace(TRAIN, steps_per_dispatch=5)
    state = create_train_state(DP3, cfg)
    _, tuned = make_train_loop(cfg, setup["dataset"], setup["sym"])(state, base_key(cfg))
    monkeypatch.setenv("EQUIBIM_JAX_XLA_TUNING", "0")
    assert train_compiler_options() is None
    _, plain = make_train_loop(cfg, setup["dataset"], setup["sym"])(state, base_key(cfg))
    for name in ("bc", "sym", "total"):
        np.testing.assert_allclose(np.asarray(tuned[name]), np.asarray(plain[name]), rtol=1e-4, atol=1e-6)


def test_constant_action_warning_names_the_channels():
    """A noise-predicting diffusion policy on actions with constant channels is warned
    about, naming them; a clean-sample predictor, or actions with no constant channel, is not."""
    from equibim_jax.training.run import constant_action_warning

    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (5, 30, 6)).astype(np.float32)
    eps_cfg = DP3Config(prediction="epsilon")
    assert constant_action_warning(eps_cfg, acts) is None
    acts[..., 2] = 1.0
    acts[..., 4] = 1e-5 * rng.standard_normal((5, 30))  # float jitter around a constant
    msg = constant_action_warning(eps_cfg, acts)
    assert msg is not None and "[2, 4]" in msg and "prediction='sample'" in msg
    assert constant_action_warning(DP3Config(prediction="sample"), acts) is None
