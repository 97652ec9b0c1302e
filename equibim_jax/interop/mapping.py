"""The declared mapping between another format's features and our dataset fields.

A mapping is a small JSON file (or :class:`FeatureMapping`)::

    {
      "features": {"observation.state": "qpos",
                   "observation.images.top": "image",
                   "observation.images.left_wrist": "wrist_image[0]",
                   "observation.images.right_wrist": "wrist_image[1]",
                   "action": "action"},
      "names":   {"qpos": ["left_waist", ..., "gripper_left", ..., "gripper_right"]},
      "cameras": {"observation.images.top": "head"},
      "pairs":   [["gripper_left", "gripper_right"]],
      "fps": 50
    }

- ``features``: source key -> target. A target is ``"action"``, ``"action_ee"`` or an
  observation field of ours (``qpos``, ``ee``, ``image``, ``depth``, ``point_cloud``,
  ``wrist_image``, or any other name); ``FIELD[i]`` stacks several source images into
  view ``i`` of one field (``wrist_image[0]`` / ``[1]``: the left and right wrist cameras,
  [H, W, 3] each -> [2, H, W, 3]).
- ``names``: target field -> the name of each entry of its last axis (joint names of a
  joint-state vector). The mirror map is matched against them (:mod:`.symmetry`).
- ``cameras``: source image key -> the camera's name in the mirror map.
- ``pairs``: entries that are unchanged by the mirror but swap sides (gripper openings).
- ``fps``: frames per second (when the source does not record it).

Every entry but ``features`` is optional; :func:`default_mapping` gives each format's
defaults. Nothing here touches arrays: the readers in :mod:`.dp3` and :mod:`.lerobot`
apply a mapping and validate what they read against it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import Any, Mapping

from equibim_jax.data.dataset import DatasetError

__all__ = ["InteropError", "FeatureMapping", "parse_target", "load_mapping", "default_mapping", "require",
           "DEFAULT_PAIRS", "DP3_KEYS", "LEROBOT_KEYS"]

DEFAULT_PAIRS = (("gripper_left", "gripper_right"),)
"""Mirror-invariant entries that swap sides: the gripper openings of our joint layout."""

DP3_KEYS = {"qpos": "state", "action": "action", "point_cloud": "point_cloud", "image": "img",
            "depth": "depth", "ee": "ee", "action_ee": "action_ee"}
"""Our field -> the DP3 / Diffusion Policy ReplayBuffer key (``data/<key>``) on export.
``wrist_image`` is written as one key per camera, ``img_<camera>``."""

LEROBOT_KEYS = {"qpos": "observation.state", "action": "action", "ee": "observation.ee_pose",
                "depth": "observation.depth", "point_cloud": "observation.point_cloud",
                "action_ee": "action_ee"}
"""Our field -> the LeRobot feature on export; images become ``observation.images.<camera>``."""

_TARGET = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?$")


class InteropError(DatasetError):
    """Data or a mapping in another format does not fit: the message names the problem."""


def require(module: str):
    """Import an optional dependency of the interop extra, or raise a clear ImportError."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{module} is needed to read and write other dataset formats; install it with "
                          f"`pip install 'equibim-jax[interop]'` ({e})") from None


def parse_target(target: str) -> tuple[str, int | None]:
    """``"qpos"`` -> ``("qpos", None)``; ``"wrist_image[1]"`` -> ``("wrist_image", 1)``."""
    m = _TARGET.match(str(target))
    if not m:
        raise InteropError(f"mapping target {target!r} is not a field name or FIELD[i]")
    return m.group(1), (int(m.group(2)) if m.group(2) is not None else None)


@dataclasses.dataclass(frozen=True)
class FeatureMapping:
    """Source features -> our fields (module docstring). All entries are JSON-ready."""

    features: Mapping[str, str]
    names: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    cameras: Mapping[str, str] = dataclasses.field(default_factory=dict)
    pairs: tuple[tuple[str, str], ...] = DEFAULT_PAIRS
    fps: float | None = None

    def __post_init__(self):
        feats = dict(self.features)
        if not feats:
            raise InteropError("mapping has no features")
        views: dict[str, list[int]] = {}
        for src, tgt in feats.items():
            field, idx = parse_target(tgt)
            if field in ("action", "action_ee") and idx is not None:
                raise InteropError(f"mapping: {src!r} -> {tgt!r}: {field} cannot be indexed")
            if idx is not None:
                views.setdefault(field, []).append(idx)
        targets = [t for t in feats.values() if parse_target(t)[1] is None]
        dup = sorted({t for t in targets if targets.count(t) > 1})
        if dup:
            raise InteropError(f"mapping: several source features map to {dup}")
        for field, idx in views.items():
            if sorted(idx) != list(range(len(idx))):
                raise InteropError(f"mapping: the views of {field!r} must be {field}[0] .. {field}[{len(idx) - 1}] "
                                   f"once each, got indices {sorted(idx)}")
            if field in targets:
                raise InteropError(f"mapping: {field!r} is both a whole field and indexed views")
        if "action" not in targets:
            raise InteropError(f"mapping: no source feature maps to 'action' (features: {feats})")
        bad_cams = sorted(set(self.cameras) - set(feats))
        if bad_cams:
            raise InteropError(f"mapping: cameras are declared for {bad_cams}, which are not mapped features")
        names = {}
        for k, v in dict(self.names).items():
            if not isinstance(v, (list, tuple)) or not all(isinstance(s, str) for s in v):
                raise InteropError(f"mapping: names[{k!r}] must be a list of strings")
            names[k] = tuple(v)
        pairs = []
        for p in self.pairs:
            if not isinstance(p, (list, tuple)) or len(p) != 2 or not all(isinstance(s, str) for s in p):
                raise InteropError(f"mapping: each entry of 'pairs' must be two names, got {p!r}")
            pairs.append((p[0], p[1]))
        if self.fps is not None and not (float(self.fps) > 0):
            raise InteropError(f"mapping: fps must be positive, got {self.fps!r}")
        object.__setattr__(self, "features", feats)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "cameras", dict(self.cameras))
        object.__setattr__(self, "pairs", tuple(pairs))
        object.__setattr__(self, "fps", None if self.fps is None else float(self.fps))

    def fields(self) -> dict[str, list[str]]:
        """Our field -> its source keys in view order (one key unless views are stacked)."""
        out: dict[str, dict[int, str]] = {}
        for src, tgt in self.features.items():
            field, idx = parse_target(tgt)
            out.setdefault(field, {})[0 if idx is None else idx] = src
        return {f: [v[i] for i in sorted(v)] for f, v in out.items()}

    def to_dict(self) -> dict:
        return {"features": dict(self.features), "names": {k: list(v) for k, v in self.names.items()},
                "cameras": dict(self.cameras), "pairs": [list(p) for p in self.pairs], "fps": self.fps}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "mapping") -> "FeatureMapping":
        if not isinstance(d, Mapping):
            raise InteropError(f"{source}: a mapping must be a JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - {"features", "names", "cameras", "pairs", "fps"})
        if unknown:
            raise InteropError(f"{source}: unknown mapping entries {unknown} (valid: features, names, cameras, "
                               f"pairs, fps)")
        if not isinstance(d.get("features"), Mapping):
            raise InteropError(f"{source}: 'features' must be an object {{source key: our field}}")
        try:
            return cls(features=d["features"], names=d.get("names") or {}, cameras=d.get("cameras") or {},
                       pairs=tuple(tuple(p) if isinstance(p, list) else p for p in d.get("pairs", DEFAULT_PAIRS)),
                       fps=d.get("fps"))
        except InteropError as e:
            raise InteropError(f"{source}: {e}") from None

    def merged(self, other: Mapping[str, Any]) -> "FeatureMapping":
        """This mapping with the entries of a partial mapping dict ``other`` replacing ours
        (``features`` given in ``other`` replace ours whole; names/cameras are merged)."""
        d = self.to_dict()
        for k, v in other.items():
            if k in ("names", "cameras") and isinstance(v, Mapping):
                d[k] = {**d[k], **v}
            else:
                d[k] = v
        return FeatureMapping.from_dict(d)


def load_mapping(path: str | os.PathLike) -> dict:
    """The JSON object in ``path``: a whole mapping or only some entries, which
    :meth:`FeatureMapping.merged` lays over a format's defaults (and validates)."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise InteropError(f"mapping file {path} does not exist") from None
    except json.JSONDecodeError as e:
        raise InteropError(f"mapping file {path} is not valid JSON: {e}") from None
    if not isinstance(d, dict):
        raise InteropError(f"mapping file {path} must hold a JSON object")
    unknown = sorted(set(d) - {"features", "names", "cameras", "pairs", "fps"})
    if unknown:
        raise InteropError(f"mapping file {path}: unknown entries {unknown} (valid: features, names, cameras, "
                           f"pairs, fps)")
    return d


def default_mapping(fmt: str, keys, recorded: Mapping[str, Any] | None = None) -> FeatureMapping:
    """A format's default mapping restricted to the source's ``keys``.

    ``recorded``: the mapping an equibim export recorded in the source (it wins: a
    round trip restores every field and its names). Otherwise: DP3 ``state`` -> ``qpos``,
    ``action``, ``point_cloud``, ``img`` -> ``image``, ``depth``; LeRobot
    ``observation.state`` -> ``qpos``, ``action``, and a single ``observation.images.<cam>``
    -> ``image`` (camera ``<cam>``).
    """
    keys = list(keys)
    if recorded:
        return FeatureMapping.from_dict(recorded, "recorded mapping")
    if fmt == "dp3":
        inv = {v: k for k, v in DP3_KEYS.items() if k in ("qpos", "action", "point_cloud", "image", "depth")}
        feats = {k: inv[k] for k in keys if k in inv}
        return FeatureMapping(feats)
    if fmt == "lerobot":
        feats = {k: t for k, t in (("observation.state", "qpos"), ("action", "action")) if k in keys}
        images = [k for k in keys if k.startswith("observation.images.")]
        cams = {}
        if len(images) == 1:
            feats[images[0]] = "image"
            cams[images[0]] = images[0].split(".", 2)[2]
        elif "observation.image" in keys:
            feats["observation.image"] = "image"
        return FeatureMapping(feats, cameras=cams)
    raise InteropError(f"unknown format {fmt!r}; valid formats: dp3, lerobot")


# ---------------------------------------------------------------- our side of the mapping
def _robot_of(meta: Mapping) -> str | None:
    """The robot of a generated dataset's task, or None (imported or unknown task)."""
    task = meta.get("task")
    if not isinstance(task, str):
        return None
    try:
        from equibim_jax.tasks import task_entry

        return task_entry(task).robot
    except ValueError:
        return None


def describe(demos) -> dict:
    """Entry names, cameras and fps of a dataset of ours, for export and the mirror check.

    Returns:
      ``{"names": {field: [names of the last axis]}, "cameras": {field: [camera per view]},
      "fps": float | None}``: from an imported dataset's record (``meta["interop"]``), or, for
      a generated one, from its task's robot: ``qpos`` and joint actions are
      ``[left arm joints, gripper_left, right arm joints, gripper_right]``, ``image`` and
      ``depth`` see the robot's camera on the mirror plane, ``wrist_image`` its (left,
      right) wrist cameras, fps is ``1 / control_dt`` (or ``1 / task_options["ctrl_dt"]``).
    """
    meta = dict(demos.meta)
    rec = meta.get("interop")
    if isinstance(rec, Mapping):
        return {"names": {k: list(v) for k, v in (rec.get("names") or {}).items()},
                "cameras": {k: list(v) for k, v in (rec.get("cameras") or {}).items()},
                "fps": rec.get("fps"), "pairs": [list(p) for p in rec.get("pairs", DEFAULT_PAIRS)]}
    names: dict[str, list[str]] = {}
    cameras: dict[str, list[str]] = {}
    fps = None
    robot = _robot_of(meta)
    if robot is not None:
        from equibim_jax.sim.robots import robot_info

        info = robot_info(robot)
        joint = [*info.arm_joints[0], "gripper_left", *info.arm_joints[1], "gripper_right"]
        if "qpos" in demos.obs and demos.obs["qpos"].shape[-1] == len(joint):
            names["qpos"] = joint
        space = meta.get("action_space", (meta.get("task_options") or {}).get("action", "joint"))
        if space == "joint" and demos.action.shape[-1] == len(joint):
            names["action"] = joint
        for f in ("image", "depth"):
            if f in demos.obs:
                cameras[f] = [(meta.get("task_options") or {}).get("camera") or info.camera]
        if "wrist_image" in demos.obs and info.wrist_cameras:
            cameras["wrist_image"] = list(info.wrist_cameras)
        dt = (meta.get("task_options") or {}).get("ctrl_dt") or info.control_dt
        fps = 1.0 / float(dt)
    return {"names": names, "cameras": cameras, "fps": fps, "pairs": [list(p) for p in DEFAULT_PAIRS]}


def episode_frames(demos) -> tuple[dict, "np.ndarray"]:
    """The valid steps of every episode, concatenated.

    Returns:
      ``({field: [F, ...]} for every observation field plus ``action`` (and ``action_ee``),
      ends int64 [E])`` with ``F = sum(length)`` and ``ends`` the cumulative episode ends.
    """
    import numpy as np

    cut = lambda a: np.concatenate([a[e, : demos.length[e]] for e in range(demos.n_episodes)])
    frames = {k: cut(v) for k, v in demos.obs.items()}
    frames["action"] = cut(demos.action)
    if demos.action_ee is not None:
        frames["action_ee"] = cut(demos.action_ee)
    return frames, np.cumsum(demos.length).astype(np.int64)


def check_episode_ends(ends, source: str):
    """``ends`` as an int64 array [E], or InteropError: not 1-D integers, or ragged (not
    strictly increasing from a positive first end: an empty or overlapping episode)."""
    import numpy as np

    ends = np.asarray(ends)
    if ends.ndim != 1 or ends.size == 0:
        raise InteropError(f"{source}: episode ends must be a non-empty 1-D array, got shape {ends.shape}")
    if not np.issubdtype(ends.dtype, np.integer):
        raise InteropError(f"{source}: wrong dtype: episode ends must be integers, got {ends.dtype}")
    if np.any(np.diff(np.concatenate([[0], ends])) < 1):
        raise InteropError(f"{source}: ragged episode ends {ends.tolist()[:20]}: they must be strictly "
                           f"increasing and positive (no empty episode)")
    return ends.astype(np.int64)


def demos_from_frames(frames: Mapping, ends, success, meta: Mapping, source: str):
    """Our :class:`~equibim_jax.data.dataset.Demos` from concatenated frames.

    Args:
      frames: ``{field: [F, ...]}`` with ``action`` (and optionally ``action_ee``); every
        other entry is an observation field.
      ends: int [E], strictly increasing cumulative episode ends, the last one ``F``.
      success: bool [E].
    Returns:
      Demos with arrays [E, T, ...], ``T`` the longest episode; shorter episodes are padded
      by repeating their last step (``length`` says which steps are real).
    Raises:
      InteropError: ragged ends, frame counts that differ between fields, bad dtypes.
    """
    import numpy as np

    from equibim_jax.data.dataset import Demos

    ends = check_episode_ends(ends, source)
    n = int(ends[-1])
    for k, v in frames.items():
        if v.shape[0] != n:
            raise InteropError(f"{source}: frame count mismatch: {k!r} has {v.shape[0]} frames but the episode "
                               f"ends say {n}")
        if v.dtype.kind not in "fiub":
            raise InteropError(f"{source}: {k!r} has dtype {v.dtype}; expected numbers")
    for k in ("action", "action_ee"):
        if k in frames and (frames[k].ndim != 2 or frames[k].dtype.kind != "f"):
            raise InteropError(f"{source}: {k!r} must be float [frames, A], got {frames[k].dtype} "
                               f"{frames[k].shape}")
    starts = np.concatenate([[0], ends[:-1]]).astype(np.int64)
    lengths = (ends - starts).astype(np.int32)
    t = int(lengths.max())
    idx = np.minimum(starts[:, None] + np.arange(t)[None, :], (ends - 1)[:, None])  # [E, T], edge-padded

    def pad(a):
        return a[idx]

    obs = {k: pad(v) for k, v in frames.items() if k not in ("action", "action_ee")}
    if not obs:
        raise InteropError(f"{source}: no observation field was mapped (only {sorted(frames)})")
    success = np.asarray(success, bool)
    if success.shape != lengths.shape:
        raise InteropError(f"{source}: {success.shape[0]} success flags for {lengths.shape[0]} episodes")
    try:
        return Demos(obs=obs, action=pad(frames["action"]).astype(np.float32), length=lengths, success=success,
                     meta=dict(meta),
                     action_ee=pad(frames["action_ee"]).astype(np.float32) if "action_ee" in frames else None)
    except DatasetError as e:
        raise InteropError(f"{source}: {e}") from None


def write_dir_atomically(out: str | os.PathLike, write, overwrite: bool = False) -> Path:
    """Call ``write(tmp_dir)`` on a temporary sibling of ``out``, fsync it, then move it to
    ``out`` (atomically exchanged with an existing ``out`` where the system allows; see
    :mod:`equibim_jax.data.dataset`). On any failure the temporary directory is removed and
    ``out`` keeps what it had.

    Raises:
      FileExistsError: ``out`` exists and ``overwrite`` is False.
    """
    import shutil
    import tempfile

    from equibim_jax.data import dataset as _ds

    out = Path(out)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite=True (--overwrite) to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        write(tmp)
        _ds._fsync_tree(tmp)
        if out.exists() or out.is_symlink():
            if _ds._exchange(tmp, out):
                _ds._remove(tmp)
            else:
                _ds._replace_with_gap(tmp, out)
        else:
            os.replace(tmp, out)
        _ds._fsync_path(out.parent, directory=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
