"""Pure-JAX IK: forward kinematics against MuJoCo, accuracy on reachable targets,
mirror equivariance, joint limits, jit/vmap, and the mjx backend."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from equibim_jax.sim.ik import (
    make_arm_chains,
    make_ee_fk,
    make_ik,
    mat_to_quat,
    mat_to_rot6d,
    pose_errors,
    quat_to_mat,
    rot6d_to_mat,
)
from equibim_jax.sim.robots import load_robot, robot_info
from equibim_jax.symmetry import derive_symmetry, reflect_pose_6d, reflect_pose_quat

NAMES = ["robot_a", "robot_b"]
N = 128


def _setup(name):
    m, mirror = load_robot(name)
    return m, mirror, robot_info(name)


def _random_q(m, info, n, spread, seed):
    """Random robot postures: arm joints uniform within +-spread of home (clipped to the
    joint ranges), grippers at home. [n, nq]."""
    rng = np.random.default_rng(seed)
    ch = make_arm_chains(m, info)
    home = m.key_qpos[m.key(info.home_key).id]
    q = np.repeat(home[None], n, 0)
    arm = np.clip(home[ch.qadr][None] + rng.uniform(-spread, spread, (n, 2, ch.n)), ch.lo, ch.hi)
    q[:, ch.qadr.reshape(-1)] = arm.reshape(n, -1)
    return q


def _targets(fk, q, fmt):
    pos, mat = jax.vmap(fk)(jnp.asarray(q, jnp.float32))
    rot = {"quat": mat_to_quat(mat), "6d": mat_to_rot6d(mat), "mat": mat.reshape(mat.shape[:-2] + (9,))}
    return jnp.concatenate([pos, rot[fmt]], -1)


def test_rotation_utils():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(64, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    r = quat_to_mat(jnp.asarray(q))
    ref = np.zeros((64, 9))
    for i in range(64):
        mujoco.mju_quat2Mat(ref[i], q[i].astype(np.float64))
    np.testing.assert_allclose(np.asarray(r).reshape(64, 9), ref, atol=1e-6)
    q2 = np.asarray(mat_to_quat(r))
    np.testing.assert_allclose(np.abs(np.sum(q2 * q, -1)), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(rot6d_to_mat(mat_to_rot6d(r))), np.asarray(r), atol=1e-5)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("backend", ["chain", "mjx"])
def test_fk_matches_mujoco(name, backend):
    m, _, info = _setup(name)
    fk = jax.jit(jax.vmap(make_ee_fk(m, info, backend=backend)))
    q = _random_q(m, info, 16, 2.0, seed=3)
    pos, mat = fk(jnp.asarray(q, jnp.float32))
    d = mujoco.MjData(m)
    sids = [m.site(s).id for s in info.ee_sites]
    for i in range(len(q)):
        d.qpos[:] = q[i]
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(np.asarray(pos[i]), d.site_xpos[sids], atol=2e-6)
        np.testing.assert_allclose(np.asarray(mat[i]), d.site_xmat[sids].reshape(2, 3, 3), atol=2e-6)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("fmt", ["quat", "6d"])
def test_ik_accuracy(name, fmt):
    """Targets from FK of random postures within +-0.6 rad of home; IK from home."""
    m, _, info = _setup(name)
    fk = make_ee_fk(m, info)
    q_true = _random_q(m, info, N, 0.6, seed=0)
    targets = _targets(fk, q_true, fmt)
    ik = jax.jit(jax.vmap(make_ik(m, info)))  # defaults: 25 iterations
    q0 = jnp.asarray(np.repeat(m.key_qpos[0][None], N, 0), jnp.float32)
    q = jax.block_until_ready(ik(q0, targets))
    t0 = time.perf_counter()
    q = jax.block_until_ready(ik(q0, targets))
    dt = time.perf_counter() - t0
    perr, rerr = pose_errors(*jax.vmap(fk)(q), targets)
    perr_mm = np.asarray(perr).ravel() * 1e3
    rerr_deg = np.degrees(np.asarray(rerr).ravel())
    ok = (perr_mm < 2.0) & (rerr_deg < 1.0)
    print(
        f"\n{name} IK ({fmt}, {N} x 2 arms, 25 it): position error median {np.median(perr_mm) * 1e3:.2f} um, "
        f"p95 {np.percentile(perr_mm, 95) * 1e3:.1f} um, max {perr_mm.max():.3f} mm; rotation error "
        f"median {np.median(rerr_deg):.2e} deg, p95 {np.percentile(rerr_deg, 95):.2e} deg, max "
        f"{rerr_deg.max():.3f} deg; within 2 mm & 1 deg: {ok.mean() * 100:.1f}%; "
        f"{dt / N * 1e6:.0f} us per solve (batch {N}, jit+vmap, 2 arms)"
    )
    assert ok.mean() >= 0.95
    assert np.median(perr_mm) < 0.1 and np.median(rerr_deg) < 0.05
    # joint limits respected
    ch = make_arm_chains(m, info)
    qa = np.asarray(q)[:, ch.qadr]
    assert np.all(qa >= ch.lo - 1e-6) and np.all(qa <= ch.hi + 1e-6)


def _mirror_targets(mirror, targets, fmt):
    """Mirror both arms' targets and swap them (left target <- mirror of right target)."""
    f = reflect_pose_quat if fmt == "quat" else reflect_pose_6d
    return f(mirror, targets)[..., ::-1, :]


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("fmt", ["quat", "6d"])
def test_ik_equivariance(name, fmt):
    """ik(S q0, S T) == S ik(q0, T), with S on targets = mirror + swap arms and S on q the
    derived joint map; the initial guess is NOT symmetric."""
    m, mirror, info = _setup(name)
    sym = derive_symmetry(m, mirror)
    fk = make_ee_fk(m, info)
    targets = _targets(fk, _random_q(m, info, N, 0.6, seed=1), fmt)
    q0 = jnp.asarray(_random_q(m, info, N, 0.3, seed=2), jnp.float32)
    # the pose mirror matches FK of the mirrored joints (a check on the conventions)
    t_m = _mirror_targets(mirror, targets, fmt)
    q_true = jnp.asarray(_random_q(m, info, N, 0.6, seed=1), jnp.float32)
    np.testing.assert_allclose(
        np.asarray(_targets(fk, sym.qpos(q_true), fmt)), np.asarray(t_m), atol=2e-5
    )
    ik = jax.jit(jax.vmap(make_ik(m, info)))
    q_a = ik(q0, targets)
    q_b = ik(sym.qpos(q0), t_m)
    diff = np.abs(np.asarray(q_b) - np.asarray(sym.qpos(q_a)))
    print(f"\n{name} IK equivariance ({fmt}): max |ik(S q0, S T) - S ik(q0, T)| = {diff.max():.2e} rad "
          f"(median {np.median(diff):.1e})")
    # float32 rounding differs between the two arms' chains; 25 iterations amplify it a
    # little on the few near-singular samples
    assert np.median(diff) < 1e-6
    assert np.mean(diff.max(-1) < 1e-3) >= 0.98


@pytest.mark.parametrize("name", NAMES)
def test_ik_limits_active_and_formats(name):
    m, _, info = _setup(name)
    fk = make_ee_fk(m, info)
    ik = jax.jit(make_ik(m, info))
    ch = make_arm_chains(m, info)
    home = jnp.asarray(m.key_qpos[0], jnp.float32)
    pos, mat = fk(home)
    # unreachable targets: the solution stays inside the joint limits and finite
    far = jnp.concatenate([pos + jnp.array([2.0, 0.0, 1.0]), mat.reshape(2, 9)], -1)
    q = np.asarray(ik(home, far))
    assert np.all(np.isfinite(q))
    qa = q[ch.qadr]
    assert np.all(qa >= ch.lo - 1e-6) and np.all(qa <= ch.hi + 1e-6)
    # non-arm entries are copied through
    other = np.setdiff1d(np.arange(m.nq), ch.qadr.reshape(-1))
    np.testing.assert_array_equal(q[other], np.asarray(home)[other])
    # active mask: only the left arm moves
    q_true = jnp.asarray(_random_q(m, info, 1, 0.4, seed=5)[0], jnp.float32)
    t = _targets(fk, q_true[None], "mat")[0]
    q_left = np.asarray(ik(home, t, jnp.array([True, False])))
    np.testing.assert_array_equal(q_left[ch.qadr[1]], np.asarray(home)[ch.qadr[1]])
    p_l, _ = fk(q_left)
    assert float(jnp.linalg.norm(p_l[0] - t[0, :3])) < 2e-3
    # position-only targets and all rotation formats give the same pose
    q_pos = ik(home, t[:, :3])
    assert float(jnp.abs(fk(q_pos)[0] - t[:, :3]).max()) < 2e-3
    sols = [ik(home, _targets(fk, q_true[None], f)[0]) for f in ("quat", "6d", "mat")]
    for s in sols[1:]:
        np.testing.assert_allclose(np.asarray(s), np.asarray(sols[0]), atol=1e-4)


def test_ik_mjx_backend_and_mjx_model():
    """The mjx.kinematics backend, and an mjx.Model passed as the model, agree with chain."""
    from mujoco import mjx

    m, _, info = _setup("robot_a")
    fk = make_ee_fk(m, info)
    targets = _targets(fk, _random_q(m, info, 8, 0.5, seed=7), "quat")
    q0 = jnp.asarray(np.repeat(m.key_qpos[0][None], 8, 0), jnp.float32)
    a = jax.jit(jax.vmap(make_ik(m, info)))(q0, targets)
    b = jax.jit(jax.vmap(make_ik(m, info, backend="mjx")))(q0, targets)
    mx = mjx.put_model(m, impl="jax")
    c = jax.jit(jax.vmap(make_ik(mx, info, host_model=m, backend="mjx")))(q0, targets)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-3)
    np.testing.assert_allclose(np.asarray(b), np.asarray(c), atol=1e-6)
    with pytest.raises(TypeError):
        make_ik(mx, info)
