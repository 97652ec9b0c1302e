"""Diffusion Policy / DP3 ``ReplayBuffer`` zarr: export our datasets to it and import from it.

The layout (zarr format 2, as the ``ReplayBuffer`` of Diffusion Policy and DP3 opens it)::

    data/<key>            [F, ...]   every valid step of every episode, concatenated
    meta/episode_ends     int64 [E]  cumulative end (exclusive) of each episode
    meta/episode_success  bool [E]   (ours, extra: whether each episode succeeded)
    attrs["equibim"]                 the key mapping, entry names, cameras, fps and the
                                     source dataset's metadata

Keys follow DP3's names where they apply: ``state`` (our ``qpos``), ``action``,
``point_cloud``, ``img`` (our ``image``, [F, H, W, 3] uint8), ``depth``; the two wrist views
of ``wrist_image`` become ``img_<camera>`` each; other fields keep their names (``ee``,
``action_ee``). Only the ``length`` valid steps of each episode are written, so the
padding of our [E, T, ...] arrays is not kept (an import pads by repeating each
episode's last step).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from equibim_jax.data.dataset import Demos, load, save
from equibim_jax.interop.mapping import (
    DP3_KEYS,
    FeatureMapping,
    InteropError,
    check_episode_ends,
    default_mapping,
    demos_from_frames,
    describe,
    episode_frames,
    parse_target,
    write_dir_atomically,
)

__all__ = ["export_dp3", "read_dp3", "import_dp3"]

FORMAT = "dp3-replay-buffer"


def _export_mapping(demos: Demos) -> tuple[FeatureMapping, dict]:
    """(the mapping DP3 key -> our field, {DP3 key: (our field, view or None)})."""
    desc = describe(demos)
    fields = [*demos.obs, "action"] + (["action_ee"] if demos.action_ee is not None else [])
    features, cameras, where = {}, {}, {}
    for f in fields:
        if f == "wrist_image":
            cams = desc["cameras"].get(f) or ["wrist_left", "wrist_right"]
            for i, c in enumerate(cams):
                key = f"img_{c}"
                features[key], cameras[key], where[key] = f"{f}[{i}]", c, (f, i)
            continue
        key = DP3_KEYS.get(f, f)
        features[key], where[key] = f, (f, None)
        if f in desc["cameras"]:
            cameras[key] = desc["cameras"][f][0]
    fm = FeatureMapping(features, names=desc["names"], cameras=cameras, pairs=desc["pairs"], fps=desc["fps"])
    return fm, where


def export_dp3(src: str | os.PathLike | Demos, out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write dataset ``src`` (a path or :class:`Demos`) as a DP3 ReplayBuffer zarr at ``out``.

    The zarr is written to a temporary sibling directory and moved into place when complete.
    Returns ``out``.
    """
    import zarr

    demos = src if isinstance(src, Demos) else load(src)
    frames, ends = episode_frames(demos)
    fm, where = _export_mapping(demos)

    def write(tmp: Path) -> None:
        g = zarr.open_group(str(tmp), mode="w", zarr_format=2)
        for key, (field, view) in where.items():
            a = frames[field] if view is None else frames[field][:, view]
            a = np.ascontiguousarray(a)
            # chunks of whole frames, ~1-4 MB: what the ReplayBuffer's own writer picks too
            per = max(1, int(a[0].nbytes))
            chunk = int(max(1, min(a.shape[0], (2 << 20) // per)))
            g.create_array(f"data/{key}", shape=a.shape, dtype=a.dtype, chunks=(chunk,) + a.shape[1:])[:] = a
        g.create_array("meta/episode_ends", shape=ends.shape, dtype=np.int64)[:] = ends
        succ = np.asarray(demos.success, bool)
        g.create_array("meta/episode_success", shape=succ.shape, dtype=bool)[:] = succ
        g.attrs["equibim"] = {"format": FORMAT, "mapping": fm.to_dict(),
                              "source_meta": {k: v for k, v in dict(demos.meta).items() if k != "interop"}}

    return write_dir_atomically(out, write, overwrite)


def read_dp3(src: str | os.PathLike, mapping: Mapping | None = None) -> Demos:
    """Read a DP3 / Diffusion Policy ReplayBuffer zarr into our :class:`Demos`.

    Args:
      src: the zarr directory (``data/<key>`` [F, ...], ``meta/episode_ends`` [E]).
      mapping: a (partial) mapping dict laid over the defaults (:mod:`.mapping`): the mapping
        an equibim export recorded, else ``state`` -> ``qpos``, ``action``, ``point_cloud``,
        ``img`` -> ``image``, ``depth``.
    Returns:
      Demos with ``meta["interop"]`` recording the source, mapping, names, cameras and fps
      (and the source's own metadata when it was exported by equibim).
    Raises:
      InteropError: not a ReplayBuffer zarr, a missing key, ragged episode ends, a frame
        count or size that does not match, a wrong dtype.
    """
    import zarr

    src = Path(src)
    if not src.exists():
        raise InteropError(f"no DP3 zarr at {src}")
    try:
        root = zarr.open_group(str(src), mode="r")
        attrs = dict(root.attrs.get("equibim", {}) or {})
    except Exception as e:  # zarr raises several types for what is not a zarr group
        raise InteropError(f"{src} is not a readable zarr group: {type(e).__name__}: {e}") from None
    if "data" not in root or "meta" not in root:
        raise InteropError(f"{src}: missing key: a ReplayBuffer zarr has groups data/ and meta/, this one has "
                           f"{sorted(root.keys())}")
    data, meta = root["data"], root["meta"]
    if "episode_ends" not in meta:
        raise InteropError(f"{src}: missing key meta/episode_ends")
    ends = check_episode_ends(meta["episode_ends"][:], f"{src}: meta/episode_ends")
    keys = sorted(data.array_keys())
    fm = default_mapping("dp3", keys, attrs.get("mapping"))
    if mapping:
        fm = fm.merged(mapping)
    frames, cameras = {}, {}
    for field, srcs in fm.fields().items():
        missing = [k for k in srcs if k not in keys]
        if missing:
            raise InteropError(f"{src}: missing key data/{missing[0]} (mapped to {field!r}); the file has "
                               f"data/{keys}")
        arrs = [np.asarray(data[k][:]) for k in srcs]
        for k, a in zip(srcs, arrs):
            if a.shape[0] != int(ends[-1]):
                raise InteropError(f"{src}: frame count mismatch: data/{k} has {a.shape[0]} frames but "
                                   f"meta/episode_ends ends at {int(ends[-1])}")
            if field in ("image", "wrist_image") and (a.dtype != np.uint8 or a.ndim != 4 or a.shape[-1] != 3):
                raise InteropError(f"{src}: data/{k} (-> {field}) must be uint8 [frames, H, W, 3] images, "
                                   f"got {a.dtype} {a.shape}")
            if field in ("qpos", "ee", "action", "action_ee") and (a.dtype.kind != "f" or a.ndim != 2):
                raise InteropError(f"{src}: data/{k} (-> {field}) must be float [frames, D], got wrong dtype "
                                   f"or shape: {a.dtype} {a.shape}")
        if len(arrs) > 1 and len({a.shape for a in arrs}) > 1:
            raise InteropError(f"{src}: the views of {field!r} ({srcs}) differ in shape: "
                               f"{[a.shape for a in arrs]}")
        stacked = parse_target(fm.features[srcs[0]])[1] is not None
        frames[field] = np.stack(arrs, 1) if stacked else arrs[0]
        if all(k in fm.cameras for k in srcs):
            cameras[field] = [fm.cameras[k] for k in srcs]
    _check_names(fm, frames, str(src))
    succ = np.asarray(meta["episode_success"][:]) if "episode_success" in meta else np.ones(ends.shape, bool)
    source_meta = dict(attrs.get("source_meta") or {})
    record = {"format": "dp3", "source": str(src), "fps": fm.fps, "mapping": fm.to_dict(),
              "names": {k: list(v) for k, v in fm.names.items() if k in frames},
              "cameras": cameras, "pairs": [list(p) for p in fm.pairs]}
    return demos_from_frames(frames, ends, succ, {**source_meta, "interop": record}, str(src))


def _check_names(fm: FeatureMapping, frames: Mapping, source: str) -> None:
    for field, names in fm.names.items():
        if field in frames and frames[field].shape[-1] != len(names):
            raise InteropError(f"{source}: size mismatch: {field!r} has {frames[field].shape[-1]} entries but the "
                               f"mapping names {len(names)} ({list(names)[:4]}...)")


def import_dp3(src: str | os.PathLike, out: str | os.PathLike, mapping: Mapping | None = None,
               overwrite: bool = False) -> Demos:
    """:func:`read_dp3` then save as our dataset at ``out`` (atomically). Returns the demos."""
    demos = read_dp3(src, mapping)
    save(demos, out, overwrite=overwrite)
    return demos
