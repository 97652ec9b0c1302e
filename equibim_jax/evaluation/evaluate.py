"""Closed-loop evaluation of trained runs on the trained side and its mirror image."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax

from equibim_jax.config import EvalConfig
from equibim_jax.data.normalizer import Normalizer
from equibim_jax.evaluation.rollout import evaluate_sides, make_policy_rollout, mirror_pair_gap
from equibim_jax.policies.base import Policy
from equibim_jax.sim.env import Env

__all__ = ["evaluate_policies", "evaluate_run"]


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
    batch = min(config.batch, 32)
    if config.mirror_noise:
        return {name: mirror_pair_gap(env, policy, normalizer, p, key, config.episodes, chunk=batch,
                                      progress=progress)
                for name, p in params.items()}
    rollout = make_policy_rollout(env, policy, normalizer, temporal_ensemble=config.temporal_ensemble)
    return {name: evaluate_sides(rollout, p, key, config.episodes, chunk=batch, progress=progress,
                                 desc=f"eval {name}")
            for name, p in params.items()}


def evaluate_run(run_dir: str | Path, config: EvalConfig = EvalConfig(), env: Env | None = None,
                 progress: bool = True) -> dict:
    """Evaluate the EMA parameters of a training run (``equibim train``) on both sides.

    Args:
      run_dir: the run folder. config: evaluation settings.
      env: the run's env if already built (else built from the run's task config).
    Returns:
      ``{"trained": summary, "mirrored": summary}`` (see :func:`evaluate_policies`).
    """
    from equibim_jax.training.run import load_run

    run = load_run(run_dir)
    env = env if env is not None else run.make_env()
    return evaluate_policies(env, run.policy, run.normalizer, {"policy": run.state.ema_params}, config,
                             progress=progress)["policy"]
