"""The JAX-written Cholesky that MJX is traced with (equibim_jax/sim/_linalg.py)."""

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import pytest

from equibim_jax.sim import _linalg


def _spd(rng, batch, n):
    a = rng.normal(size=(batch, n, n))
    return (a @ np.swapaxes(a, -1, -2) + 0.5 * np.eye(n)).astype(np.float32)


@pytest.mark.parametrize("lower", [False, True])
def test_cho_factor_and_solve_match_numpy_batched(lower):
    rng = np.random.default_rng(0)
    a = _spd(rng, 64, 22)  # 64 x robot A's nv: the batch size that deadlocked LAPACK's
    b = rng.normal(size=(64, 22)).astype(np.float32)
    f = jax.jit(jax.vmap(lambda a, b: _linalg.cho_solve(_linalg.cho_factor(a, lower=lower), b)))
    x = np.asarray(f(a, b))
    ref = np.linalg.solve(a.astype(np.float64), b.astype(np.float64)[..., None])[..., 0]
    assert np.max(np.abs(x - ref)) / np.max(np.abs(ref)) < 1e-4
    assert _linalg.cho_factor(a[0], lower=lower)[1] == lower
    c = jax.vmap(lambda a: _linalg.cho_factor(a, lower=lower)[0])(a)
    l = np.asarray(c) if lower else np.swapaxes(np.asarray(c), -1, -2)
    np.testing.assert_allclose(l @ np.swapaxes(l, -1, -2), a, atol=1e-3 * np.abs(a).max())
    assert np.all(np.triu(l, 1) == 0)  # the other triangle is zero


def test_solve_with_matrix_right_hand_side_and_no_lapack_call():
    rng = np.random.default_rng(1)
    a = _spd(rng, 1, 6)[0]
    b = rng.normal(size=(6, 3)).astype(np.float32)
    x = _linalg.cho_solve(_linalg.cho_factor(a), b)
    np.testing.assert_allclose(np.asarray(a @ x), b, atol=1e-4)
    hlo = jax.jit(jax.vmap(lambda a: _linalg.cho_factor(a)[0])).lower(jnp.stack([a] * 4)).as_text()
    assert "lapack" not in hlo.lower() and "custom_call" not in hlo


def test_context_manager_swaps_and_restores():
    orig = (jsl.cho_factor, jsl.cho_solve)
    with _linalg.jax_cholesky():
        assert jsl.cho_factor is _linalg.cho_factor and jsl.cho_solve is _linalg.cho_solve
        with _linalg.jax_cholesky():  # re-entrant
            pass
        assert jsl.cho_factor is _linalg.cho_factor
    assert (jsl.cho_factor, jsl.cho_solve) == orig
    with pytest.raises(RuntimeError):
        with _linalg.jax_cholesky():
            raise RuntimeError("boom")
    assert (jsl.cho_factor, jsl.cho_solve) == orig
