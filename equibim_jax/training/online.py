"""Online training: expert rollouts, a ring buffer and the policy update in one ``jax.jit``.

:func:`make_online_train_loop` compiles one program that, for each of ``K`` iterations
(a ``lax.scan``):

1. steps ``E`` MJX envs ``C`` control steps under the task's scripted expert;
2. writes their normalised frames (the policy's observation fields and the action) into
   an on-device ring buffer of episode slots;
3. takes ``M`` gradient steps, each on a batch of windows drawn from the buffer's
   finished episodes, with ``L_sym`` as the offline step computes it.

No dataset touches the disk. The envs run in lockstep: every ``T`` steps (the rollout
length) all ``E`` episodes end together; a successful episode's slot becomes sampleable,
cut ``tail`` steps after its first success as :func:`~equibim_jax.data.generate_demos`
cuts demos, and a failed one is dropped. Each env owns ``R`` slots used in turn, so the
buffer holds up to ``R - 1`` finished rounds of ``E`` episodes besides the one being
written.

Windows are drawn exactly as :func:`~equibim_jax.data.windows.sample_batch` draws them
from a dataset whose episodes are the buffer's valid slots in slot order (same padding,
same uniform law over windows, same random numbers), so a buffer preloaded with a fixed
dataset (:func:`buffer_from_frames`) and ``env_steps = 0`` trains bit for bit as the
offline loop does.

Unlike the offline loop, this one is not data-parallel: it runs on the default device
whatever the device count (``config.json`` records ``"mesh": {"data": 1}``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from equibim_jax._xla_options import train_compiler_options
from equibim_jax.training.train_step import TrainConfig, TrainState, build_step_fn

Array = Any

__all__ = ["OnlineConfig", "RingBuffer", "OnlineCarry", "empty_buffer", "buffer_from_frames",
           "sample_ring", "make_online_train_loop", "OnlineLoop", "train_online"]

ACTION_SPACES = ("joint", "ee")


@dataclasses.dataclass(frozen=True)
class OnlineConfig:
    """Settings of the fused online loop (frozen, hashable).

    Attributes:
      num_envs: ``E``, envs stepped in parallel (vmapped).
      env_steps: ``C``, control steps of every env per iteration (0: no collection; the
        loop trains on the buffer as it is).
      grad_steps: ``M``, gradient steps per iteration.
      iterations: ``K``, iterations per dispatch (one ``lax.scan``).
      rounds: ``R``, episode slots per env (at least 2: one is being written).
      episode_length: ``T``, control steps per episode; ``None`` takes demo generation's
        default (the expert's script plus ``2 * tail``, capped at the step limit).
      tail: steps kept after an episode's first success.
      action_space: ``"joint"`` (the env's action) or ``"ee"`` (the end-effector action
        the joint action commands; joint-action envs only).
      seed: seed of the env resets.
    """

    num_envs: int = 8
    env_steps: int = 8
    grad_steps: int = 1
    iterations: int = 50
    rounds: int = 4
    episode_length: int | None = None
    tail: int = 10
    action_space: str = "joint"
    seed: int = 0

    def __post_init__(self):
        for name in ("num_envs", "grad_steps", "iterations"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"OnlineConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.env_steps < 0 or self.tail < 0:
            raise ValueError(f"OnlineConfig: env_steps and tail must be >= 0, got "
                             f"{self.env_steps}, {self.tail}")
        if self.rounds < 2:
            raise ValueError(f"OnlineConfig.rounds must be >= 2 (one round is being written), "
                             f"got {self.rounds}")
        if self.episode_length is not None and self.episode_length < 1:
            raise ValueError(f"OnlineConfig.episode_length must be >= 1 or None, got {self.episode_length}")
        if self.action_space not in ACTION_SPACES:
            raise ValueError(f"OnlineConfig.action_space must be one of {ACTION_SPACES}, "
                             f"got {self.action_space!r}")

    @property
    def slots(self) -> int:
        """``S = R * E`` episode slots."""
        return self.rounds * self.num_envs


@flax.struct.dataclass
class RingBuffer:
    """Episode slots of normalised frames on device.

    Attributes:
      frames: ``{field: [S * T, ...]}``; slot ``s`` holds frames ``s * T .. s * T + T - 1``.
      lengths: ``[S]`` int32 valid frames per slot; 0: not sampled (empty, failed or being
        written).
      slot_len: ``T`` (static).
      obs_horizon, pred_horizon, pad_before, pad_after: window layout (static), as
        :func:`~equibim_jax.data.windows.make_dataset` pads (``To - 1`` and ``Ta - 1``).
      obs_keys, action_key: fields (static).
    """

    frames: dict[str, Array]
    lengths: Array
    slot_len: int = flax.struct.field(pytree_node=False)
    obs_horizon: int = flax.struct.field(pytree_node=False)
    pred_horizon: int = flax.struct.field(pytree_node=False)
    pad_before: int = flax.struct.field(pytree_node=False)
    pad_after: int = flax.struct.field(pytree_node=False)
    obs_keys: tuple[str, ...] = flax.struct.field(pytree_node=False)
    action_key: str = flax.struct.field(pytree_node=False)

    @property
    def num_slots(self) -> int:
        return self.lengths.shape[0]

    def window_counts(self) -> Array:
        """``[S]`` int32 training windows per slot."""
        w = self.lengths - self.pred_horizon + self.pad_after + self.pad_before + 1
        return jnp.where(self.lengths > 0, jnp.maximum(w, 0), 0).astype(jnp.int32)


def empty_buffer(policy_config: Any, slots: int, slot_len: int,
                 frame_shapes: Mapping[str, tuple[int, ...]]) -> RingBuffer:
    """A buffer of ``slots`` empty slots of ``slot_len`` frames.

    Args:
      policy_config: the resolved policy config (fields and horizons).
      frame_shapes: ``{field: shape of one frame}`` for the observation fields and the
        action field.
    """
    keys = tuple(policy_config.obs_keys) + (policy_config.action_key,)
    missing = [k for k in keys if k not in frame_shapes]
    if missing:
        raise ValueError(f"empty_buffer: no frame shape for fields {missing}")
    frames = {k: jnp.zeros((slots * slot_len,) + tuple(frame_shapes[k]), jnp.float32) for k in keys}
    return RingBuffer(frames=frames, lengths=jnp.zeros((slots,), jnp.int32), slot_len=int(slot_len),
                      obs_horizon=policy_config.obs_horizon, pred_horizon=policy_config.pred_horizon,
                      pad_before=policy_config.obs_horizon - 1, pad_after=policy_config.action_horizon - 1,
                      obs_keys=tuple(policy_config.obs_keys), action_key=policy_config.action_key)


def buffer_from_frames(frames: Mapping[str, Array], episode_ends: Array, policy_config: Any,
                       slots: int | None = None, slot_len: int | None = None,
                       first_slot: int = 0) -> RingBuffer:
    """A buffer preloaded with a fixed dataset: episode ``e`` in slot ``first_slot + e``
    (collection overwrites slots ``0 .. E - 1`` first).

    Args:
      frames: ``{field: [F, ...]}`` normalised frames of all episodes concatenated (as for
        :func:`~equibim_jax.data.windows.make_dataset`).
      episode_ends: ``[E]`` exclusive episode ends.
      slots: number of slots (default ``first_slot + E``); slot_len: ``T`` (default: the
        longest episode).
    """
    ends = np.asarray(episode_ends, np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    lens = ends - starts
    slots = first_slot + len(ends) if slots is None else int(slots)
    slot_len = int(lens.max()) if slot_len is None else int(slot_len)
    if first_slot < 0 or slots < first_slot + len(ends) or slot_len < lens.max():
        raise ValueError(f"buffer_from_frames: {len(ends)} episodes of up to {lens.max()} frames do "
                         f"not fit in {slots} slots of {slot_len} from slot {first_slot}")
    keys = tuple(policy_config.obs_keys) + (policy_config.action_key,)
    buf = empty_buffer(policy_config, slots, slot_len, {k: np.shape(frames[k])[1:] for k in keys})
    out = {}
    for k in keys:
        x = np.zeros((slots * slot_len,) + np.shape(frames[k])[1:], np.float32)
        src = np.asarray(frames[k], np.float32)
        for e, (a, n) in enumerate(zip(starts, lens), start=first_slot):
            x[e * slot_len : e * slot_len + n] = src[a : a + n]
        out[k] = jnp.asarray(x)
    lengths = np.zeros(slots, np.int32)
    lengths[first_slot : first_slot + len(ends)] = lens
    return buf.replace(frames=out, lengths=jnp.asarray(lengths))


def sample_ring(buffer: RingBuffer, key: Array, batch_size: int) -> dict[str, Array]:
    """Draw ``batch_size`` windows uniformly (with replacement) from the valid slots.

    Returns:
      ``{action_key: [B, Tp, A], obs field: [B, To, ...]}``, as
      :func:`~equibim_jax.data.windows.sample_batch` returns them.
    """
    w = buffer.window_counts()
    cum = jnp.cumsum(w)
    u = jax.random.randint(key, (batch_size,), 0, cum[-1])
    slot = jnp.searchsorted(cum, u, side="right")
    t0 = u - (cum[slot] - w[slot]) - buffer.pad_before
    last = buffer.lengths[slot][:, None] - 1
    base = (slot * buffer.slot_len)[:, None]
    obs_idx = base + jnp.clip(t0[:, None] + jnp.arange(buffer.obs_horizon), 0, last)
    act_idx = base + jnp.clip(t0[:, None] + jnp.arange(buffer.pred_horizon), 0, last)
    batch = {k: buffer.frames[k][obs_idx] for k in buffer.obs_keys}
    batch[buffer.action_key] = buffer.frames[buffer.action_key][act_idx]
    return batch


@flax.struct.dataclass
class OnlineCarry:
    """Everything the online loop updates; a pytree.

    Attributes:
      train: the :class:`TrainState`. buffer: the :class:`RingBuffer`.
      env: batched env ``State`` ``[E]``; expert: batched expert state (both ``None``
        when ``env_steps == 0``).
      t: int32 step within the current episodes. round: int32 episodes rounds started.
      first_success: ``[E]`` int32 step of each current episode's first success (-1: none).
      stats: int32 counters ``env_steps``, ``episodes``, ``successes``.
    """

    train: TrainState
    buffer: RingBuffer
    env: Any
    expert: Any
    t: Array
    round: Array
    first_success: Array
    stats: dict


class OnlineLoop:
    """The compiled online loop of one env, policy and config.

    * ``init(train_state, buffer) -> carry`` starts the envs; round 0 writes slots
      ``0 .. E - 1``, which it empties when ``env_steps > 0``.
    * ``run(carry, key) -> (carry, metrics)`` is one jitted dispatch of ``K`` iterations
      (``key``: the base training key). It donates ``carry``: use the returned one.
      ``metrics`` are ``[K]`` arrays: the train metrics averaged over each iteration's
      ``M`` steps, and ``env_steps``, ``episodes``, ``successes`` (cumulative) and
      ``valid_slots``.
    * ``episode_length``: ``T``.
    """

    def __init__(self, init: Callable, run: Callable, config: OnlineConfig, episode_length: int):
        self.init = init
        self.run = run
        self.config = config
        self.episode_length = episode_length


def make_online_train_loop(env: Any, train_config: TrainConfig, online_config: OnlineConfig,
                           normalizer: Any, symmetry: Any = None, expert: Any = None) -> OnlineLoop:
    """The fused loop (module docstring).

    Args:
      env: the task env; it must observe the policy's fields.
      train_config: optimisation and ``L_sym`` settings (``total_steps`` sets the
        learning-rate schedule).
      online_config: :class:`OnlineConfig`.
      normalizer: the fixed normaliser of the policy's fields and action (e.g. fitted on
        a first batch of expert demos with ``S``).
      symmetry: normalised-space ``S`` (needed when the mirrored branch runs).
      expert: the task's expert (default: ``equibim_jax.experts.make_expert(env)``).
    Returns:
      an :class:`OnlineLoop`.
    """
    from equibim_jax.data.generate import default_length
    from equibim_jax.experts import make_expert

    oc = online_config
    if oc.action_space == "ee" and env.config.action != "joint":
        raise ValueError("OnlineConfig.action_space='ee' needs a joint-action env (its ee actions "
                         "are those the joint actions command)")
    expert = make_expert(env) if expert is None else expert
    T = int(oc.episode_length if oc.episode_length is not None else default_length(env, oc.tail))
    E, R = oc.num_envs, oc.rounds
    step_fn = build_step_fn(train_config, symmetry, sampler=sample_ring)
    reset = jax.vmap(env.reset)
    e_init = jax.vmap(expert.init)
    e_act = jax.vmap(expert.act)
    e_step = jax.vmap(env.step)
    reset_key = jax.random.key(oc.seed)

    def start_round(r):
        keys = jax.random.split(jax.random.fold_in(reset_key, r), E)
        s = reset(keys)
        return s, e_init(s)

    def slots_of(r):
        return (r % R) * E + jnp.arange(E)

    def init(train_state: TrainState, buffer: RingBuffer) -> OnlineCarry:
        fields = tuple(train_state.policy.config.obs_keys)
        missing = [f for f in fields if f not in env.config.obs]
        if missing:
            raise ValueError(f"the policy reads {missing}, which the env does not observe ({env.config.obs})")
        if buffer.slot_len != T or buffer.num_slots != oc.slots:
            raise ValueError(f"the buffer has {buffer.num_slots} slots of {buffer.slot_len} frames; "
                             f"this loop needs {oc.slots} slots of {T}")
        r0 = jnp.zeros((), jnp.int32)
        lengths, s, e = buffer.lengths, None, None
        if oc.env_steps > 0:  # round 0 is written into slots 0 .. E - 1
            s, e = jax.jit(start_round)(r0)
            lengths = lengths.at[slots_of(r0)].set(0)
        zero = jnp.zeros((), jnp.int32)
        carry = OnlineCarry(train=train_state, buffer=buffer.replace(lengths=lengths), env=s, expert=e,
                            t=zero, round=r0, first_success=jnp.full((E,), -1, jnp.int32),
                            stats={"env_steps": zero, "episodes": zero, "successes": zero})
        # Distinct buffers for every leaf, so that ``run`` can donate the carry.
        return jax.tree.map(jnp.copy, carry)

    def env_step(c: OnlineCarry, _):
        buf = c.buffer
        e, a = e_act(c.expert, c.env)
        s2 = e_step(c.env, a)
        rows = slots_of(c.round) * T + c.t
        frames = dict(buf.frames)
        for f in buf.obs_keys:
            frames[f] = frames[f].at[rows].set(normalizer.fields[f].normalize(c.env.obs[f]))
        act = env.ee_action_from_joint(a) if oc.action_space == "ee" else a
        frames[buf.action_key] = frames[buf.action_key].at[rows].set(
            normalizer.fields[buf.action_key].normalize(act))
        first = jnp.where((c.first_success < 0) & s2.info["success"], c.t, c.first_success)
        c = c.replace(buffer=buf.replace(frames=frames), env=s2, expert=e, t=c.t + 1,
                      first_success=first,
                      stats={**c.stats, "env_steps": c.stats["env_steps"] + E})
        return jax.lax.cond(c.t >= T, end_round, lambda x: x, c), None

    def end_round(c: OnlineCarry) -> OnlineCarry:
        ok = c.first_success >= 0
        n = jnp.where(ok, jnp.minimum(T, c.first_success + 1 + oc.tail), 0).astype(jnp.int32)
        lengths = c.buffer.lengths.at[slots_of(c.round)].set(n)
        r = c.round + 1
        lengths = lengths.at[slots_of(r)].set(0)  # about to be overwritten
        s, e = start_round(r)
        stats = {**c.stats, "episodes": c.stats["episodes"] + E,
                 "successes": c.stats["successes"] + jnp.sum(ok).astype(jnp.int32)}
        return c.replace(buffer=c.buffer.replace(lengths=lengths), env=s, expert=e,
                         t=jnp.zeros((), jnp.int32), round=r,
                         first_success=jnp.full((E,), -1, jnp.int32), stats=stats)

    def iteration(c: OnlineCarry, train_key):
        if oc.env_steps > 0:
            c, _ = jax.lax.scan(env_step, c, None, length=oc.env_steps)

        def grad_step(ts, _):
            return step_fn(ts, train_key, c.buffer)

        ts, m = jax.lax.scan(grad_step, c.train, None, length=oc.grad_steps)
        metrics = {k: jnp.mean(v) for k, v in m.items()}
        metrics.update(c.stats)
        metrics["valid_slots"] = jnp.sum(c.buffer.lengths > 0).astype(jnp.int32)
        return c.replace(train=ts), metrics

    @functools.partial(jax.jit, compiler_options=train_compiler_options(), donate_argnums=0)
    def run(c: OnlineCarry, train_key: Array):
        return jax.lax.scan(lambda cc, _: iteration(cc, train_key), c, None, length=oc.iterations)

    return OnlineLoop(init, run, oc, T)


def train_online(
    task: Any,
    out_dir: str | Path,
    policy_config: Any,
    train_config: TrainConfig = TrainConfig(),
    online_config: OnlineConfig = OnlineConfig(),
    *,
    checkpoint_every: int | None = None,
    progress: bool = True,
    max_wall_s: float | None = None,
) -> dict:
    """Train a policy from a stream of fresh expert demonstrations (no dataset on disk).

    The run folder is laid out as :func:`~equibim_jax.training.run.train` lays it out
    (``config.json`` with an extra ``"online"`` entry, ``train.jsonl``, ``ckpt/``), so
    ``equibim evaluate`` and :func:`~equibim_jax.training.run.load_run` read it. First one
    round of ``E`` expert episodes is rolled out to fit the mirror-consistent normaliser
    (kept fixed after) and to preload the buffer, so the first gradient steps have data.

    A rerun resumes the parameters, optimiser and normaliser from the last checkpoint;
    the envs and the buffer start afresh (from a new preload round), so an interrupted
    online run is not bit-identical to an uninterrupted one.

    Args:
      task: a :class:`~equibim_jax.config.TaskConfig`; without an ``obs`` option the env
        observes the policy's fields.
      out_dir: the run folder.
      policy_config, train_config, online_config: settings. ``train_config.total_steps``
        must be a multiple of ``iterations * grad_steps`` (the steps of one dispatch).
      checkpoint_every: steps between checkpoints (default: only at the end).
      max_wall_s: stop after the first dispatch that ends this many seconds after the
        start (the preload round and the compile included), before ``total_steps``.
    Returns:
      a summary: steps, env steps, episodes and successes, timings (compile apart),
      env-steps/s and train-steps/s, paths.
    """
    from equibim_jax.config import TaskConfig, save_config
    from equibim_jax.data.generate import make_demo_rollout
    from equibim_jax.data.normalizer import fit_normalizer, normalized_symmetry
    from equibim_jax.policies.base import make_policy
    from equibim_jax.training.checkpoint import latest_step, restore_checkpoint, save_checkpoint
    from equibim_jax.training.train_step import base_key, create_train_state
    from equibim_jax.training.run import rotation_channels

    oc, tc = online_config, train_config
    per_dispatch = oc.iterations * oc.grad_steps
    if tc.total_steps % per_dispatch:
        raise ValueError(f"train.total_steps ({tc.total_steps}) must be a multiple of online.iterations x "
                         f"online.grad_steps ({per_dispatch}), the steps of one dispatch")
    if oc.env_steps < 1:
        raise ValueError("online training needs online.env_steps >= 1 (it collects as it trains)")
    options = dict(task.options)
    options.setdefault("obs", list(policy_config.obs_keys))
    task = TaskConfig(task.name, options)
    env = task.make_env()
    fields = tuple(policy_config.obs_keys)
    missing = [f for f in fields if f not in env.config.obs]
    if missing:
        raise ValueError(f"the policy reads {missing}, which task option obs={env.config.obs} does not give")
    akey = policy_config.action_key

    # One round of expert episodes: the normaliser's data and the buffer's preload.
    from equibim_jax.data.generate import default_length

    T = int(oc.episode_length if oc.episode_length is not None else default_length(env, oc.tail))
    roll = make_demo_rollout(env, T)
    t0 = t_start = time.perf_counter()
    _, traj = roll(jax.random.split(jax.random.key(oc.seed + 7919), oc.num_envs))
    succ = np.asarray(traj["success"])
    if not succ.any():
        raise RuntimeError(f"none of the {oc.num_envs} preload expert episodes of {task.name} succeeded "
                           f"within {T} steps; raise online.episode_length")
    ends, chunks = [], {f: [] for f in fields + (akey,)}
    for e in np.flatnonzero(succ.any(axis=1)):
        n = min(T, int(np.argmax(succ[e])) + 1 + oc.tail)
        for f in fields:
            chunks[f].append(np.asarray(traj["obs"][f][e, :n]))
        a = traj["action_ee"] if oc.action_space == "ee" else traj["action"]
        chunks[akey].append(np.asarray(a[e, :n]))
        ends.append(n)
    frames = {f: np.concatenate(v) for f, v in chunks.items()}
    ends = np.cumsum(ends)
    act_sym = env.ee_action_symmetry if oc.action_space == "ee" else env.joint_action_symmetry
    sym_raw = {**env.symmetry_ops(fields, akey), akey: act_sym}
    normalizer = fit_normalizer(frames, sym_raw, identity=rotation_channels({k: v.shape[-1] for k, v in frames.items()}, akey, oc.action_space))
    cfg = policy_config.with_data(frames[akey].shape[-1], {f: frames[f].shape[-1] for f in fields},
                                  {f: tuple(frames[f].shape[1:]) for f in fields})
    policy = make_policy(cfg.name, cfg)
    config = {"task": task, "policy": cfg, "train": tc, "online": oc}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "ckpt"
    state = create_train_state(policy, tc)
    start = 0
    if latest_step(ckpt) is not None:
        state, normalizer, _ = restore_checkpoint(ckpt, state, expected_config=config)
        start = int(state.step)
    sym = normalized_symmetry(sym_raw, normalizer)
    # The online loop is not data-parallel: it runs on the default device whatever the
    # device count, so its mesh is one device.
    save_config(out / "config.json", {**config, "devices": jax.device_count(), "mesh": {"data": 1}})
    buf = buffer_from_frames(normalizer.normalize(frames), ends, cfg, slots=oc.slots, slot_len=T,
                             first_slot=oc.num_envs)
    loop = make_online_train_loop(env, tc, oc, normalizer, sym if tc.uses_mirror else None)
    carry = loop.init(state, buf)
    preload_s = time.perf_counter() - t0
    key = base_key(tc)
    log_path = out / "train.jsonl"
    t0 = time.perf_counter()
    compile_s, row = None, {}
    env_steps0 = 0
    with open(log_path, "a" if start else "w") as log, tqdm(
            total=tc.total_steps, initial=start, desc="train --online", unit="step",
            disable=not progress) as bar:
        while int(carry.train.step) < tc.total_steps:
            td = time.perf_counter()
            carry, m = loop.run(carry, key)
            m = jax.device_get(m)
            dt = time.perf_counter() - td
            if compile_s is None:
                compile_s = dt  # the first dispatch includes the compile
            else:
                row_rate = {"env_steps_per_s": (int(m["env_steps"][-1]) - env_steps0) / dt,
                            "train_steps_per_s": per_dispatch / dt}
            if not (np.isfinite(m["total"]).all() and np.isfinite(m["grad_norm"]).all()):
                raise RuntimeError(f"the loss became non-finite before step {int(carry.train.step)}; "
                                   f"lower train.learning_rate or set train.grad_clip")
            step = int(carry.train.step)
            row = {"step": step, **{k: float(np.mean(m[k])) for k in ("bc", "sym", "total", "grad_norm")},
                   "env_steps": int(m["env_steps"][-1]), "episodes": int(m["episodes"][-1]),
                   "successes": int(m["successes"][-1]), "valid_slots": int(m["valid_slots"][-1]),
                   "dispatch_s": dt, "wall_s": time.perf_counter() - t0}
            if compile_s != dt:
                row.update(row_rate)
            env_steps0 = int(m["env_steps"][-1])
            log.write(json.dumps(row) + "\n")
            log.flush()
            bar.update(per_dispatch)
            bar.set_postfix(bc=f"{row['bc']:.3f}", sym=f"{row['sym']:.3f}", episodes=row["episodes"])
            if checkpoint_every and step % checkpoint_every == 0 and step < tc.total_steps:
                save_checkpoint(ckpt, carry.train, normalizer, config, max_to_keep=2)
            if max_wall_s is not None and time.perf_counter() - t_start >= max_wall_s:
                break
    if latest_step(ckpt) != int(carry.train.step):
        save_checkpoint(ckpt, carry.train, normalizer, config, max_to_keep=2)
    rows = [json.loads(x) for x in log_path.read_text().splitlines() if x.strip()]
    rates = [r for r in rows if "env_steps_per_s" in r]
    return {"steps": int(carry.train.step), "resumed_from": start, "preload_s": preload_s,
            "first_dispatch_s_incl_compile": compile_s, "train_s": time.perf_counter() - t0,
            "env_steps": row.get("env_steps", 0), "episodes": row.get("episodes", 0),
            "successes": row.get("successes", 0),
            "env_steps_per_s": float(np.mean([r["env_steps_per_s"] for r in rates])) if rates else None,
            "train_steps_per_s": float(np.mean([r["train_steps_per_s"] for r in rates])) if rates else None,
            "final": row, "checkpoint": str(ckpt), "log": str(log_path), "config": str(out / "config.json")}
