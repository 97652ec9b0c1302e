"""TrainConfig, TrainState, and the jitted train step / K-step loop of any policy.

``train_step(state, key) -> (state, metrics)`` is pure and compiled once. The key is a
*base* key: each step derives its randomness as ``fold_in(key, state.step)``, so calling
with the same key every step gives a fresh stream per step, and resuming from a
checkpoint (which stores ``step``) continues the same stream exactly.

The dataset (``equibim_jax.data.windows.OnDeviceDataset``) is passed to the jitted
function as an argument, not captured as a constant, which would bake it into the
compiled program.

Data parallelism: :func:`make_train_step` and :func:`make_train_loop` run on the data mesh
of every visible device (``equibim_jax._sharding``). The state, key and dataset are
replicated, each step's sampled batch is split along its batch axis, and XLA averages the
gradient over devices. On one device nothing changes.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from equibim_jax._sharding import check_divisible, constrain_batch, constrain_replicated, replicate, train_mesh
from equibim_jax._xla_options import train_compiler_options
from equibim_jax.data.windows import OnDeviceDataset, sample_batch
from equibim_jax.policies.base import Policy
from equibim_jax.training.ema import EmaConfig, ema_decay, ema_update
from equibim_jax.training.losses import SYM_NORMS, policy_loss

Array = Any

__all__ = [
    "TrainConfig",
    "TrainState",
    "make_optimizer",
    "create_train_state",
    "build_step_fn",
    "sym_ramp",
    "make_train_step",
    "make_train_loop",
    "make_joint_train_loop",
    "base_key",
    "BoundTrainFn",
]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation and loss settings of one training run (frozen, hashable).

    Attributes:
      batch_size: ``B``, samples per step.
      learning_rate: peak AdamW learning rate.
      weight_decay, b1, b2, adam_eps: AdamW settings (Diffusion Policy's).
      warmup_steps: linear warmup from 0 (at most ``total_steps - 1``); then cosine decay to 0
        at ``total_steps``.
      total_steps: length of the run and of the schedule; a multiple of
        ``steps_per_dispatch``.
      grad_clip: global-norm clip, or ``None``.
      sym_weight: ``lambda`` of ``L_sym`` (0: plain BC, no mirrored branch).
      sym_stop_gradient: treat ``S pi(O)`` as a fixed target in ``L_sym``.
      sym_norm: form of ``L_sym``: ``"mse"``, ``"rms"`` or ``"l2"`` (exact formulas in
        :mod:`equibim_jax.training.losses`). ``"mse"`` with ``sym_stop_gradient`` and
        ``sym_weight = 0.1`` is the paper's public code's form; ``"l2"`` the paper's
        written one.
      sym_warmup_steps: ``lambda`` ramps linearly from 0 to ``sym_weight`` over this many
        steps (0: constant).
      sym_start_step: ``lambda`` is 0 before this step (the mirrored branch still runs),
        then ramps as ``sym_warmup_steps`` says.
      sym_batch_size: samples per step that also go through the mirrored branch (``L_sym``
        is their mean); ``None``: all ``batch_size``.
      mirror_augment: also fit the mirrored samples by BC (mirror data augmentation).
      steps_per_dispatch: ``K`` steps per ``lax.scan`` dispatch in :func:`make_train_loop`.
      seed: seed of parameter init and of the base training key.
      ema: :class:`~equibim_jax.training.ema.EmaConfig`.
    """

    batch_size: int = 64
    learning_rate: float = 3e-3
    weight_decay: float = 1e-6
    b1: float = 0.95
    b2: float = 0.999
    adam_eps: float = 1e-8
    warmup_steps: int = 50
    total_steps: int = 1000
    grad_clip: float | None = None
    sym_weight: float = 0.1
    sym_stop_gradient: bool = True
    sym_norm: str = "rms"
    sym_warmup_steps: int = 0
    sym_start_step: int = 0
    sym_batch_size: int | None = None
    mirror_augment: bool = False
    steps_per_dispatch: int = 50
    seed: int = 0
    ema: EmaConfig = EmaConfig()

    def __post_init__(self):
        if self.batch_size < 1:
            raise ValueError(f"TrainConfig.batch_size must be >= 1, got {self.batch_size}")
        if not self.learning_rate > 0:
            raise ValueError(f"TrainConfig.learning_rate must be > 0, got {self.learning_rate}")
        if self.weight_decay < 0:
            raise ValueError(f"TrainConfig.weight_decay must be >= 0, got {self.weight_decay}")
        if not (0 <= self.b1 < 1 and 0 <= self.b2 < 1):
            raise ValueError(f"TrainConfig: b1, b2 must be in [0, 1), got {self.b1}, {self.b2}")
        if self.total_steps < 1 or self.warmup_steps < 0 or self.sym_warmup_steps < 0:
            raise ValueError(
                f"TrainConfig: need total_steps >= 1 and warmup_steps, sym_warmup_steps >= 0, got "
                f"total_steps={self.total_steps}, warmup_steps={self.warmup_steps}, "
                f"sym_warmup_steps={self.sym_warmup_steps}"
            )
        if self.steps_per_dispatch < 1 or self.total_steps % self.steps_per_dispatch:
            raise ValueError(
                f"TrainConfig: total_steps ({self.total_steps}) must be a positive multiple of "
                f"steps_per_dispatch ({self.steps_per_dispatch})"
            )
        if self.grad_clip is not None and not self.grad_clip > 0:
            raise ValueError(f"TrainConfig.grad_clip must be > 0 or None, got {self.grad_clip}")
        if self.sym_weight < 0:
            raise ValueError(f"TrainConfig.sym_weight (lambda) must be >= 0, got {self.sym_weight}")
        if self.sym_norm not in SYM_NORMS:
            raise ValueError(f"TrainConfig.sym_norm must be one of {SYM_NORMS}, got {self.sym_norm!r}")
        if not 0 <= self.sym_start_step < self.total_steps:
            raise ValueError(f"TrainConfig: need 0 <= sym_start_step < total_steps, got "
                             f"sym_start_step={self.sym_start_step}, total_steps={self.total_steps}")
        if self.sym_batch_size is not None and not 1 <= self.sym_batch_size <= self.batch_size:
            raise ValueError(
                f"TrainConfig.sym_batch_size must be None or in [1, batch_size={self.batch_size}], "
                f"got {self.sym_batch_size}"
            )

    @property
    def uses_mirror(self) -> bool:
        """Whether the step runs the mirrored branch."""
        return self.sym_weight > 0 or self.mirror_augment


@flax.struct.dataclass
class TrainState:
    """Everything that changes during training; a pytree.

    Attributes:
      step: int32 scalar, optimisation steps taken.
      params, ema_params: policy parameters and their EMA (same tree).
      opt_state: optax state.
      policy: the :class:`~equibim_jax.policies.Policy` (static).
      tx: the optax transformation (static).
    """

    step: Array
    params: Any
    ema_params: Any
    opt_state: Any
    policy: Policy = flax.struct.field(pytree_node=False)
    tx: optax.GradientTransformation = flax.struct.field(pytree_node=False)


@functools.lru_cache(maxsize=32)
def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """AdamW with linear warmup and cosine decay to 0 (optionally global-norm clipping).

    Memoised on the (hashable) config: optax transformations are tuples of fresh
    closures, and returning the same object for equal configs keeps a restored
    :class:`TrainState` (``tx`` is a static field) on the same compiled step.
    """
    lr = optax.warmup_cosine_decay_schedule(
        init_value=0.0,
        peak_value=config.learning_rate,
        warmup_steps=min(config.warmup_steps, config.total_steps - 1),  # optax needs decay > warmup
        decay_steps=config.total_steps,
        end_value=0.0,
    )
    adamw = optax.adamw(
        lr, b1=config.b1, b2=config.b2, eps=config.adam_eps, weight_decay=config.weight_decay
    )
    if config.grad_clip is None:
        return adamw
    return optax.chain(optax.clip_by_global_norm(config.grad_clip), adamw)


def create_train_state(policy: Policy, train_config: TrainConfig) -> TrainState:
    """Initialise parameters (from ``train_config.seed``), optimiser and EMA.

    Returns:
      a fresh :class:`TrainState` at step 0.
    """
    params = policy.init(jax.random.key(train_config.seed))
    tx = make_optimizer(train_config)
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        ema_params=jax.tree.map(jnp.copy, params),
        opt_state=tx.init(params),
        policy=policy,
        tx=tx,
    )


def base_key(train_config: TrainConfig) -> Array:
    """The base training key derived from ``seed`` (distinct from the init key)."""
    return jax.random.fold_in(jax.random.key(train_config.seed), 1)


def sym_ramp(step: Array, warmup_steps: int, start_step: int = 0) -> Array:
    """The fraction of ``lambda`` at ``step``: 0 before ``start_step``, then
    ``min(1, (step - start_step + 1) / warmup_steps)`` (1 from ``start_step`` on for
    ``warmup_steps == 0``)."""
    s = step.astype(jnp.float32) - start_step
    r = jnp.ones((), jnp.float32) if warmup_steps <= 0 else jnp.minimum(1.0, (s + 1.0) / warmup_steps)
    return jnp.where(s >= 0, r, 0.0).astype(jnp.float32)


def build_step_fn(
    train_config: TrainConfig,
    symmetry: Any = None,
    sampler: Callable[[Any, Array, int], dict[str, Array]] = sample_batch,
    mesh: Any = None,
) -> Callable[[TrainState, Array, Any], tuple[TrainState, dict[str, Array]]]:
    """The raw (un-jitted) pure step ``(state, key, dataset) -> (state, metrics)``.

    Use it to compose larger jitted programs; otherwise prefer :func:`make_train_step` /
    :func:`make_train_loop`. The policy is the state's (``state.policy``).

    Args:
      train_config: settings.
      symmetry: normalised-space ``S`` (``{field: op}``; see
        ``equibim_jax.data.normalized_symmetry``); required if the mirrored branch runs.
      sampler: ``(dataset, key, batch_size) -> batch`` drawing the training windows
        (default: :func:`~equibim_jax.data.windows.sample_batch` of an
        :class:`OnDeviceDataset`; the online loop passes its ring buffer's).
      mesh: a data mesh (``equibim_jax._sharding.data_mesh``): the sampled batch
        ``[B, ...]`` is split over its ``"data"`` axis and the new state and metrics kept
        replicated. ``None`` (the default) or one device: no sharding.
    Returns:
      the step; ``metrics`` holds scalars ``bc, sym, total, grad_norm, ema_decay,
      sym_weight`` (the ``lambda`` in effect at that step).
    """
    if train_config.uses_mirror and symmetry is None:
        raise ValueError("sym_weight > 0 or mirror_augment needs a symmetry")
    check_divisible(train_config.batch_size, mesh, "TrainConfig.batch_size")
    tc = train_config

    def step_fn(state: TrainState, key: Array, dataset: OnDeviceDataset):
        k_batch, k_loss = jax.random.split(jax.random.fold_in(key, state.step))
        batch = constrain_batch(sampler(dataset, k_batch, tc.batch_size), mesh)
        sym_scale = sym_ramp(state.step, min(tc.sym_warmup_steps, tc.total_steps), tc.sym_start_step)

        def loss_fn(params):
            return policy_loss(state.policy, params, batch, k_loss, symmetry,
                               sym_weight=tc.sym_weight, sym_scale=sym_scale,
                               stop_gradient=tc.sym_stop_gradient, norm=tc.sym_norm,
                               sym_batch=tc.sym_batch_size, mirror_augment=tc.mirror_augment)

        (_, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        updates, opt_state = state.tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        decay = ema_decay(state.step, tc.ema)
        new_state = state.replace(
            step=state.step + 1,
            params=params,
            ema_params=ema_update(state.ema_params, params, decay),
            opt_state=opt_state,
        )
        metrics = dict(terms, grad_norm=optax.tree.norm(grads), ema_decay=decay,
                       sym_weight=sym_scale * tc.sym_weight)
        return constrain_replicated((new_state, metrics), mesh)

    return step_fn


@dataclasses.dataclass(frozen=True, eq=False)
class BoundTrainFn:
    """A jitted ``fn(state, key, dataset)`` with its dataset bound: ``f(state, key)``.

    Attributes:
      fn: the jitted function (its own cache; compiled on first call).
      dataset: the on-device dataset passed to ``fn`` as an argument (replicated on
        ``mesh``).
      mesh: the data mesh the step runs on; the state and key are replicated on it before
        each call (a no-op once they are, and for ``None`` or one device).
    """

    fn: Callable
    dataset: OnDeviceDataset
    mesh: Any = None

    def __call__(self, state: TrainState, key: Array):
        """``(state, key) -> (state, metrics)``."""
        return self.fn(*replicate((state, key), self.mesh), self.dataset)

    def lower(self, state: TrainState, key: Array):
        """Ahead-of-time lowering (``.compile()`` it; call the result with
        ``(state, key, dataset)``), e.g. to time compilation or read ``cost_analysis()``."""
        return self.fn.lower(*replicate((state, key), self.mesh), self.dataset)


def make_train_step(train_config: TrainConfig, dataset: OnDeviceDataset,
                    symmetry: Any = None) -> BoundTrainFn:
    """A jitted single step ``train_step(state, key) -> (state, metrics)``, data-parallel
    over every visible device (module docstring).

    Args:
      dataset: on-device normalised data (passed to the jitted function as an argument).
      symmetry: normalised-space ``S``.
    Returns:
      the step; ``metrics`` are scalars ``{bc, sym, total, grad_norm, ema_decay, sym_weight}``.
    Raises:
      ValueError: ``batch_size`` is not a multiple of the device count.
    """
    mesh = train_mesh()
    step = build_step_fn(train_config, symmetry, mesh=mesh)
    return BoundTrainFn(jax.jit(step, compiler_options=train_compiler_options()),
                        replicate(dataset, mesh), mesh)


def make_train_loop(train_config: TrainConfig, dataset: OnDeviceDataset, symmetry: Any = None,
                    num_steps: int | None = None) -> BoundTrainFn:
    """A jitted ``train_k_steps(state, key) -> (state, metrics)`` running K steps in a scan,
    data-parallel over every visible device (module docstring).

    Args:
      num_steps: ``K``; defaults to ``train_config.steps_per_dispatch``.
    Returns:
      the loop; each metric is ``[K]``.
    Raises:
      ValueError: ``batch_size`` is not a multiple of the device count.
    """
    k_steps = train_config.steps_per_dispatch if num_steps is None else num_steps
    mesh = train_mesh()
    step_fn = build_step_fn(train_config, symmetry, mesh=mesh)

    @functools.partial(jax.jit, compiler_options=train_compiler_options())
    def loop(state, key, data):
        def body(s, _):
            return step_fn(s, key, data)

        return jax.lax.scan(body, state, None, length=k_steps)

    return BoundTrainFn(loop, replicate(dataset, mesh), mesh)


def make_joint_train_loop(train_configs: tuple[TrainConfig, ...], dataset: OnDeviceDataset,
                          symmetries: tuple[Any, ...], num_steps: int | None = None) -> BoundTrainFn:
    """Several runs on one dataset, K steps each, in one jitted program:
    ``loop(states, keys) -> (states, metrics)`` with ``states``, ``keys`` and ``metrics``
    tuples in the order of ``train_configs`` (each metric ``[K]``).

    Each run takes the steps :func:`make_train_loop` would give it (its own config, state,
    base key and symmetry), up to float rounding; only the program is shared. It compiles
    once instead of once per run, and XLA overlaps the runs' independent operations
    (``benchmarks/joint_train.py`` compares it with separate loops). The runs may differ
    in anything but their length per dispatch.

    Args:
      train_configs: one config per run.
      dataset: the on-device data every run samples from.
      symmetries: one normalised-space ``S`` (or ``None``) per run.
      num_steps: ``K``; defaults to the first config's ``steps_per_dispatch``.
    Raises:
      ValueError: empty or mismatched ``train_configs`` / ``symmetries``.
    """
    if not train_configs or len(train_configs) != len(symmetries):
        raise ValueError(f"need one symmetry per train config, got {len(train_configs)} configs "
                         f"and {len(symmetries)} symmetries")
    k_steps = train_configs[0].steps_per_dispatch if num_steps is None else num_steps
    mesh = train_mesh()
    step_fns = tuple(build_step_fn(tc, sym, mesh=mesh) for tc, sym in zip(train_configs, symmetries))

    @functools.partial(jax.jit, compiler_options=train_compiler_options())
    def loop(states, keys, data):
        def body(ss, _):
            outs = tuple(f(s, k, data) for f, s, k in zip(step_fns, ss, keys))
            return tuple(o[0] for o in outs), tuple(o[1] for o in outs)

        return jax.lax.scan(body, tuple(states), None, length=k_steps)

    return BoundTrainFn(loop, replicate(dataset, mesh), mesh)
