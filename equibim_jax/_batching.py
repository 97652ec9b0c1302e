"""Chunked vmap: ``vmap`` over sub-batches inside a ``lax.scan``.

Why: on a 2-core CPU, jaxlib 0.10.2's batched LAPACK Cholesky (``lapack_spotrf_ffi``, used by
every ``mjx.step`` to factor the mass matrix) splits large batches across the intra-op
thread pool with ``ParallelBatchMap`` and deadlocks there (0 % CPU, forever) once the
batch reaches 64 envs; at 32 it runs. Mapping chunks of at most ``MAX_CPU_CHUNK`` envs
sidesteps that, costs nothing measurable on CPU (throughput is flat in batch size there),
and on a GPU the chunk can be the whole batch.
"""

from __future__ import annotations

from typing import Callable

import jax

MAX_CPU_CHUNK = 32


def default_chunk() -> int | None:
    """``MAX_CPU_CHUNK`` on the CPU backend, ``None`` (plain vmap) elsewhere."""
    return MAX_CPU_CHUNK if jax.default_backend() == "cpu" else None


def chunked_vmap(f: Callable, chunk: int | None | str = "auto", in_axes=0) -> Callable:
    """Like ``jax.vmap(f, in_axes)`` but over sub-batches of at most ``chunk`` elements.

    The batch size B must be a multiple of ``chunk`` when it exceeds it. ``in_axes`` is
    0 or None per positional argument (None arguments are broadcast). ``chunk="auto"`` uses
    :func:`default_chunk`.
    """
    vf = jax.vmap(f, in_axes=in_axes)
    if chunk == "auto":
        chunk = default_chunk()

    def g(*args):
        axes = in_axes if isinstance(in_axes, (tuple, list)) else (in_axes,) * len(args)
        mapped = [a for a, ax in zip(args, axes) if ax is not None]
        b = jax.tree.leaves(mapped)[0].shape[0]
        if chunk is None or b <= chunk:
            return vf(*args)
        if b % chunk:
            raise ValueError(f"batch {b} is not a multiple of the vmap chunk {chunk}")
        n = b // chunk
        split = [
            jax.tree.map(lambda x: x.reshape((n, chunk) + x.shape[1:]), a) if ax is not None else None
            for a, ax in zip(args, axes)
        ]

        def body(carry, xs):
            it = iter(xs)
            call = [next(it) if ax is not None else a for a, ax in zip(args, axes)]
            return carry, vf(*call)

        _, ys = jax.lax.scan(body, None, [s for s, ax in zip(split, axes) if ax is not None])
        return jax.tree.map(lambda y: y.reshape((b,) + y.shape[2:]), ys)

    return g
