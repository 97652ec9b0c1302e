"""Data parallelism over every visible device with ``jax.sharding``.

One 1-D :class:`~jax.sharding.Mesh` over ``jax.devices()`` with the axis ``"data"``:
batches (training windows, evaluation and demo-generation episodes) are split along
their leading axis over it, and parameters, optimiser state and the training dataset are
replicated. The programs stay ordinary ``jit`` functions of sharded inputs: XLA inserts
the collectives, so the gradient of a batch-mean loss is averaged over devices by the
compiler.

On one device every helper here returns its input unchanged and adds nothing to a traced
program, so single-device runs compile and compute exactly what they did without it.

A batch whose leading size is not a multiple of the device count is refused with a
``ValueError`` (:func:`check_divisible`); callers that can pad (evaluation, demo
generation) round their batch up with :func:`round_up` instead.

Multi-host runs call ``jax.distributed.initialize()`` first (``equibim_jax.cli.main`` does
it when :func:`distributed_requested`); ``jax.devices()`` then lists the devices of every
process and the same mesh spans the hosts. ``docs/scaling.md`` gives the commands.
"""

from __future__ import annotations

import functools
import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

__all__ = [
    "DATA_AXIS",
    "data_mesh",
    "is_trivial",
    "mesh_shape",
    "batch_sharding",
    "replicated_sharding",
    "check_divisible",
    "round_up",
    "shard_batch",
    "replicate",
    "constrain_batch",
    "constrain_replicated",
    "distributed_requested",
    "distributed_args",
    "maybe_initialize_distributed",
    "cpu_devices_requested",
    "maybe_use_cpu_cores",
    "train_mesh",
    "is_main_process",
    "to_host",
]

DATA_AXIS = "data"


@functools.lru_cache(maxsize=None)
def _mesh_of(devices: tuple) -> Mesh:
    return Mesh(np.asarray(devices, dtype=object), (DATA_AXIS,))


def data_mesh(devices: Any = None) -> Mesh:
    """The 1-D data mesh, axis ``"data"`` of size ``len(devices)``.

    Args:
      devices: the devices to span (default ``jax.devices()``: every device of every
        process).
    Returns:
      the mesh (the same object for the same devices, so jit caches keyed on shardings
      are reused).
    """
    return _mesh_of(tuple(jax.devices() if devices is None else devices))


def train_mesh() -> Mesh:
    """The mesh training shards its batch over: :func:`data_mesh`, except when
    :func:`maybe_use_cpu_cores` split this host's CPU into devices, where it is the first
    device alone. The train step is mostly matrix products, which XLA:CPU already runs on
    every core from one device; split over CPU devices, each half-batch step loses that
    and adds a gradient all-reduce (the demo's training ran about half as fast)."""
    if _CPU_SPLIT["n"] and jax.default_backend() == "cpu":
        return data_mesh(jax.local_devices()[:1])
    return data_mesh()


def is_trivial(mesh: Mesh | None) -> bool:
    """Whether ``mesh`` spans at most one device (then sharding is a no-op)."""
    return mesh is None or mesh.size <= 1


def mesh_shape(mesh: Mesh | None = None) -> dict[str, int]:
    """``{axis name: size}`` of ``mesh`` (default :func:`data_mesh`), e.g. ``{"data": 2}``."""
    mesh = data_mesh() if mesh is None else mesh
    return {str(k): int(v) for k, v in mesh.shape.items()}


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split over ``"data"``, the other axes whole: ``P("data")``."""
    return NamedSharding(mesh, P(DATA_AXIS))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
    """A full copy on every device of ``mesh``: ``P()``."""
    return NamedSharding(mesh, P())


def check_divisible(batch_size: int, mesh: Mesh | None, what: str = "batch size") -> None:
    """Raise ``ValueError`` unless ``batch_size`` is a multiple of the mesh's device count."""
    n = 1 if mesh is None else mesh.size
    if batch_size % n:
        raise ValueError(
            f"{what} {batch_size} is not divisible by the device count {n}: data parallelism "
            f"splits the batch evenly over the devices; use a multiple of {n}, or make fewer "
            f"devices visible (e.g. CUDA_VISIBLE_DEVICES)")


def round_up(n: int, mesh: Mesh | None) -> int:
    """The smallest multiple of the mesh's device count that is ``>= n``."""
    d = 1 if mesh is None else mesh.size
    return -(-int(n) // d) * d


def _leading(tree: Any) -> int:
    leaves = jax.tree.leaves(tree)
    if not leaves or any(np.ndim(x) == 0 for x in leaves):
        raise ValueError("shard_batch needs a non-empty tree of arrays with a leading batch axis")
    sizes = {int(np.shape(x)[0]) for x in leaves}
    if len(sizes) != 1:
        raise ValueError(f"shard_batch: the leaves' leading (batch) sizes differ: {sorted(sizes)}")
    return sizes.pop()


def _put(tree: Any, sharding: NamedSharding) -> Any:
    """``jax.device_put(tree, sharding)``, with typed PRNG keys put as their raw key data:
    in a multi-process run ``device_put`` takes host-local arrays to a sharding over
    other processes' devices, but not key arrays."""

    def put(x):
        if isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return jax.random.wrap_key_data(jax.device_put(jax.random.key_data(x), sharding),
                                            impl=jax.random.key_impl(x))
        return jax.device_put(x, sharding)

    return jax.tree.map(put, tree)


def shard_batch(tree: Any, mesh: Mesh | None) -> Any:
    """Put a batch on the mesh, split along its leading axis.

    Args:
      tree: a pytree of arrays ``[B, ...]`` (host or device; typed PRNG keys included),
        the same ``B`` for all leaves.
      mesh: the data mesh; ``None`` or one device: ``tree`` is returned unchanged.
    Returns:
      the tree with every leaf a ``[B, ...]`` array sharded ``P("data")``: device ``i``
      holds rows ``i * B / n .. (i + 1) * B / n - 1``.
    Raises:
      ValueError: ``B`` is not a multiple of the device count ``n``.
    """
    if is_trivial(mesh):
        return tree
    check_divisible(_leading(tree), mesh)
    return _put(tree, batch_sharding(mesh))


def replicate(tree: Any, mesh: Mesh | None) -> Any:
    """A full copy of every array leaf of ``tree`` (any shapes) on each device of ``mesh``
    (``P()``); unchanged for ``None`` or one device. Static pytree fields stay as they are."""
    if is_trivial(mesh):
        return tree
    return _put(tree, replicated_sharding(mesh))


def constrain_batch(tree: Any, mesh: Mesh | None) -> Any:
    """Inside ``jit``: ask XLA to keep ``tree``'s leaves (``[B, ...]``) split along the
    leading axis over ``"data"``. Identity for ``None`` or one device (no op is traced)."""
    if is_trivial(mesh):
        return tree
    return jax.lax.with_sharding_constraint(tree, batch_sharding(mesh))


def constrain_replicated(tree: Any, mesh: Mesh | None) -> Any:
    """Inside ``jit``: ask XLA to keep every leaf of ``tree`` whole on each device.
    Identity for ``None`` or one device (no op is traced)."""
    if is_trivial(mesh):
        return tree
    return jax.lax.with_sharding_constraint(tree, replicated_sharding(mesh))


_DISTRIBUTED_ENV = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")


def distributed_requested(environ: Any = None) -> bool:
    """Whether the environment asks for a multi-process run: ``EQUIBIM_JAX_DISTRIBUTED=1``
    (arguments auto-detected on SLURM, Open MPI or Cloud TPU) or ``JAX_COORDINATOR_ADDRESS``
    set (with ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``)."""
    env = os.environ if environ is None else environ
    flag = env.get("EQUIBIM_JAX_DISTRIBUTED", "").strip().lower()
    return flag in ("1", "true", "yes", "on") or bool(env.get("JAX_COORDINATOR_ADDRESS"))


def distributed_args(environ: Any = None) -> dict[str, Any]:
    """Keyword arguments of ``jax.distributed.initialize`` from the environment.

    ``jax.distributed.initialize`` reads ``JAX_COORDINATOR_ADDRESS`` itself but not the
    process count and index, so ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` are passed
    as ``num_processes`` and ``process_id`` when set; anything unset is left to JAX's
    cluster detection.

    Raises:
      ValueError: one of them is set but not an integer.
    """
    env = os.environ if environ is None else environ
    args: dict[str, Any] = {}
    for var, name in (("JAX_NUM_PROCESSES", "num_processes"), ("JAX_PROCESS_ID", "process_id")):
        raw = env.get(var, "").strip()
        if raw:
            try:
                args[name] = int(raw)
            except ValueError:
                raise ValueError(f"{var} must be an integer, got {raw!r}") from None
    return args


def maybe_initialize_distributed() -> bool:
    """Call ``jax.distributed.initialize(**distributed_args())`` if
    :func:`distributed_requested`; it must run before anything touches a JAX backend.
    Returns whether it was called (not when already initialised)."""
    if not distributed_requested() or jax.distributed.is_initialized():
        return False
    jax.distributed.initialize(**distributed_args())
    return True


CPU_DEVICES_FLAG = "--xla_force_host_platform_device_count"
_CPU_SPLIT = {"n": 0}  # devices maybe_use_cpu_cores asked for in this process (0: none)


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def cpu_devices_requested(environ: Any = None) -> int:
    """CPU devices asked for by ``EQUIBIM_JAX_CPU_DEVICES``: ``auto`` (the default) is the
    largest power of two not above the usable cores, capped at 8 (so that the usual batch
    sizes, 32 or 64, divide evenly); an integer N is N; ``0``, ``1`` or ``off`` is XLA's
    default (one CPU device).

    Raises:
      ValueError: a value that is none of these.
    """
    env = os.environ if environ is None else environ
    raw = env.get("EQUIBIM_JAX_CPU_DEVICES", "auto").strip().lower()
    if raw in ("", "auto"):
        n = min(_usable_cores(), 8)
        return 1 << (n.bit_length() - 1)
    if raw in ("off", "no", "false"):
        return 1
    try:
        n = int(raw)
    except ValueError:
        raise ValueError(f"EQUIBIM_JAX_CPU_DEVICES must be 'auto', 'off' or an integer, got {raw!r}") from None
    if n < 0:
        raise ValueError(f"EQUIBIM_JAX_CPU_DEVICES must be >= 0, got {n}")
    return max(n, 1)


def maybe_use_cpu_cores(environ: Any = None) -> int:
    """Ask XLA for :func:`cpu_devices_requested` CPU devices, before any backend starts.

    XLA:CPU runs one device's program on one thread (matrix products aside), so batched
    physics and rendering use one core however large the batch; with one CPU device per
    core the data mesh (:func:`data_mesh`) splits each batch over the cores (training keeps
    one device: :func:`train_mesh`). It adds
    ``--xla_force_host_platform_device_count=N`` to ``XLA_FLAGS`` and returns N, or leaves
    everything as it is and returns 0 when: N is 1, ``XLA_FLAGS`` already sets the count,
    a JAX backend has already started (the flag would be ignored), or a multi-process run
    is requested (:func:`distributed_requested`). On a GPU host the flag only adds CPU
    devices; the default backend, and so the mesh, stays the GPU.
    """
    env = os.environ if environ is None else environ
    n = cpu_devices_requested(env)
    flags = env.get("XLA_FLAGS", "")
    if n <= 1 or CPU_DEVICES_FLAG in flags or distributed_requested(env):
        return 0
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        return 0
    env["XLA_FLAGS"] = f"{flags} {CPU_DEVICES_FLAG}={n}".strip()
    if environ is None:
        _CPU_SPLIT["n"] = n
    return n


def is_main_process() -> bool:
    """Whether this is process 0 (the one that writes files and shows progress bars)."""
    return jax.process_index() == 0


def to_host(tree: Any) -> Any:
    """The leaves of ``tree`` as whole host ``numpy`` arrays, in every process.

    Arrays sharded over the devices of several processes are gathered
    (``multihost_utils.process_allgather``); in one process this is ``jax.device_get``.
    """
    if jax.process_count() == 1:
        return jax.device_get(tree)
    from jax.experimental import multihost_utils

    return multihost_utils.process_allgather(tree, tiled=True)
