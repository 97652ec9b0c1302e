"""A training run on a dataset: run folder, config.json, progress, logs, checkpoints, resume.

A run folder holds ``config.json`` (the resolved task, policy and train configs),
``train.jsonl`` (one JSON row per dispatch of ``steps_per_dispatch`` steps) and ``ckpt/``
(orbax checkpoints). Training resumes exactly from the last checkpoint of the folder.

The train loop is data-parallel over every visible device (``equibim_jax._sharding``);
``config.json`` records the device count and the mesh shape, which a resumed run may
change. In a multi-process run every process trains and saves checkpoints together (orbax
coordinates them; the run folder must be on a shared file system), and only process 0
writes ``config.json``, ``train.jsonl`` and the progress bar.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
from tqdm.auto import tqdm

from equibim_jax._io import atomic_write_bytes
from equibim_jax._sharding import is_main_process, mesh_shape, train_mesh
from equibim_jax.config import TaskConfig, config_from_dict, save_config
from equibim_jax.data.dataset import Demos, load
from equibim_jax.data.generate import env_from_meta
from equibim_jax.data.normalizer import Normalizer, fit_normalizer, normalized_symmetry
from equibim_jax.data.windows import OnDeviceDataset, frames_from_demos, make_dataset, sample_batch
from equibim_jax.policies.base import Policy, PolicyConfig, make_policy
from equibim_jax.sim.env import Env
from equibim_jax.training.checkpoint import (
    CheckpointError,
    latest_step,
    read_checkpoint_config,
    restore_checkpoint,
    save_checkpoint,
)
from equibim_jax.training.losses import equivariance_error
from equibim_jax.training.train_step import (
    TrainConfig,
    TrainState,
    base_key,
    create_train_state,
    make_joint_train_loop,
)

__all__ = ["TrainingDiverged", "Run", "prepare_data", "constant_action_warning", "train", "train_together", "load_run", "read_log"]


class TrainingDiverged(RuntimeError):
    """The loss became NaN or infinite; the last good state was kept as a checkpoint."""


class Run(NamedTuple):
    """A trained run, loaded: ``policy``, ``state`` (EMA parameters in ``state.ema_params``),
    ``normalizer`` and ``config`` (``{"task": TaskConfig, "policy": ..., "train": TrainConfig}``)."""

    policy: Policy
    state: TrainState
    normalizer: Normalizer
    config: dict

    def make_env(self) -> Env:
        """The env of the run's task and options."""
        return self.config["task"].make_env()


class Data(NamedTuple):
    """A dataset prepared for one policy: resolved ``policy_config``, ``normalizer``,
    normalised-space ``sym`` and the on-device ``dataset``."""

    policy_config: PolicyConfig
    normalizer: Normalizer
    sym: dict
    dataset: OnDeviceDataset


def constant_channels(x: np.ndarray, tol: float = 2e-4) -> np.ndarray:
    """Indices of the trailing-axis channels of ``x [..., D]`` whose range is below ``tol``."""
    flat = np.asarray(x).reshape(-1, np.shape(x)[-1])
    return np.flatnonzero(flat.max(0) - flat.min(0) < tol)


def constant_action_warning(policy_config: PolicyConfig, actions: np.ndarray, tol: float = 2e-4) -> str | None:
    """The warning :func:`prepare_data` gives when a noise-predicting diffusion policy
    (``prediction="epsilon"``) is trained on actions ``[..., A]`` with channels whose range
    is below ``tol`` (the normaliser leaves them unscaled, near 0), else ``None``.

    Such a policy learns constant channels poorly: their noise target is the noisy input
    rescaled, with no signal to fit, and the DDIM samples come out noisy in exactly those
    channels. The end-effector action's rotation entries that a task never changes are the
    common case. A clean-sample predictor (``prediction="sample"``) fits them at once.
    """
    if getattr(policy_config, "prediction", None) != "epsilon":
        return None
    const = constant_channels(actions, tol)
    if const.size == 0:
        return None
    return (f"action channels {const.tolist()} are constant in the data (range < {tol:g}); a "
            "noise-predicting diffusion policy (prediction='epsilon') fits constant channels "
            "poorly and samples noise in them. Use prediction='sample' for these actions.")


def ee_rotation_mask(size: int) -> np.ndarray:
    """Bool ``[size]``: the rotation entries of the end-effector layout (per arm: position
    3, rotation ``R`` = 6 (6D) or 4 (quaternion), opening 1; ``size = 2 * (3 + R + 1)``)."""
    rot = size // 2 - 4
    if size % 2 or rot not in (4, 6):
        raise ValueError(f"an end-effector field has 2 * (3 + R + 1) entries with R = 6 or 4 (20 or 16); got {size}")
    one = np.r_[np.zeros(3, bool), np.ones(rot, bool), False]
    return np.concatenate([one, one])


def rotation_channels(sizes: dict[str, int], action_key: str, action_space: str) -> dict[str, np.ndarray]:
    """``{field: bool [D]}``: the end-effector rotation entries of the ``ee`` observation
    (when in ``sizes``, ``{field: D}``) and of an ``action_space == "ee"`` action (under
    ``action_key``); the normaliser leaves them unscaled (``fit_normalizer(identity=...)``)."""
    out = {}
    if "ee" in sizes:
        out["ee"] = ee_rotation_mask(int(sizes["ee"]))
    if action_space == "ee" and action_key in sizes:
        out[action_key] = ee_rotation_mask(int(sizes[action_key]))
    return out


def _action_space(env) -> str:
    """``"joint"`` or ``"ee"``: an :class:`Env`'s ``config.action``, or the ``action_space``
    of an env stand-in (``interop.symmetry.MapEnv``)."""
    space = getattr(env, "action_space", None)
    return space if space is not None else env.config.action


def prepare_data(demos: Demos, env: Env, policy_config: PolicyConfig,
                 normalizer: Normalizer | None = None) -> Data:
    """Frames of the fields the policy reads, the mirror-consistent normaliser (fitted on
    the frames and their mirror images unless given; end-effector rotation entries left
    unscaled, :func:`rotation_channels`), ``S`` in normalised space, the policy config with
    the data's dims, and the on-device windows. Warns (:func:`constant_action_warning`)
    when a noise-predicting policy meets constant action channels."""
    fields = tuple(policy_config.obs_keys)
    frames, ends = frames_from_demos(demos, fields)
    msg = constant_action_warning(policy_config, frames["action"])
    if msg is not None:
        warnings.warn(msg, stacklevel=2)
    sym_raw = env.symmetry_ops(fields, policy_config.action_key)
    if policy_config.action_key != "action":
        frames[policy_config.action_key] = frames.pop("action")
    if normalizer is None:
        sizes = {k: v.shape[-1] for k, v in frames.items()}
        unscaled = rotation_channels(sizes, policy_config.action_key, _action_space(env))
        normalizer = fit_normalizer(frames, sym_raw, identity=unscaled)
    cfg = policy_config.with_data(frames[policy_config.action_key].shape[-1],
                                  {f: frames[f].shape[-1] for f in fields},
                                  {f: tuple(frames[f].shape[1:]) for f in fields})
    dataset = make_dataset(normalizer.normalize(frames), ends, cfg)
    return Data(cfg, normalizer, normalized_symmetry(sym_raw, normalizer), dataset)


def read_log(path: str | Path) -> list[dict]:
    """The rows of a ``train.jsonl``; a torn (half-written) line is skipped with a warning."""
    rows = []
    for i, line in enumerate(Path(path).read_text().splitlines()):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            warnings.warn(f"{path}: skipping unreadable line {i + 1} (a write cut short?)", stacklevel=2)
    return rows


def _same_normalizer(a: Normalizer, b: Normalizer) -> bool:
    da, db = a.to_state_dict(), b.to_state_dict()
    if jax.tree.structure(da) != jax.tree.structure(db):
        return False
    return all(np.array_equal(np.asarray(x), np.asarray(y))
               for x, y in zip(jax.tree.leaves(da), jax.tree.leaves(db)))


def _probe(policy: Policy, dataset: OnDeviceDataset, sym: dict, n: int = 64):
    """``probe(params) -> relative equivariance error`` on a fixed batch and fixed noise."""
    key = jax.random.key(12345)
    batch = sample_batch(dataset, key, n)
    return jax.jit(lambda p: equivariance_error(policy, p, batch, jax.random.fold_in(key, 1), sym))


def train(
    data: str | Path | Demos,
    out_dir: str | Path,
    policy_config: PolicyConfig,
    train_config: TrainConfig = TrainConfig(),
    *,
    env: Env | None = None,
    normalizer: Normalizer | None = None,
    checkpoint_every: int | None = None,
    progress: bool = True,
    desc: str = "train",
    max_wall_s: float | None = None,
) -> dict:
    """Train a policy on a dataset; resumes from ``out_dir`` if it holds a checkpoint.

    Args:
      data: a dataset path (``equibim generate``) or loaded :class:`Demos`.
      out_dir: the run folder (module docstring).
      policy_config: the policy's config (dims are taken from the data).
      train_config: settings; ``total_steps`` is the run's length.
      env: the dataset's env, if already built (else rebuilt from the dataset metadata).
      normalizer: use this normaliser instead of fitting one (so two runs share it).
      checkpoint_every: steps between checkpoints (default: only at the end).
      max_wall_s: stop after the first dispatch that ends this many seconds after the
        start (compile included), before ``total_steps``; the learning-rate schedule is
        still the one of ``total_steps``. ``None``: run to ``total_steps``.
    Returns:
      a summary: steps, timings, the last log row, paths.
    Raises:
      TrainingDiverged: the loss became non-finite; training stops, and the state before
        the failing dispatch is saved as a checkpoint (unless one of that step exists).
      CheckpointError: ``out_dir`` holds a checkpoint of a different config or normaliser.
    """
    return train_together(data, {desc: (out_dir, train_config)}, policy_config, env=env, normalizer=normalizer,
                          checkpoint_every=checkpoint_every, progress=progress, desc=desc,
                          max_wall_s=max_wall_s)[desc]


class _Arm:
    """One run of :func:`train_together`: its folder, config and last log row."""

    def __init__(self, name: str, out_dir: str | Path, tc: TrainConfig, config: dict):
        self.name, self.tc, self.config = name, tc, config
        self.out = Path(out_dir)
        self.ckpt = self.out / "ckpt"
        self.log_path = self.out / "train.jsonl"
        self.row: dict[str, Any] = {}


def train_together(
    data: str | Path | Demos,
    runs: dict[str, tuple[str | Path, TrainConfig]],
    policy_config: PolicyConfig,
    *,
    env: Env | None = None,
    normalizer: Normalizer | None = None,
    checkpoint_every: int | None = None,
    progress: bool = True,
    desc: str = "train",
    max_wall_s: float | None = None,
) -> dict[str, dict]:
    """Train several runs of one policy on one dataset in lockstep, in one compiled
    program (:func:`~equibim_jax.training.train_step.make_joint_train_loop`); each run
    folder ends up as :func:`train` would leave it.

    Baseline and +EquiBim differ only in their train configs, so the demo and the
    experiment runner train both at once: one compile instead of two, and XLA overlaps
    the two runs' small operations.

    Args:
      runs: ``{name: (run folder, train config)}``; the configs must agree on
        ``total_steps`` and ``steps_per_dispatch``. Other arguments as in :func:`train`;
        ``normalizer`` (or the one fitted on ``data``) is used by every run.
    Returns:
      ``{name: summary}`` as :func:`train` returns, plus ``trained_with`` (the names);
      ``train_s`` and the first dispatch's time are those of the joint program.
    Raises:
      ValueError: no runs, mismatched lengths, or runs resumed from different steps.
      TrainingDiverged, CheckpointError: as in :func:`train` (for any of the runs).
    """
    if not runs:
        raise ValueError("train_together needs at least one run")
    lengths = {(tc.total_steps, tc.steps_per_dispatch) for _, tc in runs.values()}
    if len(lengths) > 1:
        raise ValueError("runs trained together must share total_steps and steps_per_dispatch, got "
                         + ", ".join(f"{n}: {tc.total_steps}/{tc.steps_per_dispatch}" for n, (_, tc) in runs.items()))
    demos = load(data) if not isinstance(data, Demos) else data
    env = env if env is not None else env_from_meta(dict(demos.meta))
    prep = prepare_data(demos, env, policy_config, normalizer)
    policy = make_policy(prep.policy_config.name, prep.policy_config)
    task = TaskConfig(env.task, env.task_options)
    arms = [_Arm(n, d, tc, {"task": task, "policy": prep.policy_config, "train": tc}) for n, (d, tc) in runs.items()]

    states, saved = [], None
    for arm in arms:
        arm.out.mkdir(parents=True, exist_ok=True)
        state = create_train_state(policy, arm.tc)
        if latest_step(arm.ckpt) is not None:
            state, arm_norm, _ = restore_checkpoint(arm.ckpt, state, expected_config=arm.config)
            if normalizer is not None and not _same_normalizer(normalizer, arm_norm):
                raise CheckpointError(f"{arm.ckpt}: was saved with a different normaliser than the one given")
            if saved is not None and not _same_normalizer(saved, arm_norm):
                raise CheckpointError(f"{arm.ckpt}: was saved with a different normaliser than "
                                      f"{arms[0].ckpt}; train these runs separately")
            saved = arm_norm
        states.append(state)
    steps = {int(s.step) for s in states}
    if len(steps) > 1:
        raise ValueError("runs trained together must resume from the same step, got "
                         + ", ".join(f"{a.name}: {int(s.step)}" for a, s in zip(arms, states))
                         + "; train them separately to bring them level")
    start = steps.pop()
    if saved is not None:
        prep = prep._replace(normalizer=saved, sym=normalized_symmetry(
            env.symmetry_ops(tuple(prep.policy_config.obs_keys), prep.policy_config.action_key), saved))
    lead = is_main_process()  # the one process that writes config.json, train.jsonl, the bar
    for arm in arms:
        if lead:
            save_config(arm.out / "config.json", {
                **arm.config, "data": {"path": str(data) if not isinstance(data, Demos) else None,
                                       "episodes": demos.n_episodes, "steps": demos.n_steps},
                "devices": jax.device_count(), "mesh": mesh_shape(train_mesh())})
        if lead and start and arm.log_path.exists():  # drop rows logged after the checkpoint we resume from
            rows = [r for r in read_log(arm.log_path) if r.get("step", 0) <= start]
            atomic_write_bytes(arm.log_path, "".join(json.dumps(r) + "\n" for r in rows).encode())
    loop = make_joint_train_loop(tuple(a.tc for a in arms), prep.dataset,
                                 tuple(prep.sym if a.tc.uses_mirror else None for a in arms))
    probe = _probe(policy, prep.dataset, prep.sym)
    keys = tuple(base_key(a.tc) for a in arms)
    total, k = arms[0].tc.total_steps, arms[0].tc.steps_per_dispatch
    t0 = time.perf_counter()
    compile_s = None
    states = tuple(states)
    with contextlib.ExitStack() as stack, tqdm(total=total, initial=start, desc=desc, unit="step",
                                               disable=not (progress and lead)) as bar:
        logs = [stack.enter_context(open(a.log_path if lead else os.devnull, "a" if start else "w")) for a in arms]
        while int(states[0].step) < total:
            tc0 = time.perf_counter()
            prev = states
            states, metrics = loop(states, keys)
            metrics = jax.device_get(metrics)
            if compile_s is None:
                compile_s = time.perf_counter() - tc0
            for arm, p, m in zip(arms, prev, metrics):
                bad = ~(np.isfinite(m["total"]) & np.isfinite(m["grad_norm"]))
                if bad.any():
                    _diverged(arm.ckpt, p, prep.normalizer, arm.config, m, bad)
            step = int(states[0].step)
            wall = time.perf_counter() - t0
            for arm, s, m, log in zip(arms, states, metrics, logs):
                arm.row = {"step": step, **{n: float(np.mean(v)) for n, v in m.items()},
                           "equiv_err": float(probe(s.ema_params)), "wall_s": wall}
                log.write(json.dumps(arm.row) + "\n")
                log.flush()
            bar.update(k)
            r = arms[-1].row
            bar.set_postfix(bc=f"{r['bc']:.3f}", sym=f"{r['sym']:.3f}", equiv=f"{r['equiv_err']:.3f}")
            if checkpoint_every and step % checkpoint_every == 0 and step < total:
                for arm, s in zip(arms, states):
                    save_checkpoint(arm.ckpt, s, prep.normalizer, arm.config, max_to_keep=2)
            if max_wall_s is not None and time.perf_counter() - t0 >= max_wall_s:
                break
    train_s = time.perf_counter() - t0
    out = {}
    for arm, s in zip(arms, states):
        if latest_step(arm.ckpt) != int(s.step):
            save_checkpoint(arm.ckpt, s, prep.normalizer, arm.config, max_to_keep=2)
        out[arm.name] = {"steps": int(s.step), "resumed_from": start, "train_s": train_s,
                         "first_dispatch_s_incl_compile": compile_s, "final": arm.row,
                         "checkpoint": str(arm.ckpt), "log": str(arm.log_path),
                         "config": str(arm.out / "config.json"), "trained_with": [a.name for a in arms]}
    return out


def _diverged(ckpt: Path, prev: TrainState, normalizer: Normalizer, config: dict, metrics: dict,
              bad: np.ndarray) -> None:
    first = int(np.argmax(bad))
    step = int(prev.step) + first + 1
    kept = latest_step(ckpt)
    if kept is None or kept < int(prev.step):
        save_checkpoint(ckpt, prev, normalizer, config, max_to_keep=None)
        kept = int(prev.step)
    terms = ", ".join(f"{m}={float(np.asarray(metrics[m])[first]):.4g}"
                      for m in ("bc", "sym", "total", "grad_norm") if m in metrics)
    where = f"the last good checkpoint is step {kept} in {ckpt}"
    raise TrainingDiverged(
        f"the loss became non-finite at step {step} ({terms}); training stopped and {where}. "
        "Lower train.learning_rate or set train.grad_clip, then rerun to resume from it.")


def load_run(run_dir: str | Path) -> Run:
    """Load the last checkpoint of a run folder written by :func:`train`.

    Raises:
      FileNotFoundError: no checkpoint. CheckpointError: unreadable or inconsistent.
    """
    ckpt = Path(run_dir) / "ckpt"
    if latest_step(ckpt) is None:
        raise FileNotFoundError(f"no checkpoint in {ckpt} (train with `equibim train` first)")
    saved = read_checkpoint_config(ckpt)
    try:
        config = {"task": config_from_dict(TaskConfig, saved["task"]),
                  "policy": config_from_dict(PolicyConfig, saved["policy"]),
                  "train": config_from_dict(TrainConfig, saved["train"])}
    except (KeyError, ValueError, TypeError) as e:
        raise CheckpointError(f"{ckpt}: its config is not a training run's ({e})") from e
    policy = make_policy(config["policy"].name, config["policy"])
    state, normalizer, _ = restore_checkpoint(ckpt, create_train_state(policy, config["train"]))
    return Run(policy, state, normalizer, config)

