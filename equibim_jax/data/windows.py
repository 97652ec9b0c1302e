"""Training windows over demonstration frames, kept on device.

A dataset is per-frame arrays (all episodes concatenated) plus index tables of windows:
``To`` observation frames and ``Tp`` action frames each, padded at episode edges by
repeating the edge frame, as Diffusion Policy's sequence sampler does. Batches are drawn
on device inside the jitted train step.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

Array = Any

__all__ = ["OnDeviceDataset", "frames_from_demos", "window_indices", "make_dataset", "sample_batch"]


def frames_from_demos(demos: Any, fields: tuple[str, ...] | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Concatenate the valid steps of every episode.

    Args:
      demos: an ``equibim_jax.data.dataset.Demos``.
      fields: observation fields to keep (default: all).
    Returns:
      ``({field: [F, ...], "action": [F, A]}, episode_ends [E])`` with ``F`` the total
      number of valid steps and ``episode_ends`` the exclusive end of each episode.
    """
    eps = range(demos.n_episodes)
    fields = tuple(demos.obs) if fields is None else tuple(fields)
    missing = [f for f in fields if f not in demos.obs]
    if missing:
        raise KeyError(f"the dataset has no observation field(s) {missing}; it has {sorted(demos.obs)}")
    frames = {k: np.concatenate([demos.obs[k][e, : demos.length[e]] for e in eps]) for k in fields}
    frames["action"] = np.concatenate([demos.action[e, : demos.length[e]] for e in eps])
    return frames, np.cumsum(demos.length).astype(np.int64)


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


def make_dataset(frames: Mapping[str, Array], episode_ends: Array, config: Any) -> OnDeviceDataset:
    """Put normalised frames on device with windows as Diffusion Policy pads them.

    Args:
      frames: ``{field: [F, ...]}`` normalised frames; must hold the action field and
        the policy's observation fields.
      episode_ends: ``[E]`` exclusive episode ends (``episode_ends[-1] == F``).
      config: a policy config (``obs_keys``, ``action_key`` and the horizons).
    Returns:
      :class:`OnDeviceDataset` with ``pad_before = To - 1``, ``pad_after = Ta - 1``.
    """
    keys = tuple(config.obs_keys)
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
