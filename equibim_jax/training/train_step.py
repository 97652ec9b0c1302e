"""TrainState, the on-device dataset, and the jitted train step / K-step loop.

``train_step(state, key) -> (state, metrics)`` is pure and compiled once. The key is a
*base* key: each step derives its randomness as ``fold_in(key, state.step)``, so calling
with the same key every step gives a fresh stream per step, and resuming from a
checkpoint (which stores ``step``) continues the same stream exactly.

The dataset stays on device as per-frame arrays plus index tables of windows, and is
passed to the jitted function as an argument (not captured as a constant, which would
bake it into the compiled program).
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

from equibim_jax._xla_options import train_compiler_options
from equibim_jax.policies.diffusion import (
    DiffusionSchedule,
    EmaConfig,
    PolicyApplyFn,
    PolicyConfig,
    ema_decay,
    ema_update,
    init_params,
    make_schedule,
)
from equibim_jax.training.losses import SYM_NORMS, SYM_SPACES, diffusion_loss

Array = Any

__all__ = [
    "TrainConfig",
    "TrainState",
    "OnDeviceDataset",
    "window_indices",
    "make_dataset",
    "sample_batch",
    "make_optimizer",
    "create_train_state",
    "build_step_fn",
    "sym_ramp",
    "make_train_step",
    "make_train_loop",
    "base_key",
    "BoundTrainFn",
]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation and loss configuration.

    Attributes:
      batch_size: ``B``, samples per step (the mirrored branch doubles the network batch).
      learning_rate: peak AdamW learning rate.
      weight_decay, b1, b2, adam_eps: AdamW settings (Diffusion Policy's defaults).
      warmup_steps: linear warmup from 0; then cosine decay to 0 at ``total_steps``.
      total_steps: length of the schedule.
      grad_clip: global-norm clip, or ``None``.
      sym_weight: ``lambda`` of ``L_sym`` (0 = plain BC, no mirrored branch).
      sym_stop_gradient: stop gradients through the ``S_a eps(a_k, k, O)`` side of ``L_sym``.
      sym_norm: ``"mse"`` (squared, the default) or ``"l2"`` (the paper's unsquared
        per-sample norm) for ``L_sym``.
      sym_space: ``"eps"`` (the noise predictions) or ``"x0"`` (the clean actions they
        imply); see :func:`equibim_jax.training.losses.diffusion_loss`.
      sym_warmup_steps: ``lambda`` ramps linearly from 0 to ``sym_weight`` over this many
        steps (0: constant).
      sym_start_step: ``lambda`` is 0 before this step (plain BC; the mirrored branch still
        runs), then ramps as ``sym_warmup_steps`` says.
      sym_batch_size: samples per step that also go through the mirrored branch (``L_sym``
        is their mean); ``None``: all ``batch_size``. On the demo's network, 32 of 64 samples
        take 29 ms a step against 38 ms for all 64 and 21 ms for BC alone.
      mirror_augment: also train BC on the mirrored branch.
      steps_per_dispatch: ``K`` steps per ``lax.scan`` dispatch in :func:`make_train_loop`.
      seed: seed of parameter init and of the base training key.
      ema: :class:`EmaConfig`.
    """

    batch_size: int = 64
    learning_rate: float = 1e-4
    weight_decay: float = 1e-6
    b1: float = 0.95
    b2: float = 0.999
    adam_eps: float = 1e-8
    warmup_steps: int = 500
    total_steps: int = 100_000
    grad_clip: float | None = None
    sym_weight: float = 0.0
    sym_stop_gradient: bool = False
    sym_norm: str = "mse"
    sym_space: str = "eps"
    sym_warmup_steps: int = 0
    sym_start_step: int = 0
    sym_batch_size: int | None = None
    mirror_augment: bool = False
    steps_per_dispatch: int = 10
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
        if self.total_steps < 1 or not 0 <= self.warmup_steps <= self.total_steps:
            raise ValueError(
                f"TrainConfig: need total_steps >= 1 and 0 <= warmup_steps <= total_steps, "
                f"got warmup_steps={self.warmup_steps}, total_steps={self.total_steps}"
            )
        if self.grad_clip is not None and not self.grad_clip > 0:
            raise ValueError(f"TrainConfig.grad_clip must be > 0 or None, got {self.grad_clip}")
        if self.sym_weight < 0:
            raise ValueError(f"TrainConfig.sym_weight (lambda) must be >= 0, got {self.sym_weight}")
        if self.sym_space not in SYM_SPACES:
            raise ValueError(f"TrainConfig.sym_space must be one of {SYM_SPACES}, got {self.sym_space!r}")
        if self.sym_norm not in SYM_NORMS:
            raise ValueError(f"TrainConfig.sym_norm must be one of {SYM_NORMS}, got {self.sym_norm!r}")
        if not 0 <= self.sym_start_step < self.total_steps:
            raise ValueError(f"TrainConfig: need 0 <= sym_start_step < total_steps, got "
                             f"sym_start_step={self.sym_start_step}, total_steps={self.total_steps}")
        if not 0 <= self.sym_warmup_steps <= self.total_steps:
            raise ValueError(
                f"TrainConfig: need 0 <= sym_warmup_steps <= total_steps, got "
                f"sym_warmup_steps={self.sym_warmup_steps}, total_steps={self.total_steps}"
            )
        if self.sym_batch_size is not None and not 1 <= self.sym_batch_size <= self.batch_size:
            raise ValueError(
                f"TrainConfig.sym_batch_size must be None or in [1, batch_size={self.batch_size}], "
                f"got {self.sym_batch_size}"
            )
        if self.steps_per_dispatch < 1:
            raise ValueError(
                f"TrainConfig.steps_per_dispatch must be >= 1, got {self.steps_per_dispatch}"
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
      params, ema_params: network parameters and their EMA (same tree).
      opt_state: optax state.
      apply_fn: ``(params, [N, Tp, A], [N], obs) -> [N, Tp, A]`` (static).
      tx: the optax transformation (static).
    """

    step: Array
    params: Any
    ema_params: Any
    opt_state: Any
    apply_fn: Callable = flax.struct.field(pytree_node=False)
    tx: optax.GradientTransformation = flax.struct.field(pytree_node=False)


@flax.struct.dataclass
class OnDeviceDataset:
    """Normalised per-frame arrays plus window index tables.

    Attributes:
      frames: ``{field: [F, ...]}`` normalised arrays over all frames of all episodes.
      obs_index: ``[N, To]`` int32 frame indices of each window's observations.
      action_index: ``[N, Tp]`` int32 frame indices of each window's actions.
      obs_keys: observation fields to sample (static).
      action_key: action field (static).
    """

    frames: dict[str, Array]
    obs_index: Array
    action_index: Array
    obs_keys: tuple[str, ...] = flax.struct.field(pytree_node=False, default=())
    action_key: str = flax.struct.field(pytree_node=False, default="action")

    @property
    def num_windows(self) -> int:
        """``N``, the number of training windows."""
        return self.obs_index.shape[0]


def window_indices(
    episode_ends: Array,
    obs_horizon: int,
    pred_horizon: int,
    pad_before: int | None = None,
    pad_after: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame indices of all training windows, padded by repeating edge frames.

    As Diffusion Policy's sequence sampler: a window starting at ``t`` (possibly before the
    episode's first frame or running past its last) takes frames ``t .. t + Tp - 1``,
    clamped into the episode.

    Args:
      episode_ends: ``[E]`` exclusive end frame of each episode (cumulative lengths).
      obs_horizon: ``To``. pred_horizon: ``Tp``.
      pad_before: frames a window may start before an episode (default ``To - 1``).
      pad_after: frames a window may run past the episode's end (default 0;
        ``make_dataset`` passes ``Ta - 1``).
    Returns:
      ``(obs_index [N, To], action_index [N, Tp])`` int32.
    Raises:
      ValueError: for non-increasing ``episode_ends`` or if no window fits.
    """
    ends = np.asarray(episode_ends, np.int64)
    if ends.ndim != 1 or ends.size == 0 or np.any(np.diff(np.concatenate([[0], ends])) <= 0):
        raise ValueError(f"episode_ends must be strictly increasing positive ints, got {ends}")
    pad_before = obs_horizon - 1 if pad_before is None else pad_before
    pad_after = 0 if pad_after is None else pad_after
    obs_rows, act_rows = [], []
    start = 0
    for end in ends:
        for t in range(start - pad_before, end - pred_horizon + pad_after + 1):
            obs_rows.append(np.clip(t + np.arange(obs_horizon), start, end - 1))
            act_rows.append(np.clip(t + np.arange(pred_horizon), start, end - 1))
        start = end
    if not obs_rows:
        raise ValueError(
            f"no training window fits: episodes {np.diff(np.concatenate([[0], ends])).tolist()} "
            f"frames long, pred_horizon={pred_horizon}, pad_before={pad_before}, "
            f"pad_after={pad_after}"
        )
    return np.stack(obs_rows).astype(np.int32), np.stack(act_rows).astype(np.int32)


def make_dataset(
    frames: Mapping[str, Array], episode_ends: Array, config: PolicyConfig
) -> OnDeviceDataset:
    """Put normalised frames on device with windows as Diffusion Policy pads them.

    Args:
      frames: ``{field: [F, ...]}`` normalised frames; must hold the action field and
        the encoder's observation fields.
      episode_ends: ``[E]`` exclusive episode ends (``episode_ends[-1] == F``).
      config: policy config (horizons and field names).
    Returns:
      :class:`OnDeviceDataset` with ``pad_before = To - 1``, ``pad_after = Ta - 1``.
    """
    keys = config.encoder.keys
    missing = [k for k in keys + (config.action_key,) if k not in frames]
    if missing:
        raise KeyError(f"make_dataset: frames lack fields {missing}; have {list(frames)}")
    n_frames = {k: np.shape(frames[k])[0] for k in keys + (config.action_key,)}
    if len(set(n_frames.values())) != 1 or int(np.asarray(episode_ends)[-1]) != next(
        iter(n_frames.values())
    ):
        raise ValueError(
            f"make_dataset: frame counts {n_frames} must agree with episode_ends[-1]="
            f"{int(np.asarray(episode_ends)[-1])}"
        )
    obs_idx, act_idx = window_indices(
        episode_ends,
        config.obs_horizon,
        config.pred_horizon,
        pad_before=config.obs_horizon - 1,
        pad_after=config.action_horizon - 1,
    )
    return OnDeviceDataset(
        frames={k: jnp.asarray(frames[k], jnp.float32) for k in keys + (config.action_key,)},
        obs_index=jnp.asarray(obs_idx),
        action_index=jnp.asarray(act_idx),
        obs_keys=tuple(keys),
        action_key=config.action_key,
    )


def sample_batch(dataset: OnDeviceDataset, key: Array, batch_size: int) -> dict[str, Array]:
    """Draw ``batch_size`` windows uniformly with replacement, on device.

    Returns:
      ``{action_key: [B, Tp, A], obs field: [B, To, ...]}``.
    """
    idx = jax.random.randint(key, (batch_size,), 0, dataset.num_windows)
    batch = {k: dataset.frames[k][dataset.obs_index[idx]] for k in dataset.obs_keys}
    batch[dataset.action_key] = dataset.frames[dataset.action_key][dataset.action_index[idx]]
    return batch


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
        warmup_steps=config.warmup_steps,
        decay_steps=config.total_steps,
        end_value=0.0,
    )
    adamw = optax.adamw(
        lr, b1=config.b1, b2=config.b2, eps=config.adam_eps, weight_decay=config.weight_decay
    )
    if config.grad_clip is None:
        return adamw
    return optax.chain(optax.clip_by_global_norm(config.grad_clip), adamw)


def create_train_state(policy_config: PolicyConfig, train_config: TrainConfig):
    """Initialise parameters (from ``train_config.seed``), optimiser and EMA.

    Returns:
      ``(state, model)``: a fresh :class:`TrainState` at step 0 and the
      ``NoisePredictor`` module.
    """
    model, params = init_params(policy_config, jax.random.key(train_config.seed))
    tx = make_optimizer(train_config)
    state = TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        ema_params=jax.tree.map(jnp.copy, params),
        opt_state=tx.init(params),
        apply_fn=PolicyApplyFn(policy_config),
        tx=tx,
    )
    return state, model


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
    policy_config: PolicyConfig,
    train_config: TrainConfig,
    symmetry: Any = None,
    schedule: DiffusionSchedule | None = None,
) -> Callable[[TrainState, Array, OnDeviceDataset], tuple[TrainState, dict[str, Array]]]:
    """The raw (un-jitted) pure step ``(state, key, dataset) -> (state, metrics)``.

    Use it to compose larger jitted programs (e.g. online data generation); otherwise
    prefer :func:`make_train_step` / :func:`make_train_loop`.

    Args:
      symmetry: normalised-space ``S`` (``{field: op}``; see
        ``equibim_jax.data.normalized_symmetry``); required if the mirrored branch runs.
    Returns:
      the step; ``metrics`` holds scalars ``bc, sym, total, grad_norm, ema_decay,
      sym_weight`` (the ``lambda`` in effect at that step).
    """
    if train_config.uses_mirror and symmetry is None:
        raise ValueError("sym_weight > 0 or mirror_augment needs a symmetry")
    schedule = schedule if schedule is not None else make_schedule(policy_config.num_train_steps)

    def step_fn(state: TrainState, key: Array, dataset: OnDeviceDataset):
        k_batch, k_loss = jax.random.split(jax.random.fold_in(key, state.step))
        batch = sample_batch(dataset, k_batch, train_config.batch_size)
        sym_scale = sym_ramp(state.step, train_config.sym_warmup_steps, train_config.sym_start_step)

        def loss_fn(params):
            return diffusion_loss(
                state.apply_fn,
                params,
                batch,
                k_loss,
                schedule,
                symmetry,
                sym_weight=train_config.sym_weight,
                stop_gradient=train_config.sym_stop_gradient,
                mirror_augment=train_config.mirror_augment,
                action_key=policy_config.action_key,
                sym_norm=train_config.sym_norm,
                sym_space=train_config.sym_space,
                sym_scale=sym_scale,
                sym_batch=train_config.sym_batch_size,
            )

        (_, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        updates, opt_state = state.tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        decay = ema_decay(state.step, train_config.ema)
        new_state = state.replace(
            step=state.step + 1,
            params=params,
            ema_params=ema_update(state.ema_params, params, decay),
            opt_state=opt_state,
        )
        metrics = dict(terms, grad_norm=optax.tree.norm(grads), ema_decay=decay,
                       sym_weight=sym_scale * train_config.sym_weight)
        return new_state, metrics

    return step_fn


@dataclasses.dataclass(frozen=True, eq=False)
class BoundTrainFn:
    """A jitted ``fn(state, key, dataset)`` with its dataset bound: ``f(state, key)``.

    Attributes:
      fn: the jitted function (its own cache; compiled on first call).
      dataset: the on-device dataset passed to ``fn`` as an argument.
    """

    fn: Callable
    dataset: OnDeviceDataset

    def __call__(self, state: TrainState, key: Array):
        """``(state, key) -> (state, metrics)``."""
        return self.fn(state, key, self.dataset)

    def lower(self, state: TrainState, key: Array):
        """Ahead-of-time lowering (``.compile()`` it; call the result with
        ``(state, key, dataset)``), e.g. to time compilation or read ``cost_analysis()``."""
        return self.fn.lower(state, key, self.dataset)


def make_train_step(
    policy_config: PolicyConfig,
    train_config: TrainConfig,
    dataset: OnDeviceDataset,
    symmetry: Any = None,
    schedule: DiffusionSchedule | None = None,
) -> BoundTrainFn:
    """A jitted single step ``train_step(state, key) -> (state, metrics)``.

    Args:
      dataset: on-device normalised data (closed over, passed to the jitted function as
        an argument).
      symmetry: normalised-space ``S``.
    Returns:
      the step; ``metrics`` are scalars ``{bc, sym, total, grad_norm, ema_decay}``.
    """
    step = build_step_fn(policy_config, train_config, symmetry, schedule)
    return BoundTrainFn(jax.jit(step, compiler_options=train_compiler_options()), dataset)


def make_train_loop(
    policy_config: PolicyConfig,
    train_config: TrainConfig,
    dataset: OnDeviceDataset,
    symmetry: Any = None,
    schedule: DiffusionSchedule | None = None,
    num_steps: int | None = None,
) -> BoundTrainFn:
    """A jitted ``train_k_steps(state, key) -> (state, metrics)`` running K steps in a scan.

    Args:
      num_steps: ``K``; defaults to ``train_config.steps_per_dispatch``.
    Returns:
      the loop; ``metrics`` are ``{bc, sym, total, grad_norm, ema_decay}``, each ``[K]``.
    """
    k_steps = train_config.steps_per_dispatch if num_steps is None else num_steps
    step_fn = build_step_fn(policy_config, train_config, symmetry, schedule)

    @functools.partial(jax.jit, compiler_options=train_compiler_options())
    def loop(state, key, data):
        def body(s, _):
            return step_fn(s, key, data)

        return jax.lax.scan(body, state, None, length=k_steps)

    return BoundTrainFn(loop, dataset)
