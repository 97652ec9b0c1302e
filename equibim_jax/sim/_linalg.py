"""Cholesky factor and solve written in JAX, for MJX's small dense systems.

MJX factors the mass matrix (``smooth.factor_m``), the Newton solver's Hessian
(``solver._update_gradient``) and the implicit integrator's matrix with
``jax.scipy.linalg.cho_factor`` / ``cho_solve``. On the CPU these lower to LAPACK
(``potrf``/``potrs`` custom calls); jaxlib 0.10.2 splits a *batched* call over its intra-op
thread pool and, on 2 cores, deadlocks there once the batch reaches 64 matrices. The
functions here are plain JAX (a ``fori_loop`` over columns of masked matrix-vector
products), so ``vmap`` turns them into ordinary batched array ops: no custom call, no
thread pool, any batch size, and the same program on a GPU.

:func:`jax_cholesky` swaps them into ``jax.scipy.linalg`` while a function is being
*traced* (``Env`` wraps its ``mjx.step`` / ``mjx.forward`` calls in it); compiled programs
keep no reference to the swap, and the originals are restored on exit. The systems are
``nv x nv`` (22 for robot A with one free body), where an O(n^3) loop of O(n^2) vector ops
costs the same order as the LAPACK call.
"""

from __future__ import annotations

import contextlib
import threading

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl


def cholesky_lower(a: jax.Array) -> jax.Array:
    """Lower-triangular ``L`` with ``L @ L.T == a`` for a symmetric positive-definite
    ``a`` [n, n] (only the lower triangle of ``a`` is read). The upper triangle of the
    result is zero. Column ``j`` is ``(a[:, j] - L @ L[j]) / L[j, j]`` below the diagonal,
    computed with the columns left of ``j`` only (the others are still zero)."""
    n = a.shape[-1]
    idx = jnp.arange(n)

    def col(j, l):
        v = a[:, j] - l @ l[j]
        d = jnp.sqrt(v[j])
        c = jnp.where(idx > j, v / d, jnp.where(idx == j, d, 0.0))
        return l.at[:, j].set(c.astype(l.dtype))

    return jax.lax.fori_loop(0, n, col, jnp.zeros_like(a))


def solve_lower(l: jax.Array, b: jax.Array) -> jax.Array:
    """``x`` with ``l @ x == b`` for lower-triangular ``l`` [n, n] and ``b`` [n] or [n, k]."""
    n = l.shape[-1]

    def row(i, x):
        xi = (b[i] - l[i] @ x) / l[i, i]  # x[i:] is still zero
        return x.at[i].set(xi)

    return jax.lax.fori_loop(0, n, row, jnp.zeros_like(b))


def solve_upper(u: jax.Array, b: jax.Array) -> jax.Array:
    """``x`` with ``u @ x == b`` for upper-triangular ``u`` [n, n] and ``b`` [n] or [n, k]."""
    n = u.shape[-1]

    def row(k, x):
        i = n - 1 - k
        xi = (b[i] - u[i] @ x) / u[i, i]  # x[:i + 1] is still zero
        return x.at[i].set(xi)

    return jax.lax.fori_loop(0, n, row, jnp.zeros_like(b))


def cho_factor(a, lower: bool = False, overwrite_a: bool = False, check_finite: bool = True):
    """Drop-in for ``jax.scipy.linalg.cho_factor``: ``(c, lower)`` with ``c`` the lower
    (``lower=True``) or upper factor; the other triangle is zero."""
    del overwrite_a, check_finite
    a = jnp.asarray(a)
    if a.ndim != 2:  # batched calls come through vmap; a stacked one would be a new use
        return _ORIG["cho_factor"](a, lower=lower)
    l = cholesky_lower(a)
    return (l if lower else l.T), lower


def cho_solve(c_and_lower, b, overwrite_b: bool = False, check_finite: bool = True):
    """Drop-in for ``jax.scipy.linalg.cho_solve`` with a factor from :func:`cho_factor`
    (or any ``(c, lower)`` whose other triangle is ignored)."""
    del overwrite_b, check_finite
    c, lower = c_and_lower
    c = jnp.asarray(c)
    b = jnp.asarray(b)
    if c.ndim != 2:
        return _ORIG["cho_solve"]((c, lower), b)
    l = jnp.tril(c) if lower else jnp.triu(c).T
    return solve_upper(l.T, solve_lower(l, b))


_ORIG = {"cho_factor": jsl.cho_factor, "cho_solve": jsl.cho_solve}
_LOCK = threading.RLock()
_DEPTH = 0


@contextlib.contextmanager
def jax_cholesky():
    """Within the block, ``jax.scipy.linalg.cho_factor`` / ``cho_solve`` are the JAX
    versions above (so MJX functions traced inside use them). Re-entrant; the originals
    come back when the outermost block exits. Two threads using the block take turns (a
    lock); a trace in another thread that does not use it, running at the same moment,
    would see the swap as well."""
    global _DEPTH
    with _LOCK:
        if _DEPTH == 0:
            jsl.cho_factor, jsl.cho_solve = cho_factor, cho_solve
        _DEPTH += 1
        try:
            yield
        finally:
            _DEPTH -= 1
            if _DEPTH == 0:
                jsl.cho_factor, jsl.cho_solve = _ORIG["cho_factor"], _ORIG["cho_solve"]
