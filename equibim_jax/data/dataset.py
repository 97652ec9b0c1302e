"""On-disk demonstration datasets (zarr), written atomically and validated on load.

Layout of a dataset directory ``NAME.zarr``::

    obs/<field>      [E, T, ...]   observations per episode and step (``qpos``, ``point_cloud``, ...)
    action           [E, T, A]     the expert's actions
    length           [E]           valid steps of each episode (the rest is padding)
    success          [E]           whether the episode succeeded
    side             [E]           +1 left / -1 right (the task's side), 0 if none
    attrs["equibim"] metadata: format, version, task, env config, seed, counts, fields

Writing goes to a temporary sibling directory that is renamed into place, so a crash never
leaves a half-written dataset where a good one was.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Mapping

import numpy as np
import zarr

FORMAT = "equibim-demos"
VERSION = 1


class DatasetError(ValueError):
    """A dataset on disk is missing, corrupt, or does not match what was asked for."""


@dataclasses.dataclass(frozen=True)
class Demos:
    """Episodes in memory.

    Attributes:
      obs: field -> [E, T, ...] arrays.
      action: [E, T, A].
      length: int32 [E], valid steps per episode.
      success: bool [E].
      side: float32 [E].
      meta: JSON-serialisable metadata (task, env config, seed, ...).
    """

    obs: Mapping[str, np.ndarray]
    action: np.ndarray
    length: np.ndarray
    success: np.ndarray
    side: np.ndarray
    meta: Mapping

    def __post_init__(self):
        validate(self)

    @property
    def n_episodes(self) -> int:
        return int(self.action.shape[0])

    @property
    def n_steps(self) -> int:
        """Total valid steps over all episodes."""
        return int(self.length.sum())


def validate(d: Demos) -> None:
    """Raise :class:`DatasetError` naming the first inconsistency in ``d``."""
    if d.action.ndim != 3:
        raise DatasetError(f"action must be [E, T, A], got shape {d.action.shape}")
    e, t, _ = d.action.shape
    if not d.obs:
        raise DatasetError("dataset has no observation fields")
    for k, v in d.obs.items():
        if v.shape[:2] != (e, t):
            raise DatasetError(f"obs/{k} has shape {v.shape}; expected leading dims ({e}, {t})")
        if np.issubdtype(v.dtype, np.floating) and not np.all(np.isfinite(v)):
            raise DatasetError(f"obs/{k} contains NaN or inf")
    if not np.all(np.isfinite(d.action)):
        raise DatasetError("action contains NaN or inf")
    for name, arr in (("length", d.length), ("success", d.success), ("side", d.side)):
        if arr.shape != (e,):
            raise DatasetError(f"{name} has shape {arr.shape}; expected ({e},)")
    if np.any(d.length < 1) or np.any(d.length > t):
        raise DatasetError(f"episode lengths must be in [1, {t}], got min {d.length.min()} max {d.length.max()}")
    try:
        json.dumps(dict(d.meta))
    except TypeError as err:
        raise DatasetError(f"metadata is not JSON-serialisable: {err}") from None


def save(demos: Demos, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``demos`` to ``path`` (a ``.zarr`` directory) atomically.

    Raises:
      FileExistsError: ``path`` exists and ``overwrite`` is False.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        g = zarr.open_group(str(tmp), mode="w")
        e = demos.n_episodes
        for k, v in demos.obs.items():
            g.create_array(f"obs/{k}", shape=v.shape, dtype=v.dtype, chunks=(1,) + v.shape[1:])[:] = v
        g.create_array("action", shape=demos.action.shape, dtype=demos.action.dtype,
                       chunks=(1,) + demos.action.shape[1:])[:] = demos.action
        for name, arr in (("length", demos.length.astype(np.int32)), ("success", demos.success.astype(bool)),
                          ("side", demos.side.astype(np.float32))):
            g.create_array(name, shape=(e,), dtype=arr.dtype)[:] = arr
        g.attrs["equibim"] = {
            "format": FORMAT, "version": VERSION, "n_episodes": e, "n_steps": demos.n_steps,
            "obs_fields": sorted(demos.obs), "action_dim": int(demos.action.shape[-1]),
            "horizon": int(demos.action.shape[1]), **dict(demos.meta),
        }
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def load(path: str | os.PathLike, expect: Mapping | None = None) -> Demos:
    """Load and validate a dataset.

    Args:
      path: the ``.zarr`` directory.
      expect: metadata entries that must match (e.g. ``{"task": "place_empty_cup"}``).
    Raises:
      DatasetError: missing, not a dataset of this format, corrupt, or not as expected.
    """
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"no dataset at {path}")
    try:
        g = zarr.open_group(str(path), mode="r")
        meta = dict(g.attrs.get("equibim", {}))
    except Exception as err:  # zarr raises several types for broken stores
        raise DatasetError(f"{path} is not a readable zarr dataset: {err}") from None
    if meta.get("format") != FORMAT:
        raise DatasetError(f"{path} is not an {FORMAT} dataset (metadata: {meta or 'none'})")
    if meta.get("version") != VERSION:
        raise DatasetError(f"{path} has format version {meta.get('version')}; this code reads {VERSION}")
    try:
        obs = {k: np.asarray(g[f"obs/{k}"][:]) for k in meta["obs_fields"]}
        demos = Demos(
            obs=obs, action=np.asarray(g["action"][:]), length=np.asarray(g["length"][:]),
            success=np.asarray(g["success"][:]), side=np.asarray(g["side"][:]),
            meta={k: v for k, v in meta.items()},
        )
    except DatasetError as err:
        raise DatasetError(f"{path}: {err}") from None
    except Exception as err:
        raise DatasetError(f"{path} is corrupt: {type(err).__name__}: {err}") from None
    if demos.n_episodes != meta.get("n_episodes") or demos.n_steps != meta.get("n_steps"):
        raise DatasetError(
            f"{path}: metadata says {meta.get('n_episodes')} episodes / {meta.get('n_steps')} steps, "
            f"arrays hold {demos.n_episodes} / {demos.n_steps}"
        )
    for k, v in (expect or {}).items():
        if meta.get(k) != v:
            raise DatasetError(f"{path}: expected {k}={v!r}, dataset has {meta.get(k)!r}")
    return demos
