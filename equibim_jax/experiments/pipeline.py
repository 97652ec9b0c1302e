"""Generate -> train -> evaluate, as library functions (the ``equibim`` subcommands call them).

* :func:`generate_dataset`: scripted-expert demos of one task into a zarr dataset whose
  metadata records the :class:`EnvSpec`, so training and evaluation rebuild the same env.
* :func:`train_policy`: diffusion policy (+ optional ``L_sym``) on a dataset, with a
  progress bar, a JSONL log, the equivariance error of the EMA parameters on a fixed
  probe batch, periodic orbax checkpoints and exact resume.
* :func:`evaluate_checkpoint` / :func:`evaluate_policies`: closed-loop success on the
  trained side and on its mirror image, with Wilson intervals.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from equibim_jax._io import atomic_write_bytes
from equibim_jax.data import fit_normalizer, normalized_symmetry
from equibim_jax.data.dataset import DatasetError, Demos, load, save
from equibim_jax.data.generate import generate_demos
from equibim_jax.data.normalizer import Normalizer
from equibim_jax.evaluation.rollout import evaluate_sides, make_policy_rollout
from equibim_jax.policies import (
    EncoderConfig,
    PolicyApplyFn,
    PolicyConfig,
    UNetConfig,
    add_noise,
    make_schedule,
)
from equibim_jax.sim.env import Env
from equibim_jax.tasks import make_env, task_names
from equibim_jax.training import TrainConfig, create_train_state, make_dataset, make_train_loop
from equibim_jax.training.checkpoint import (
    CheckpointError,
    config_from_dict,
    latest_step,
    restore_checkpoint,
    save_checkpoint,
)
from equibim_jax.training.losses import field_op, mirror_batch
from equibim_jax.training.train_step import OnDeviceDataset, sample_batch

__all__ = [
    "EnvSpec",
    "ModelOptions",
    "generate_dataset",
    "env_spec_of",
    "frames_from_demos",
    "raw_symmetry",
    "policy_config_for",
    "train_policy",
    "load_policy",
    "evaluate_policies",
    "open_loop_errors",
    "evaluate_checkpoint",
]


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """The env a dataset was generated in (stored in its metadata; rebuilt by train/eval)."""

    task: str = "place_empty_cup"
    """Task name (see ``equibim_jax.tasks.task_names``)."""
    side: str = "left"
    """Side of the task the demos come from: left, right or both."""
    obs: tuple[str, ...] = ("qpos", "point_cloud")
    """Observation fields recorded (the policy reads qpos and point_cloud)."""
    action: str = "joint"
    """Action mode: joint or ee."""
    n_points: int = 64
    """Points per point cloud."""
    episode_length: int = 240
    """Control steps per episode (the expert finishes place_empty_cup in about 207)."""

    def __post_init__(self):
        object.__setattr__(self, "obs", tuple(self.obs))
        if self.task not in task_names():
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {task_names()}")
        if self.side not in ("left", "right", "both"):
            raise ValueError(f"side must be left, right or both, got {self.side!r}")
        if self.n_points < 1 or self.episode_length < 1:
            raise ValueError("n_points and episode_length must be >= 1")

    def make(self) -> Env:
        """The env (validates every option through ``make_env``)."""
        return make_env(self.task, obs=self.obs, action=self.action, side=self.side,
                        n_points=self.n_points, episode_length=self.episode_length)


@dataclasses.dataclass(frozen=True)
class ModelOptions:
    """Diffusion-policy size and horizons (the dataset fixes the input and action widths)."""

    down_dims: tuple[int, ...] = (32, 64, 128)
    """U-Net channel widths per level."""
    pc_hidden: tuple[int, ...] = (32, 64, 128)
    """Per-point MLP widths of the DP3-style encoder (DP3 uses 64, 128, 256; half is 1.4x
    faster per step on 2 CPU cores)."""
    pc_out: int = 64
    """Point-cloud feature width per frame."""
    state_out: int = 64
    """qpos feature width per frame."""
    obs_horizon: int = 2
    pred_horizon: int = 16
    action_horizon: int = 8
    num_inference_steps: int = 10
    """DDIM steps at inference."""


def _json_ready(x: Any) -> Any:
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _json_ready(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, Mapping):
        return {str(k): _json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_ready(v) for v in x]
    return x


# ----------------------------------------------------------------------------- generate
def generate_dataset(spec: EnvSpec, out: str | Path, n_episodes: int, seed: int = 0,
                     chunk: int = 32, overwrite: bool = False,
                     progress: bool = True) -> tuple[Demos, dict]:
    """Generate ``n_episodes`` successful expert demos in ``spec``'s env and save them.

    The dataset at ``out`` is written atomically; an existing one is only replaced with
    ``overwrite=True``. Returns ``(demos, stats)``.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite=True (--overwrite) to replace it")
    env = spec.make()
    chunk = max(1, min(int(chunk), 32, int(n_episodes)))  # <= 32 envs per vmap on CPU
    # Equal batches that cover n_episodes exactly (48 -> 2 x 24, not 2 x 32): the expert
    # rarely fails, so a last batch padded to ``chunk`` would mostly simulate spares.
    chunk = math.ceil(int(n_episodes) / math.ceil(int(n_episodes) / chunk))
    demos, stats = generate_demos(env, jax.random.key(seed), n_episodes, chunk=chunk,
                                  progress=progress,
                                  meta={"seed": int(seed), "env_spec": _json_ready(spec)})
    save(demos, out, overwrite=overwrite)
    return demos, stats


def env_spec_of(demos: Demos) -> EnvSpec:
    """The :class:`EnvSpec` recorded in a dataset's metadata."""
    spec = demos.meta.get("env_spec")
    if not isinstance(spec, Mapping):
        raise DatasetError("dataset metadata has no 'env_spec' (not written by generate_dataset?)")
    try:
        return config_from_dict(EnvSpec, spec)
    except (ValueError, TypeError) as e:
        raise DatasetError(f"dataset metadata 'env_spec' is invalid: {e}") from None


def frames_from_demos(demos: Demos) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Concatenate the valid steps of every episode: ``{field: [F, ...]}``, ends ``[E]``."""
    eps = range(demos.n_episodes)
    frames = {k: np.concatenate([v[e, : demos.length[e]] for e in eps]) for k, v in demos.obs.items()}
    frames["action"] = np.concatenate([demos.action[e, : demos.length[e]] for e in eps])
    return frames, np.cumsum(demos.length).astype(np.int64)


def raw_symmetry(env: Env, fields: tuple[str, ...]) -> dict:
    """``S`` in raw (unnormalised) units for the observation ``fields`` and the action."""
    return {**{f: env.obs_symmetry.ops[f] for f in fields}, "action": env.action_symmetry}


def policy_config_for(env: Env, opts: ModelOptions) -> PolicyConfig:
    """The policy config for ``env``'s observation (qpos [+ point_cloud]) and action widths."""
    if "qpos" not in env.config.obs:
        raise ValueError(f"the policy needs the qpos observation; the env observes {env.config.obs}")
    pc = "point_cloud" if "point_cloud" in env.config.obs else None
    return PolicyConfig(
        action_dim=env.action_size, state_dim=2 * (env.info.n_arm + 1),
        obs_horizon=opts.obs_horizon, pred_horizon=opts.pred_horizon,
        action_horizon=opts.action_horizon, num_inference_steps=opts.num_inference_steps,
        encoder=EncoderConfig(state_key="qpos", pc_key=pc, pc_hidden=tuple(opts.pc_hidden),
                              pc_out=opts.pc_out, state_out=opts.state_out),
        unet=UNetConfig(down_dims=tuple(opts.down_dims)),
    )


# ----------------------------------------------------------------------------- train
def _same_normalizer(a: Normalizer, b: Normalizer) -> bool:
    da, db = a.to_state_dict(), b.to_state_dict()
    if jax.tree.structure(da) != jax.tree.structure(db):
        return False
    return all(np.array_equal(np.asarray(x), np.asarray(y))
               for x, y in zip(jax.tree.leaves(da), jax.tree.leaves(db)))


def _probe(policy_cfg: PolicyConfig, dataset: OnDeviceDataset, sym: Mapping, n: int = 64):
    """``probe(params) -> relative equivariance error`` of the noise prediction.

    On a fixed batch of training windows with fixed noise levels:
    ``sum ||eps(S a_k, k, S O) - S eps(a_k, k, O)||^2 / sum ||eps(a_k, k, O)||^2``.
    0 for an exactly equivariant network; about 2 for unrelated predictions.
    """
    apply = PolicyApplyFn(policy_cfg)
    schedule = make_schedule(policy_cfg.num_train_steps)
    key = jax.random.key(12345)
    batch = sample_batch(dataset, key, n)
    a0 = batch["action"]
    obs = {f: v for f, v in batch.items() if f != "action"}
    noise = jax.random.normal(jax.random.fold_in(key, 1), a0.shape)
    k = jax.random.randint(jax.random.fold_in(key, 2), (n,), 0, policy_cfg.num_train_steps)
    a_k = add_noise(schedule, a0, noise, k)
    s_a = field_op(sym, "action")
    obs_m = mirror_batch(sym, obs)

    @jax.jit
    def probe(params):
        e = apply(params, a_k, k, obs)
        e_m = apply(params, s_a(a_k), k, obs_m)
        return jnp.sum(jnp.square(e_m - s_a(e))) / jnp.sum(jnp.square(e))

    return probe


def train_policy(
    data: str | Path | Demos,
    out_dir: str | Path,
    model: ModelOptions = ModelOptions(),
    train: TrainConfig = TrainConfig(),
    *,
    normalizer: Normalizer | None = None,
    checkpoint_every: int | None = None,
    progress: bool = True,
    desc: str = "train",
) -> dict:
    """Train a diffusion policy on a dataset; resumes from ``out_dir`` if it holds a checkpoint.

    Args:
      data: a dataset path (written by :func:`generate_dataset`) or loaded :class:`Demos`.
      out_dir: run folder: ``ckpt/`` (orbax), ``train.jsonl`` (one line per dispatch of
        ``train.steps_per_dispatch`` steps: mean losses, grad norm and the EMA parameters'
        relative equivariance error ``equiv_err`` on a fixed probe batch).
      model, train: settings. ``train.total_steps`` is the run length; ``sym_weight`` > 0
        adds ``L_sym``.
      normalizer: use this normaliser instead of fitting one (so two runs share it).
      checkpoint_every: steps between checkpoints (default: only at the end).
    Returns:
      summary dict (steps, timings, final losses, equivariance error).
    """
    demos = load(data) if not isinstance(data, Demos) else data
    spec = env_spec_of(demos)
    env = spec.make()
    frames, ends = frames_from_demos(demos)
    fields = tuple(f for f in ("qpos", "point_cloud") if f in frames)
    frames = {k: frames[k] for k in (*fields, "action")}
    sym_raw = raw_symmetry(env, fields)
    normalizer = normalizer or fit_normalizer(frames, sym_raw)
    sym = normalized_symmetry(sym_raw, normalizer)
    policy_cfg = policy_config_for(env, model)
    dataset = make_dataset(normalizer.normalize(frames), ends, policy_cfg)
    config = {"policy": policy_cfg, "train": train, "env": spec, "model": model}

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "ckpt"
    state, _ = create_train_state(policy_cfg, train)
    start = 0
    if latest_step(ckpt) is not None:
        state, normalizer_saved, _ = restore_checkpoint(ckpt, state, expected_config=config)
        if normalizer is not None and not _same_normalizer(normalizer, normalizer_saved):
            raise CheckpointError(f"{ckpt}: was saved with a different normaliser than the one given")
        normalizer = normalizer_saved
        start = int(state.step)
    total, k = train.total_steps, train.steps_per_dispatch
    if total % k:
        raise ValueError(f"total_steps ({total}) must be a multiple of steps_per_dispatch ({k})")
    loop = make_train_loop(policy_cfg, train, dataset, sym if train.uses_mirror else None)
    probe = _probe(policy_cfg, dataset, sym)
    key = jax.random.fold_in(jax.random.key(train.seed), 1)
    log_path = out / "train.jsonl"
    if start and log_path.exists():  # drop rows logged after the checkpoint we resume from
        rows = [line for line in log_path.read_text().splitlines()
                if line.strip() and json.loads(line).get("step", 0) <= start]
        atomic_write_bytes(log_path, "".join(r + "\n" for r in rows).encode())
    mode = "a" if start else "w"
    t0 = time.perf_counter()
    compile_s = None
    row = {}
    with open(log_path, mode) as log, tqdm(total=total, initial=start, desc=desc, unit="step",
                                           disable=not progress) as bar:
        while int(state.step) < total:
            tc = time.perf_counter()
            state, metrics = loop(state, key)
            metrics = jax.device_get(metrics)
            if compile_s is None:
                compile_s = time.perf_counter() - tc
            step = int(state.step)
            row = {"step": step, **{m: float(np.mean(v)) for m, v in metrics.items()},
                   "equiv_err": float(probe(state.ema_params)),
                   "wall_s": time.perf_counter() - t0}
            log.write(json.dumps(row) + "\n")
            log.flush()
            bar.update(k)
            bar.set_postfix(bc=f"{row['bc']:.3f}", sym=f"{row['sym']:.3f}",
                            equiv=f"{row['equiv_err']:.3f}")
            if checkpoint_every and step % checkpoint_every == 0 and step < total:
                save_checkpoint(ckpt, state, normalizer, config, max_to_keep=2)
    if latest_step(ckpt) != int(state.step):
        save_checkpoint(ckpt, state, normalizer, config, max_to_keep=2)
    wall = time.perf_counter() - t0
    return {"steps": int(state.step), "resumed_from": start, "train_s": wall,
            "first_dispatch_s_incl_compile": compile_s, "final": row,
            "checkpoint": str(ckpt), "log": str(log_path)}


def load_policy(run_dir: str | Path):
    """``(model, state, normalizer, config dict)`` from a :func:`train_policy` run folder."""
    ckpt = Path(run_dir) / "ckpt"
    if latest_step(ckpt) is None:
        raise FileNotFoundError(f"no checkpoint in {ckpt} (train with `equibim train` first)")
    # Read the config first, then restore into a template built from it.
    import orbax.checkpoint as ocp

    mngr = ocp.CheckpointManager(ckpt.absolute())
    try:
        saved = mngr.restore(latest_step(ckpt), args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
    except Exception as e:
        raise CheckpointError(f"{ckpt}: cannot read the config ({e})") from e
    finally:
        mngr.close()
    try:
        policy_cfg = config_from_dict(PolicyConfig, saved["policy"])
        train_cfg = config_from_dict(TrainConfig, saved["train"])
        spec = config_from_dict(EnvSpec, saved["env"])
    except (KeyError, ValueError, TypeError) as e:
        raise CheckpointError(f"{ckpt}: config is not a train_policy config ({e})") from e
    template, model = create_train_state(policy_cfg, train_cfg)
    state, normalizer, config = restore_checkpoint(ckpt, template)
    config = dict(config, env_spec=spec)
    return model, state, normalizer, config


# ----------------------------------------------------------------------------- evaluate
def open_loop_errors(model, normalizer: Normalizer, params: Mapping[str, Any], demos: Demos,
                     env: Env, n_windows: int = 128, seed: int = 0) -> dict:
    """Open-loop action error on demo windows and on their mirror images, and the
    equivariance error of the sampled actions.

    For ``n_windows`` random windows of ``demos`` (and the same windows mirrored by ``S``,
    observations and actions alike), sample an action chunk with DDIM (noise ``z`` on the
    demos, ``S_a z`` on the mirrored windows) and compare the executed part (``Ta`` steps
    from the current frame) with the expert's, in raw units. ``"equivariance"`` compares
    the two samples with each other: ``|S pi(S O, S_a z) - pi(O, z)|``, 0 for an exactly
    equivariant policy whatever its fit. Unlike the relative error of the noise prediction
    logged in training, it is in the units the robot executes: two policies with the same
    noise-prediction error were measured 1.5x apart in action error (README).
    Arm joints and gripper openings are reported apart: ``{name: {"demos": {"arm_rad",
    "gripper"}, "mirrored_demos": {...}, "equivariance": {...}}}``, mean absolute errors;
    ``"equivariance"`` also holds ``"per_dim_normalized_rms"``, the gap per action
    dimension in normalised units (where in the action the symmetry breaks).
    The mirrored windows are exactly what the expert does on the other side, so a policy
    that generalises by symmetry has the same error on both.
    """
    from equibim_jax.policies import sample_actions

    cfg = model.config
    frames, ends = frames_from_demos(demos)
    fields = tuple(cfg.encoder.keys)
    frames = {k: frames[k] for k in (*fields, "action")}
    dataset = make_dataset(normalizer.normalize(frames), ends, cfg)
    sym = normalized_symmetry(raw_symmetry(env, fields), normalizer)
    s_a = field_op(sym, "action")
    key = jax.random.key(seed)
    batch = sample_batch(dataset, key, n_windows)
    mirrored = mirror_batch(sym, batch)
    n_arm = env.info.n_arm
    arm = np.r_[0:n_arm, n_arm + 1 : 2 * n_arm + 1]
    grip = np.array([n_arm, 2 * n_arm + 1])
    act = normalizer.fields["action"]
    start = cfg.obs_horizon - 1

    def executed(a):
        return act.unnormalize(a)[:, start : start + cfg.action_horizon]

    def split(d):
        return jnp.mean(d[..., arm]), jnp.mean(d[..., grip])

    @jax.jit
    def err(p):
        k = jax.random.fold_in(key, 1)
        a = sample_actions(model, p, {f: batch[f] for f in fields}, k)
        a_m = sample_actions(model, p, {f: mirrored[f] for f in fields}, k, noise_op=s_a)
        gap = (s_a(a_m) - a)[:, start : start + cfg.action_horizon]
        return ({"demos": split(jnp.abs(executed(a) - executed(batch["action"]))),
                 "mirrored_demos": split(jnp.abs(executed(a_m) - executed(mirrored["action"]))),
                 "equivariance": split(jnp.abs(executed(s_a(a_m)) - executed(a)))},
                jnp.sqrt(jnp.mean(jnp.square(gap), axis=(0, 1))))

    out = {}
    for name, p in params.items():
        res, per_dim = jax.device_get(err(p))
        out[name] = {which: {"arm_rad": float(e_arm), "gripper": float(e_grip)}
                     for which, (e_arm, e_grip) in res.items()}
        out[name]["equivariance"]["per_dim_normalized_rms"] = [float(x) for x in per_dim]
    return out


def evaluate_policies(spec: EnvSpec, model, normalizer: Normalizer, params: Mapping[str, Any],
                      n_episodes: int, seed: int = 0, sides=("trained", "mirrored"),
                      chunk: int = 32, progress: bool = True) -> dict:
    """Closed-loop success of several parameter sets of one model, on both sides.

    All parameter sets share one compiled rollout and the same episode keys (paired
    comparison); the mirrored side starts each episode from the mirror image of the
    trained side's initial state (``env.mirror_state``).

    Returns:
      ``{name: {side: {success, ci95, episodes, successes, per_episode, ...}}}``.
    """
    env = spec.make()
    rollout = make_policy_rollout(env, model, normalizer)
    key = jax.random.key(seed)
    return {name: evaluate_sides(rollout, p, key, n_episodes, chunk=min(chunk, 32), sides=sides,
                                 progress=progress, desc=f"eval {name}")
            for name, p in params.items()}


def evaluate_checkpoint(run_dir: str | Path, n_episodes: int, seed: int = 0,
                        sides=("trained", "mirrored"), progress: bool = True) -> dict:
    """Evaluate the EMA parameters of a :func:`train_policy` run on both sides."""
    model, state, normalizer, config = load_policy(run_dir)
    res = evaluate_policies(config["env_spec"], model, normalizer, {"policy": state.ema_params},
                            n_episodes, seed=seed, sides=sides, progress=progress)["policy"]
    return res
