"""Open-loop checks of a trained policy on demo windows: action error on the demos and on
their mirror images, and the equivariance of the sampled actions."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax.data.dataset import Demos
from equibim_jax.data.normalizer import Normalizer, normalized_symmetry
from equibim_jax.data.windows import frames_from_demos, make_dataset, sample_batch
from equibim_jax.policies.base import Policy
from equibim_jax.sim.env import Env
from equibim_jax.training.losses import mirror_batch

__all__ = ["open_loop_errors", "error_groups", "describe_errors"]


def error_groups(env: Env) -> dict[str, np.ndarray]:
    """``{name: action channel indices}`` the errors are averaged over, by the env's action
    layout: joint actions ``{"arm_rad", "gripper"}`` (arm joints in rad, openings);
    end-effector actions ``{"position_m", "rotation", "gripper"}`` (site positions in m,
    rotation entries, 6D or quaternion, unitless, openings)."""
    if env.config.action == "joint":
        n = env.info.n_arm
        return {"arm_rad": np.r_[0:n, n + 1 : 2 * n + 1], "gripper": np.array([n, 2 * n + 1])}
    r = env.rot_dim
    per = 3 + r + 1
    return {"position_m": np.r_[0:3, per : per + 3], "rotation": np.r_[3 : 3 + r, per + 3 : per + 3 + r],
            "gripper": np.array([per - 1, 2 * per - 1])}


_UNITS = {"arm_rad": ("arm", " rad"), "position_m": ("position", " m"), "rotation": ("rotation", ""),
          "gripper": ("gripper", "")}


def describe_errors(d: Mapping[str, Any]) -> str:
    """One line for an error dict of :func:`open_loop_errors`, e.g. ``"arm 0.0031 rad,
    gripper 0.012"`` or ``"position 0.0021 m, rotation 0.0040, gripper 0.012"``."""
    return ", ".join(f"{_UNITS[k][0]} {d[k]:.4f}{_UNITS[k][1]}" for k in _UNITS if k in d)


def open_loop_errors(policy: Policy, normalizer: Normalizer, params: Mapping[str, Any], demos: Demos,
                     env: Env, n_windows: int = 128, seed: int = 0) -> dict:
    """Open-loop action errors and the equivariance error of the sampled actions.

    For ``n_windows`` random windows of ``demos`` (and the same windows mirrored by ``S``,
    observations and actions alike), sample an action chunk (noise ``z`` on the demos,
    ``S_a z`` on the mirrored windows) and compare the executed part (``Ta`` steps from the
    current frame) with the expert's, in raw units. ``"equivariance"`` compares the two
    samples with each other, ``|S pi(S O, S_a z) - pi(O, z)|``: 0 for an exactly
    equivariant policy whatever its fit, and in the units the robot executes. The mirrored
    windows are what the expert does on the other side, so a policy that generalises by
    symmetry has the same error on both.

    Args:
      policy: the policy. normalizer: its normaliser (mirror-consistent).
      params: ``{name: parameters}``; all share one compiled function.
      demos: the demonstrations. env: their env (its ``S`` and arm layout).
    Returns:
      ``{name: {"demos": {group: error}, "mirrored_demos": {...}, "equivariance": {...,
      "per_dim_normalized_rms": [A]}}}``: mean absolute errors per group of action
      channels (:func:`error_groups`: ``arm_rad`` and ``gripper`` for joint actions,
      ``position_m``, ``rotation`` and ``gripper`` for end-effector actions), and the gap
      per action dimension in normalised units.
    """
    cfg = policy.config
    fields = tuple(cfg.obs_keys)
    frames, ends = frames_from_demos(demos, fields)
    dataset = make_dataset(normalizer.normalize(frames), ends, cfg)
    sym = normalized_symmetry(env.symmetry_ops(fields), normalizer)
    s_a = sym["action"]
    key = jax.random.key(seed)
    batch = sample_batch(dataset, key, n_windows)
    mirrored = mirror_batch(sym, batch)
    groups = error_groups(env)
    size = max(int(i.max()) for i in groups.values()) + 1
    if batch["action"].shape[-1] != size:
        raise ValueError(f"open_loop_errors: the actions have {batch['action'].shape[-1]} channels; the env's "
                         f"{env.config.action!r} action layout has {size}")
    act = normalizer.fields["action"]
    start = cfg.obs_horizon - 1

    def executed(a):
        return act.unnormalize(a)[:, start : start + cfg.action_horizon]

    def split(d):
        return {k: jnp.mean(d[..., idx]) for k, idx in groups.items()}

    @jax.jit
    def err(p):
        k = jax.random.fold_in(key, 1)
        a = policy.sample(p, {f: batch[f] for f in fields}, k, None)
        a_m = policy.sample(p, {f: mirrored[f] for f in fields}, k, s_a)
        gap = (s_a(a_m) - a)[:, start : start + cfg.action_horizon]
        return ({"demos": split(jnp.abs(executed(a) - executed(batch["action"]))),
                 "mirrored_demos": split(jnp.abs(executed(a_m) - executed(mirrored["action"]))),
                 "equivariance": split(jnp.abs(executed(s_a(a_m)) - executed(a)))},
                jnp.sqrt(jnp.mean(jnp.square(gap), axis=(0, 1))))

    out = {}
    for name, p in params.items():
        res, per_dim = jax.device_get(err(p))
        out[name] = {which: {k: float(v) for k, v in errs.items()} for which, errs in res.items()}
        out[name]["equivariance"]["per_dim_normalized_rms"] = [float(x) for x in per_dim]
    return out
