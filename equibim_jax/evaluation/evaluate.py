"""Closed-loop evaluation of trained runs on the trained side and its mirror image."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from equibim_jax.config import EvalConfig
from equibim_jax.data.normalizer import Normalizer
from equibim_jax.evaluation.rollout import evaluate_sides, make_policy_rollout, mirror_pair_gap
from equibim_jax.policies.base import Policy
from equibim_jax.sim.env import Env

__all__ = ["evaluate_policies", "evaluate_run", "episode_records", "episode_steps", "heldout_equivariance",
           "write_jsonl"]


def evaluate_policies(env: Env, policy: Policy, normalizer: Normalizer, params: Mapping[str, Any],
                      config: EvalConfig = EvalConfig(), progress: bool = True) -> dict:
    """Closed-loop success of several parameter sets of one policy, on both sides.

    All parameter sets share one compiled rollout and the same episode keys (paired
    comparison); the mirrored side starts each episode from the mirror image of the
    trained side's initial state (``env.mirror_state``).

    Returns:
      ``{name: {"trained": summary, "mirrored": summary}}``, summaries as
      :func:`~equibim_jax.evaluation.rollout.evaluate_sides` gives them. With
      ``config.mirror_noise`` each entry is :func:`~equibim_jax.evaluation.rollout.mirror_pair_gap`'s
      result instead.
    """
    key = jax.random.key(config.seed)
    batch = config.batch
    if config.mirror_noise:
        return {name: mirror_pair_gap(env, policy, normalizer, p, key, config.episodes, chunk=batch,
                                      progress=progress)
                for name, p in params.items()}
    rollout = make_policy_rollout(env, policy, normalizer, temporal_ensemble=config.temporal_ensemble)
    return {name: evaluate_sides(rollout, p, key, config.episodes, chunk=batch, progress=progress,
                                 desc=f"eval {name}")
            for name, p in params.items()}


def episode_steps(env: Env, policy: Policy, length: int | None = None) -> int:
    """Control steps of one evaluation episode: ``ceil(length / Ta) * Ta`` (``length``
    defaults to the env's ``episode_length``), as ``make_policy_rollout`` runs them."""
    ta = int(policy.config.action_horizon)
    return math.ceil(int(env.config.episode_length if length is None else length) / ta) * ta


def episode_records(result: Mapping[str, Any], steps_limit: int) -> list[dict]:
    """One record per episode and side of an evaluation result, for a JSON-lines table.

    Args:
      result: ``{"trained": summary, "mirrored": summary, ...}`` (one entry of
        :func:`evaluate_policies`, or :func:`evaluate_run`'s result); other keys are ignored.
      steps_limit: control steps per episode (:func:`episode_steps`).
    Returns:
      ``[{"episode": i (index of the episode key: ``jax.random.split(key(seed), n)[i]``,
      the same on both sides), "side": "trained" | "mirrored", "success": bool,
      "steps": steps to success, or ``steps_limit`` for a failure, "nan_actions": int,
      "any_nan": bool}, ...]``, trained side first. With ``mirror_noise`` summaries (no
      per-step data) ``steps``, ``nan_actions`` and ``any_nan`` are ``None``.
    """
    out = []
    for side in ("trained", "mirrored"):
        if side not in result:
            continue
        r = result[side]
        first = r.get("first_success_step")
        nan = r.get("nan_per_episode")
        for i, ok in enumerate(r["per_episode"]):
            steps = None if first is None else (int(first[i]) + 1 if first[i] >= 0 else int(steps_limit))
            out.append({"episode": i, "side": side, "success": bool(ok), "steps": steps,
                        "nan_actions": None if nan is None else int(nan[i]),
                        "any_nan": None if nan is None else bool(nan[i] > 0)})
    return out


def write_jsonl(path: str | Path, rows: Sequence[Mapping]) -> Path:
    """Write ``rows`` as JSON lines, atomically (temporary file, then a rename)."""
    import json

    from equibim_jax._io import atomic_write_bytes

    atomic_write_bytes(path, "".join(json.dumps(dict(r), sort_keys=True) + "\n" for r in rows).encode())
    return Path(path)


def heldout_equivariance(env: Env, policy: Policy, normalizer: Normalizer, params: Any, key: jax.Array,
                         n_demos: int = 4, n_windows: int = 64) -> dict:
    """Equivariance error of a policy on windows of fresh expert demos (held out: their
    starts are drawn from ``key``, which training's demos did not use).

    Generates ``n_demos`` successful expert episodes in ``env`` (in memory; for an
    end-effector-action env, in its joint-action twin, with the demos' actions read in the
    end-effector space), then measures
    on ``n_windows`` random windows of them (and their mirror images):
    ``"relative"``, what training logs as ``equiv_err`` (the relative error of what
    ``L_sym`` compares, ``training.losses.equivariance_error``: 0 for an exactly
    equivariant policy, about 2 for unrelated predictions); and
    ``open_loop_errors``'s result (``"equivariance"`` of the sampled actions in rad and
    gripper units, the action errors on the demos and on their mirror images).

    Returns:
      ``{"demos": n_demos, "windows": n_windows, "relative": float, "equivariance": {...},
      "demos_error": {...}, "mirrored_demos_error": {...}}``.
    """
    from equibim_jax.data.generate import generate_demos
    from equibim_jax.data.windows import sample_batch
    from equibim_jax.evaluation.open_loop import open_loop_errors
    from equibim_jax.training.losses import equivariance_error
    from equibim_jax.training.run import prepare_data

    if n_demos < 1 or n_windows < 1:
        raise ValueError(f"n_demos and n_windows must be >= 1, got {n_demos}, {n_windows}")
    k_demo, k_win = jax.random.split(key)
    gen_env = env
    if env.config.action == "ee":
        # The scripted experts emit joint actions: generate in the joint-action twin of the
        # env (same task and options) and read the demos' end-effector actions, as the
        # experiment runner does for its EE cells.
        from equibim_jax.tasks import make_env

        gen_env = make_env(env.task, **{**dict(env.task_options), "action": "joint"})
    demos, _ = generate_demos(gen_env, k_demo, int(n_demos), chunk=min(int(n_demos), 32), progress=False)
    if gen_env is not env:
        demos = demos.in_action_space("ee")
    prep = prepare_data(demos, env, policy.config, normalizer)
    batch = sample_batch(prep.dataset, k_win, int(n_windows))
    rel = float(jax.jit(lambda p: equivariance_error(policy, p, batch, jax.random.fold_in(k_win, 1),
                                                     prep.sym))(params))
    seed = int(jax.random.randint(k_win, (), 0, 2**31 - 1))
    ol = open_loop_errors(policy, normalizer, {"p": params}, demos, env, n_windows=int(n_windows), seed=seed)["p"]
    return {"demos": int(n_demos), "windows": int(n_windows), "relative": rel,
            "equivariance": ol["equivariance"], "demos_error": ol["demos"],
            "mirrored_demos_error": ol["mirrored_demos"]}


HELDOUT_KEY = 0x4E1D
"""``fold_in`` constant of the held-out demos' key: ``fold_in(key(EvalConfig.seed), HELDOUT_KEY)``."""


def evaluate_run(run_dir: str | Path, config: EvalConfig = EvalConfig(), env: Env | None = None,
                 progress: bool = True, *, out_dir: str | Path | None = None,
                 video_episodes: Sequence[int] = (), video_size: int = 128, video_format: str = "gif",
                 video_fps: int = 20, video_every: int = 1, equivariance_demos: int = 0,
                 equivariance_windows: int = 64) -> dict:
    """Evaluate the EMA parameters of a training run (``equibim train``) on both sides.

    Args:
      run_dir: the run folder, or a :class:`~equibim_jax.training.run.Run` already loaded
        (``load_run``; its ``state.ema_params`` are evaluated). config: evaluation settings.
      env: the run's env if already built (else built from the run's task config).
      out_dir: if given, write ``eval.json`` (the result), ``episodes.jsonl`` (the
        per-episode records) and the videos (``videos/``) here; with videos and no
        ``out_dir`` the videos go to ``run_dir/eval/videos``.
      video_episodes: episode indices (each in ``[0, config.episodes)``) to film, each as
        the episode beside its mirrored twin (``evaluation.videos``), ``video_size`` pixels
        a side per half, ``video_format`` ``"gif"`` or ``"mp4"``, ``video_fps`` frames per
        second, every ``video_every``-th control step.
      equivariance_demos: if > 0, also measure the equivariance error on
        ``equivariance_windows`` windows of that many fresh expert demos
        (:func:`heldout_equivariance`, key ``fold_in(key(config.seed), HELDOUT_KEY)``).
    Returns:
      ``{"trained": summary, "mirrored": summary}`` (see :func:`evaluate_policies`), plus
      ``"records"`` (:func:`episode_records`), ``"steps_limit"``, and where asked
      ``"equivariance"`` and ``"videos"`` (per video: path, frame count, size, success on
      both sides and ``"matches_evaluation"``: the refilmed episode succeeded as in the
      evaluation).
    Raises:
      ValueError: a video episode outside the evaluation, an unknown video format, or a
        negative ``equivariance_demos``; checked before anything runs.
    """
    from equibim_jax.evaluation.videos import VIDEO_FORMATS, check_episodes
    from equibim_jax.training.run import Run, load_run

    video_episodes = check_episodes(video_episodes, config.episodes)
    if video_format not in VIDEO_FORMATS:
        raise ValueError(f"video format must be one of {VIDEO_FORMATS}, got {video_format!r}")
    if equivariance_demos < 0:
        raise ValueError(f"equivariance_demos must be >= 0, got {equivariance_demos}")
    if isinstance(run_dir, Run):
        run, run_dir = run_dir, None
    else:
        run = load_run(run_dir)
    env = env if env is not None else run.make_env()
    params = run.state.ema_params
    roll_q = None
    if config.mirror_noise:
        res = evaluate_policies(env, run.policy, run.normalizer, {"policy": params}, config,
                                progress=progress)["policy"]
    else:
        # The rollout that also records qpos: the video pass below reruns its compiled program.
        roll_q = _qpos_rollout(env, run.policy, run.normalizer, config.temporal_ensemble)
        res = evaluate_sides(roll_q, params, jax.random.key(config.seed), config.episodes,
                             chunk=config.batch, progress=progress, desc="eval policy")
    limit = episode_steps(env, run.policy)
    res = {**res, "steps_limit": limit, "records": episode_records(res, limit)}
    if equivariance_demos:
        key = jax.random.fold_in(jax.random.key(config.seed), HELDOUT_KEY)
        res["equivariance"] = heldout_equivariance(env, run.policy, run.normalizer, params, key,
                                                   equivariance_demos, equivariance_windows)
    if video_episodes:
        from equibim_jax.evaluation.videos import write_paired_videos

        if out_dir is None and run_dir is None:
            raise ValueError("videos of a loaded Run need out_dir")
        vdir = Path(out_dir) / "videos" if out_dir is not None else Path(run_dir) / "eval" / "videos"
        vids = write_paired_videos(env, run.policy, run.normalizer, params, config, video_episodes, vdir,
                                   size=video_size, fmt=video_format, fps=video_fps, every=video_every,
                                   rollout=roll_q)
        for v in vids:
            i = v["episode"]
            v["matches_evaluation"] = (v["success"] == bool(res["trained"]["per_episode"][i])
                                       and v["mirror_success"] == bool(res["mirrored"]["per_episode"][i]))
        res["videos"] = vids
    if out_dir is not None:
        from equibim_jax._io import atomic_write_json

        out_dir = Path(out_dir)
        write_jsonl(out_dir / "episodes.jsonl", res["records"])
        atomic_write_json(out_dir / "eval.json", _jsonable(res))
    return res


_QPOS_ROLLOUTS: dict = {}


def _qpos_rollout(env: Env, policy: Policy, normalizer: Normalizer, temporal_ensemble: float | None):
    """``make_policy_rollout(..., record_qpos=True)``, one per (env, policy, normaliser,
    temporal_ensemble) objects (the last 4 kept), so that repeated evaluations of the same
    loaded objects reuse one compiled program."""
    k = (id(env), id(policy), id(normalizer), temporal_ensemble)
    hit = _QPOS_ROLLOUTS.get(k)
    if hit is None or hit[0] is not env or hit[1] is not policy or hit[2] is not normalizer:
        roll = make_policy_rollout(env, policy, normalizer, record_qpos=True, temporal_ensemble=temporal_ensemble)
        hit = (env, policy, normalizer, roll)
        _QPOS_ROLLOUTS[k] = hit
        while len(_QPOS_ROLLOUTS) > 4:
            _QPOS_ROLLOUTS.pop(next(iter(_QPOS_ROLLOUTS)))
    return hit[3]


def _jsonable(x):
    """``x`` with numpy scalars and arrays turned into Python numbers and lists, dict keys into str."""
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x
