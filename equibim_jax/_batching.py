"""Chunked vmap: ``vmap`` over sub-batches inside a ``lax.scan``.

A plain ``vmap`` of the whole batch is the default everywhere (``chunk="auto"`` maps to
``None``). Chunking bounds the memory of very large batches (each chunk's intermediates are
live at once, not the whole batch's) at no cost in throughput on the CPU.

History: jaxlib 0.10.2's *batched* LAPACK Cholesky (``lapack_spotrf_ffi``) deadlocks on a
2-core CPU once a vmapped ``mjx.step`` reaches 64 envs, and chunks of 32 used to be the
CPU default for that reason. :class:`~equibim_jax.sim.env.Env` now traces MJX with a
Cholesky written in JAX (``equibim_jax/sim/_linalg.py``), so no LAPACK call is left in a
step and any batch runs as one ``vmap``.
"""

from __future__ import annotations

from typing import Callable

import jax

def default_chunk() -> int | None:
    """The chunk ``chunk="auto"`` stands for: ``None``, a plain ``vmap`` of the batch."""
    return None


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
