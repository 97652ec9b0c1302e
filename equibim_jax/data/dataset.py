"""On-disk demonstration datasets (zarr), written atomically and validated on load.

Layout of a dataset directory ``NAME.zarr``::

    obs/<field>      [E, T, ...]   observations per episode and step (``qpos``, ``point_cloud``, ...)
    action           [E, T, A]     the expert's actions
    length           [E]           valid steps of each episode (the rest is padding)
    success          [E]           whether the episode succeeded
    attrs["equibim"] metadata: format, version, counts, fields, and the caller's ``Demos.meta``
                     (task, env config, seed, a task's per-episode info, ...)

Format versions: 2 (this code). Version 1 also stored a per-episode ``side`` array;
:func:`load` rejects it (regenerate such a dataset with ``equibim generate``).

Writing goes to a temporary sibling directory that is complete (and fsynced) before it is
moved into place, so a crash never leaves a half-written dataset where a good one was. A new
dataset is renamed into place. An existing one is replaced, on Linux, by atomically
exchanging the two directories (``renameat2(RENAME_EXCHANGE)``), so a dataset is under the
final name at every moment; where that is unavailable (other systems, glibc < 2.28, a
filesystem without the flag) it falls back to two renames, old away then new in, which
leaves a short gap with no dataset under the final name.
"""

from __future__ import annotations

import ctypes
import dataclasses
import errno
import functools
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Mapping

import numpy as np
import zarr

FORMAT = "equibim-demos"
VERSION = 2


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
      meta: JSON-serialisable metadata (task, env config, seed, a task's per-episode info, ...).
      action_ee: optional [E, T, A_ee], the same actions in the end-effector space (per
        arm: position, rotation, opening; see ``Env.ee_action_from_joint``) when
        ``action`` holds joint actions. :meth:`in_action_space` picks one.
    """

    obs: Mapping[str, np.ndarray]
    action: np.ndarray
    length: np.ndarray
    success: np.ndarray
    meta: Mapping
    action_ee: np.ndarray | None = None

    def __post_init__(self):
        validate(self)

    @property
    def n_episodes(self) -> int:
        return int(self.action.shape[0])

    @property
    def action_spaces(self) -> tuple[str, ...]:
        """The action spaces this dataset holds: ``("joint",)`` or ``("joint", "ee")``."""
        return ("joint", "ee") if self.action_ee is not None else ("joint",)

    def in_action_space(self, space: str) -> "Demos":
        """These demos with ``action`` in ``space`` (``"joint"`` or ``"ee"``).

        The metadata's ``task_options["action"]`` is set to ``space``, so that the env
        rebuilt from the metadata takes actions of that space.

        Raises:
          DatasetError: the dataset does not hold actions in ``space``.
        """
        if space not in ("joint", "ee"):
            raise DatasetError(f"action space must be 'joint' or 'ee', got {space!r}")
        if space not in self.action_spaces:
            raise DatasetError(f"this dataset holds {list(self.action_spaces)} actions, not {space!r} "
                               f"(regenerate it with `equibim generate` to record both)")
        if space == "joint":
            return self
        meta = dict(self.meta)
        if isinstance(meta.get("task_options"), Mapping):
            meta["task_options"] = {**meta["task_options"], "action": "ee"}
        return dataclasses.replace(self, action=self.action_ee, action_ee=None,
                                   meta={**meta, "action_space": "ee"})

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
    if d.action_ee is not None:
        if d.action_ee.ndim != 3 or d.action_ee.shape[:2] != (e, t):
            raise DatasetError(f"action_ee has shape {d.action_ee.shape}; expected ({e}, {t}, A_ee)")
        if not np.all(np.isfinite(d.action_ee)):
            raise DatasetError("action_ee contains NaN or inf")
    for name, arr in (("length", d.length), ("success", d.success)):
        if arr.shape != (e,):
            raise DatasetError(f"{name} has shape {arr.shape}; expected ({e},)")
    if np.any(d.length < 1) or np.any(d.length > t):
        raise DatasetError(f"episode lengths must be in [1, {t}], got min {d.length.min()} max {d.length.max()}")
    try:
        json.dumps(dict(d.meta))
    except TypeError as err:
        raise DatasetError(f"metadata is not JSON-serialisable: {err}") from None


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


@functools.lru_cache(maxsize=None)
def _renameat2():
    """libc's ``renameat2`` (ctypes function), or None where there is none (non-Linux, old libc)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap the directory entries ``a`` and ``b`` (both must exist).

    Returns False, having changed nothing, where ``renameat2(RENAME_EXCHANGE)`` is
    unavailable: no such libc function, or the kernel/filesystem answers ENOSYS or EINVAL.
    Raises:
      OSError: the exchange failed for another reason (errno and both paths in the message).
    """
    fn = _renameat2()
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL):
        return False
    raise OSError(err, f"renameat2(RENAME_EXCHANGE) of {a} and {b} failed: {os.strerror(err)}")


def _fsync_path(p: Path, directory: bool = False) -> None:
    if directory and os.name != "posix":  # directories cannot be opened for fsync there
        return
    fd = os.open(p, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as err:  # some filesystems cannot fsync a directory
        if err.errno not in (errno.EINVAL, errno.EBADF, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    """fsync every file and directory under ``root`` (files first), so renaming it is durable."""
    for dirpath, _, files in os.walk(root, topdown=False):
        for f in files:
            _fsync_path(Path(dirpath, f))
        _fsync_path(Path(dirpath), directory=True)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    else:
        p.unlink()


def _replace_with_gap(tmp: Path, path: Path) -> None:
    """Fallback replace: move ``path`` away, then ``tmp`` in. Between the two renames no
    dataset is at ``path``; if the second rename fails the old dataset is moved back."""
    old = path.with_name(f".{path.name}.old")
    if old.exists() or old.is_symlink():
        _remove(old)
    os.replace(path, old)
    try:
        os.replace(tmp, path)
    except BaseException:
        os.replace(old, path)
        raise
    _remove(old)


def _write(demos: Demos, root: Path) -> None:
    g = zarr.open_group(str(root), mode="w")
    e = demos.n_episodes
    for k, v in demos.obs.items():
        g.create_array(f"obs/{k}", shape=v.shape, dtype=v.dtype, chunks=(1,) + v.shape[1:])[:] = v
    g.create_array("action", shape=demos.action.shape, dtype=demos.action.dtype,
                   chunks=(1,) + demos.action.shape[1:])[:] = demos.action
    if demos.action_ee is not None:
        a = demos.action_ee
        g.create_array("action_ee", shape=a.shape, dtype=a.dtype, chunks=(1,) + a.shape[1:])[:] = a
    for name, arr in (("length", demos.length.astype(np.int32)), ("success", demos.success.astype(bool))):
        g.create_array(name, shape=(e,), dtype=arr.dtype)[:] = arr
    # The layout entries come last: metadata loaded from an older file must not override them.
    g.attrs["equibim"] = {
        **dict(demos.meta),
        "format": FORMAT, "version": VERSION, "n_episodes": e, "n_steps": demos.n_steps,
        "obs_fields": sorted(demos.obs), "action_dim": int(demos.action.shape[-1]),
        "horizon": int(demos.action.shape[1]), "action_spaces": list(demos.action_spaces),
    }


def save(demos: Demos, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``demos`` to ``path`` (a ``.zarr`` directory) atomically.

    The dataset is written in full to a temporary sibling ``.NAME.*.tmp`` and fsynced, then
    moved into place: renamed if ``path`` is new; if ``path`` exists (``overwrite=True``),
    exchanged with it atomically on Linux and the old dataset (now at the temporary name)
    deleted, or, where the exchange is unavailable, by two renames with a short gap (see the
    module docstring). If anything fails before the new dataset is in place, the temporary
    directory is removed and ``path`` keeps what it had.

    Raises:
      FileExistsError: ``path`` exists and ``overwrite`` is False.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        _write(demos, tmp)
        _fsync_tree(tmp)
        if path.exists() or path.is_symlink():
            if _exchange(tmp, path):
                _remove(tmp)  # the old dataset, now under the temporary name
            else:
                _replace_with_gap(tmp, path)
        else:
            os.replace(tmp, path)
        _fsync_path(path.parent, directory=True)
    except BaseException:
        if tmp.is_dir() and not tmp.is_symlink():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists() or tmp.is_symlink():
            tmp.unlink()
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
    version = meta.get("version")
    if version != VERSION:
        if isinstance(version, int) and version < VERSION:
            raise DatasetError(
                f"{path} is an {FORMAT} dataset of format version {version}, older than the "
                f"version {VERSION} this code reads; regenerate it with `equibim generate`"
            )
        raise DatasetError(f"{path} has format version {version!r}; this code reads version {VERSION}")
    try:
        obs = {k: np.asarray(g[f"obs/{k}"][:]) for k in meta["obs_fields"]}
        demos = Demos(
            obs=obs, action=np.asarray(g["action"][:]), length=np.asarray(g["length"][:]),
            success=np.asarray(g["success"][:]), meta={k: v for k, v in meta.items()},
            action_ee=np.asarray(g["action_ee"][:]) if "ee" in meta.get("action_spaces", ()) else None,
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
