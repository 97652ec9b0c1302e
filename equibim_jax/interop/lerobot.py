"""LeRobotDataset v3 layout: export our datasets to it and import from it.

Written layout (``codebase_version`` ``"v3.0"``)::

    meta/info.json                                 fps, features (dtype, shape, names), totals,
                                                   data_path and video_path templates
    meta/tasks.parquet                             task_index, task (one row per task string)
    meta/episodes/chunk-000/file-000.parquet       one row per episode: episode_index, tasks,
                                                   length, dataset_from_index/to_index,
                                                   data/{chunk,file}_index, and per camera
                                                   videos/<key>/{chunk_index, file_index,
                                                   from_timestamp, to_timestamp}; plus our
                                                   ``success``
    meta/stats.json                                min, max, mean, std, count per feature
    data/chunk-000/file-000.parquet                one row per frame: observation.state,
                                                   action, other vector/array features,
                                                   episode_index, frame_index, timestamp,
                                                   index, task_index
    videos/observation.images.<cam>/chunk-000/file-000.mp4   every frame of every episode

This writer puts all episodes in one data file and one video file per camera (the format
allows several; the reader follows the per-episode chunk/file indices and timestamps, so
it reads datasets split over many files too). Arrays of more than one axis (a point cloud
[N, 3]) are nested fixed-size lists. ``observation.images.*`` features of dtype ``video``
are decoded from the mp4 files; dtype ``image`` (PNG/JPEG bytes in the parquet) is read
too.

Video goes through PyAV (``av``): it ships FFmpeg's libraries in its wheel (no ffmpeg
binary, no subprocess), encodes and decodes frame by frame in memory, and is one of the
decoders LeRobot itself uses. The default codec is H.264 (libx264) at CRF 18, yuv420p
(yuv444p for odd image sizes): lossy, so images come back within a small error, not
bit-exact (:data:`DEFAULT_VIDEO`).
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from equibim_jax.data.dataset import Demos, load, save
from equibim_jax.interop.mapping import (
    LEROBOT_KEYS,
    FeatureMapping,
    InteropError,
    default_mapping,
    demos_from_frames,
    describe,
    episode_frames,
    parse_target,
    require,
    write_dir_atomically,
)

__all__ = ["export_lerobot", "read_lerobot", "import_lerobot", "DEFAULT_VIDEO", "CODEBASE_VERSION"]

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DEFAULT_VIDEO = {"codec": "libx264", "pix_fmt": "yuv420p", "crf": 18, "g": 2}
"""Video settings of :func:`export_lerobot`: H.264, CRF 18, a key frame every 2 frames (so
a reader can seek to any timestamp cheaply, as LeRobot's own writer does)."""
_CODEC_NAMES = {"libx264": "h264", "libopenh264": "h264", "libsvtav1": "av1", "libaom-av1": "av1",
                "librav1e": "av1", "libx265": "hevc", "libvpx-vp9": "vp9"}
"""Encoder -> the codec name info.json records (LeRobot's spelling: the format, not the encoder)."""
BOOKKEEPING = ("timestamp", "frame_index", "episode_index", "index", "task_index")


# ------------------------------------------------------------------------------ video
def _encode_video(path: Path, frames: np.ndarray, fps: float, video: Mapping) -> dict:
    """Write uint8 frames [F, H, W, 3] to an mp4; returns the feature's ``info`` entries."""
    av = require("av")
    from fractions import Fraction

    f, h, w, _ = frames.shape
    pix = video["pix_fmt"]
    if pix == "yuv420p" and (h % 2 or w % 2):
        pix = "yuv444p"  # 4:2:0 needs even sizes
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as c:
        s = c.add_stream(video["codec"], rate=Fraction(fps).limit_denominator(1001))
        s.width, s.height, s.pix_fmt = w, h, pix
        s.options = {"crf": str(video["crf"]), "g": str(video["g"])}
        for img in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
        codec = s.codec_context.name
    return {"video.height": h, "video.width": w, "video.codec": _CODEC_NAMES.get(codec, codec),
            "video.pix_fmt": pix, "video.is_depth_map": False, "video.fps": fps, "video.channels": 3,
            "has_audio": False, "video.g": video["g"], "video.crf": video["crf"], "video.video_backend": "pyav"}


def _decode_video(path: Path) -> np.ndarray:
    """Every frame of an mp4 as uint8 [F, H, W, 3], in presentation order."""
    av = require("av")
    if not path.exists():
        raise InteropError(f"missing video file {path}")
    try:
        with av.open(str(path)) as c:
            frames = [(fr.pts if fr.pts is not None else i, fr.to_ndarray(format="rgb24"))
                      for i, fr in enumerate(c.decode(c.streams.video[0]))]
    except av.error.FFmpegError as e:
        raise InteropError(f"cannot decode video {path}: {e}") from None
    frames.sort(key=lambda x: x[0])
    if not frames:
        raise InteropError(f"video {path} has no frames")
    return np.stack([f for _, f in frames])


# ------------------------------------------------------------------------------ arrow helpers
def _column(pa, a: np.ndarray):
    """numpy [F, d1, ..., dk] -> an arrow column of nested fixed-size lists (k levels)."""
    arr = pa.array(np.ascontiguousarray(a).reshape(-1))
    for d in reversed(a.shape[1:]):
        arr = pa.FixedSizeListArray.from_arrays(arr, int(d))
    return arr


def _to_numpy(col, shape: tuple[int, ...], key: str, source: str) -> np.ndarray:
    """An arrow column of (nested) lists -> numpy [F, *shape]; clear errors for bad rows."""
    import pyarrow as pa

    col = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    n = len(col)
    if col.null_count:
        raise InteropError(f"{source}: {key!r} has {col.null_count} missing (null) values")
    flat = col
    while pa.types.is_list(flat.type) or pa.types.is_fixed_size_list(flat.type) or \
            pa.types.is_large_list(flat.type):
        flat = flat.flatten()
    t = flat.type
    if not (pa.types.is_floating(t) or pa.types.is_integer(t) or pa.types.is_boolean(t)):
        raise InteropError(f"{source}: wrong dtype: {key!r} holds {t} values; expected numbers")
    a = flat.to_numpy(zero_copy_only=False)
    want = n * int(np.prod(shape, dtype=np.int64))
    if a.size != want:
        raise InteropError(f"{source}: {key!r} holds {a.size} values over {n} frames; info.json says shape "
                           f"{list(shape)} ({want} values)")
    return a.reshape((n,) + tuple(shape))


# ------------------------------------------------------------------------------ export
def _export_plan(demos: Demos) -> tuple[FeatureMapping, dict]:
    """(mapping LeRobot key -> our field, {key: (our field, view or None, is_video)})."""
    desc = describe(demos)
    fields = [*demos.obs, "action"] + (["action_ee"] if demos.action_ee is not None else [])
    features, cameras, plan = {}, {}, {}
    for f in fields:
        if f in ("image", "wrist_image"):
            default = ["head"] if f == "image" else ["wrist_left", "wrist_right"]
            cams = desc["cameras"].get(f) or default
            for i, c in enumerate(cams):
                key = f"observation.images.{c}"
                if key in features:
                    raise InteropError(f"camera name {c!r} is used by two image fields; cannot export")
                view = i if f == "wrist_image" else None
                features[key] = f if view is None else f"{f}[{i}]"
                cameras[key], plan[key] = c, (f, view, True)
            continue
        key = LEROBOT_KEYS.get(f, f"observation.{f}")
        features[key], plan[key] = f, (f, None, False)
        if f in desc["cameras"]:
            cameras[key] = desc["cameras"][f][0]
    return FeatureMapping(features, names=desc["names"], cameras=cameras, pairs=desc["pairs"],
                          fps=desc["fps"]), plan


def _stats(a: np.ndarray, image: bool) -> dict:
    """min/max/mean/std/count over frames (per channel for images, as LeRobot keeps them:
    [3, 1, 1], in [0, 1]); over frames and all but the last axis otherwise."""
    x = a.astype(np.float64)
    if image:
        x = x / 255.0
        axes = tuple(range(x.ndim - 1))
        r = lambda v: v.reshape(3, 1, 1).tolist()
    else:
        axes = tuple(range(x.ndim - 1)) if x.ndim > 1 else (0,)
        r = lambda v: np.atleast_1d(v).tolist()
    return {"min": r(x.min(axes)), "max": r(x.max(axes)), "mean": r(x.mean(axes)), "std": r(x.std(axes)),
            "count": [int(a.shape[0])]}


def export_lerobot(src: str | os.PathLike | Demos, out: str | os.PathLike, overwrite: bool = False,
                   fps: float | None = None, task: str | None = None, video: Mapping | None = None) -> Path:
    """Write dataset ``src`` (a path or :class:`Demos`) as a LeRobotDataset v3 at ``out``.

    Args:
      fps: frames per second; default: the dataset's (its robot's control rate, or the fps
        recorded at import). Required when the dataset does not know it.
      task: the task string of every episode (default: the dataset's task name).
      video: overrides of :data:`DEFAULT_VIDEO` (``codec``, ``pix_fmt``, ``crf``, ``g``).
    Raises:
      InteropError: no fps known; a field that cannot be written.
    Returns ``out``; written to a temporary sibling directory and moved into place.
    """
    pa = require("pyarrow")
    pq = require("pyarrow.parquet")
    demos = src if isinstance(src, Demos) else load(src)
    fm, plan = _export_plan(demos)
    fps = float(fps or fm.fps or 0)
    if not fps > 0:
        raise InteropError("the dataset does not record its frame rate; pass fps (--fps)")
    vid = {**DEFAULT_VIDEO, **(video or {})}
    frames, ends = episode_frames(demos)
    e, n = demos.n_episodes, int(ends[-1])
    starts = np.concatenate([[0], ends[:-1]])
    ep_index = np.repeat(np.arange(e), demos.length).astype(np.int64)
    frame_index = (np.arange(n) - starts[ep_index]).astype(np.int64)
    meta = dict(demos.meta)
    task = task or str(meta.get("task_description") or meta.get("task") or "imported demonstrations")
    robot = None
    try:
        from equibim_jax.interop.mapping import _robot_of

        robot = _robot_of(meta)
    except Exception:  # the robot name is informational only
        robot = None

    def write(tmp: Path) -> None:
        features: dict[str, Any] = {}
        columns: dict[str, Any] = {}
        stats: dict[str, Any] = {}
        videos = []
        for key, (field, view, is_video) in plan.items():
            a = frames[field] if view is None else frames[field][:, view]
            if is_video:
                if a.dtype != np.uint8 or a.ndim != 4 or a.shape[-1] != 3:
                    raise InteropError(f"{field} must be uint8 [.., H, W, 3] to become a video, got {a.dtype} "
                                       f"{a.shape[1:]}")
                info = _encode_video(tmp / VIDEO_PATH.format(video_key=key, chunk_index=0, file_index=0), a,
                                     fps, vid)
                features[key] = {"dtype": "video", "shape": list(a.shape[1:]),
                                 "names": ["height", "width", "channels"], "info": info}
                videos.append(key)
                stats[key] = _stats(a, image=True)
                continue
            names = fm.names.get(field)
            features[key] = {"dtype": str(a.dtype), "shape": list(a.shape[1:]),
                             "names": list(names) if names is not None else None}
            columns[key] = _column(pa, a)
            stats[key] = _stats(a, image=False)
        book = {"timestamp": (frame_index / fps).astype(np.float32), "frame_index": frame_index,
                "episode_index": ep_index, "index": np.arange(n, dtype=np.int64),
                "task_index": np.zeros(n, np.int64)}
        for k, v in book.items():
            features[k] = {"dtype": str(v.dtype), "shape": [1], "names": None}
            columns[k] = pa.array(v)
            stats[k] = _stats(v, image=False)
        (tmp / "data/chunk-000").mkdir(parents=True)
        pq.write_table(pa.table(columns), tmp / DATA_PATH.format(chunk_index=0, file_index=0))
        (tmp / "meta/episodes/chunk-000").mkdir(parents=True)
        pq.write_table(pa.table({"task_index": pa.array([0], pa.int64()), "task": pa.array([task])}),
                       tmp / "meta/tasks.parquet")
        ep = {"episode_index": pa.array(np.arange(e, dtype=np.int64)),
              "tasks": pa.array([[task]] * e, pa.list_(pa.string())),
              "length": pa.array(demos.length.astype(np.int64)),
              "data/chunk_index": pa.array(np.zeros(e, np.int64)),
              "data/file_index": pa.array(np.zeros(e, np.int64)),
              "dataset_from_index": pa.array(starts.astype(np.int64)),
              "dataset_to_index": pa.array(ends.astype(np.int64))}
        for key in videos:
            ep[f"videos/{key}/chunk_index"] = pa.array(np.zeros(e, np.int64))
            ep[f"videos/{key}/file_index"] = pa.array(np.zeros(e, np.int64))
            ep[f"videos/{key}/from_timestamp"] = pa.array(starts / fps)
            ep[f"videos/{key}/to_timestamp"] = pa.array(ends / fps)
        ep["meta/episodes/chunk_index"] = pa.array(np.zeros(e, np.int64))
        ep["meta/episodes/file_index"] = pa.array(np.zeros(e, np.int64))
        ep["success"] = pa.array(np.asarray(demos.success, bool))
        pq.write_table(pa.table(ep), tmp / EPISODES_PATH.format(chunk_index=0, file_index=0))
        info = {
            "codebase_version": CODEBASE_VERSION, "robot_type": robot, "total_episodes": e, "total_frames": n,
            "total_tasks": 1, "chunks_size": 1000, "data_files_size_in_mb": 100, "video_files_size_in_mb": 500,
            "fps": fps, "splits": {"train": f"0:{e}"}, "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if videos else None, "features": features,
            "equibim": {"mapping": fm.to_dict(), "source_meta": {k: v for k, v in meta.items() if k != "interop"}},
        }
        (tmp / "meta/info.json").write_text(json.dumps(info, indent=2))
        (tmp / "meta/stats.json").write_text(json.dumps(stats))

    return write_dir_atomically(out, write, overwrite)


# ------------------------------------------------------------------------------ import
def _read_parquets(pq, files: list[Path], what: str, source: str):
    import pyarrow as pa

    if not files:
        raise InteropError(f"{source}: missing {what} files")
    try:
        tables = [pq.read_table(f) for f in files]
        return pa.concat_tables(tables, promote_options="default") if len(tables) > 1 else tables[0]
    except (pa.ArrowInvalid, OSError) as e:
        raise InteropError(f"{source}: cannot read {what}: {e}") from None


def _sorted_files(root: Path, pattern: str) -> list[Path]:
    return sorted(root.glob(pattern), key=lambda p: (p.parent.name, p.name))


def _decode_images(col, key: str, source: str) -> np.ndarray:
    """A parquet column of ``image`` structs ({bytes, path}) -> uint8 [F, H, W, 3]."""
    from PIL import Image

    out = []
    for i, v in enumerate(col.to_pylist()):
        b = v.get("bytes") if isinstance(v, dict) else None
        if not b:
            raise InteropError(f"{source}: {key!r} row {i} holds no image bytes")
        out.append(np.asarray(Image.open(io.BytesIO(b)).convert("RGB")))
    return np.stack(out)


def read_lerobot(src: str | os.PathLike, mapping: Mapping | None = None) -> Demos:
    """Read a LeRobotDataset v3 directory into our :class:`Demos`.

    Args:
      src: the dataset root (``meta/info.json``, ``data/``, ``videos/``).
      mapping: a (partial) mapping dict laid over the defaults (:mod:`.mapping`): the mapping
        an equibim export recorded, else ``observation.state`` -> ``qpos``, ``action``, and a
        single ``observation.images.<cam>`` -> ``image``.
    Raises:
      InteropError: missing files or keys, a codebase version other than v3, totals, episode
        lengths or video frame counts that disagree, values of the wrong dtype or shape.
    """
    pq = require("pyarrow.parquet")
    root = Path(src)
    source = str(root)
    info_path = root / "meta/info.json"
    if not info_path.exists():
        raise InteropError(f"{source}: missing meta/info.json (not a LeRobot dataset?)")
    try:
        info = json.loads(info_path.read_text())
    except json.JSONDecodeError as e:
        raise InteropError(f"{source}: meta/info.json is not valid JSON: {e}") from None
    version = str(info.get("codebase_version", ""))
    if not version.startswith("v3"):
        raise InteropError(f"{source}: codebase_version {version!r}; this reader reads LeRobotDataset v3.x "
                           f"(convert older datasets with LeRobot's v2.1 -> v3.0 converter)")
    for k in ("fps", "features"):
        if k not in info:
            raise InteropError(f"{source}: meta/info.json has no {k!r}")
    fps = float(info["fps"])
    feats: dict = info["features"]
    table = _read_parquets(pq, _sorted_files(root, "data/chunk-*/file-*.parquet"), "data (data/chunk-*/*.parquet)",
                           source)
    episodes = _read_parquets(pq, _sorted_files(root, "meta/episodes/chunk-*/file-*.parquet"),
                              "episode metadata (meta/episodes/chunk-*/*.parquet)", source)
    for k in ("episode_index", "frame_index"):
        if k not in table.column_names:
            raise InteropError(f"{source}: missing key {k!r} in the data parquet")
    for k in ("episode_index", "length"):
        if k not in episodes.column_names:
            raise InteropError(f"{source}: missing key {k!r} in meta/episodes")
    if table.num_rows != int(info.get("total_frames", table.num_rows)):
        raise InteropError(f"{source}: frame count mismatch: the data parquet has {table.num_rows} rows, "
                           f"info.json total_frames is {info['total_frames']}")
    ep_idx = episodes.column("episode_index").to_numpy()
    order = np.argsort(ep_idx, kind="stable")
    episodes = episodes.take(order)
    ep_idx = ep_idx[order]
    if not np.array_equal(ep_idx, np.arange(len(ep_idx))):
        raise InteropError(f"{source}: meta/episodes episode_index must be 0..E-1 once each, got "
                           f"{ep_idx.tolist()[:20]}")
    if len(ep_idx) != int(info.get("total_episodes", len(ep_idx))):
        raise InteropError(f"{source}: {len(ep_idx)} episodes in meta/episodes, info.json total_episodes is "
                           f"{info['total_episodes']}")
    lengths = episodes.column("length").to_numpy().astype(np.int64)
    # rows in episode, frame order
    d_ep = table.column("episode_index").to_numpy()
    d_fr = table.column("frame_index").to_numpy()
    row_order = np.lexsort((d_fr, d_ep))
    table = table.take(row_order)
    d_ep, d_fr = d_ep[row_order], d_fr[row_order]
    counts = np.bincount(d_ep, minlength=len(lengths)) if d_ep.size else np.zeros(len(lengths), int)
    if counts.shape[0] != len(lengths) or np.any(counts != lengths):
        bad = int(np.flatnonzero(counts[:len(lengths)] != lengths)[0]) if np.any(
            counts[:len(lengths)] != lengths) else len(lengths)
        raise InteropError(f"{source}: frame count mismatch: episode {bad} has "
                           f"{int(counts[bad]) if bad < len(counts) else 0} rows in the data but length "
                           f"{int(lengths[bad]) if bad < len(lengths) else 'none'} in meta/episodes")
    ends = np.cumsum(lengths)
    starts = ends - lengths
    if not np.array_equal(d_fr, np.arange(len(d_fr)) - np.repeat(starts, lengths)):
        raise InteropError(f"{source}: frame_index must run 0..length-1 within each episode")

    keys = [k for k in feats if k not in BOOKKEEPING]
    recorded = (info.get("equibim") or {}).get("mapping")
    fm = default_mapping("lerobot", keys, recorded)
    if mapping:
        fm = fm.merged(mapping)
    frames, cameras = {}, {}
    video_cache: dict[Path, np.ndarray] = {}
    for field, srcs in fm.fields().items():
        arrs = []
        for key in srcs:
            if key not in feats:
                raise InteropError(f"{source}: missing key {key!r} (mapped to {field!r}); info.json features: "
                                   f"{sorted(feats)}")
            ft = feats[key]
            shape = tuple(int(s) for s in ft.get("shape", ()))
            if ft.get("dtype") == "video":
                arrs.append(_read_video_feature(root, info, episodes, key, lengths, fps, video_cache, source))
            elif ft.get("dtype") == "image":
                if key not in table.column_names:
                    raise InteropError(f"{source}: missing key {key!r} in the data parquet")
                arrs.append(_decode_images(table.column(key), key, source))
            else:
                if key not in table.column_names:
                    raise InteropError(f"{source}: missing key {key!r} in the data parquet")
                a = _to_numpy(table.column(key), shape, key, source)
                want = str(ft.get("dtype"))
                if want.startswith("float") and a.dtype.kind != "f":
                    raise InteropError(f"{source}: wrong dtype: {key!r} is {a.dtype} in the parquet, info.json "
                                       f"says {want}")
                if want in ("float32", "float64", "int32", "int64", "bool", "uint8", "int16", "float16"):
                    a = a.astype(want)
                arrs.append(a)
            if field in ("image", "wrist_image") and (arrs[-1].dtype != np.uint8 or arrs[-1].ndim != 4):
                raise InteropError(f"{source}: {key!r} (-> {field}) must be images [frames, H, W, 3] uint8, got "
                                   f"{arrs[-1].dtype} {arrs[-1].shape}")
            if field in ("qpos", "ee", "action", "action_ee") and (arrs[-1].dtype.kind != "f" or arrs[-1].ndim != 2):
                raise InteropError(f"{source}: {key!r} (-> {field}) must be float [frames, D], got wrong dtype or "
                                   f"shape: {arrs[-1].dtype} {arrs[-1].shape}")
        if len({a.shape for a in arrs}) > 1:
            raise InteropError(f"{source}: the views of {field!r} ({srcs}) differ in shape: "
                               f"{[a.shape for a in arrs]}")
        stacked = parse_target(fm.features[srcs[0]])[1] is not None
        frames[field] = np.stack(arrs, 1) if stacked else arrs[0]
        cams = [fm.cameras.get(k) or (k.split(".", 2)[2] if k.startswith("observation.images.") else None)
                for k in srcs]
        if all(c is not None for c in cams) and (field in ("image", "wrist_image", "depth")
                                                 or feats[srcs[0]].get("dtype") in ("video", "image")):
            cameras[field] = cams
    names = {k: list(v) for k, v in fm.names.items() if k in frames}
    for field, srcs in fm.fields().items():  # names from info.json where they name every entry
        n = feats[srcs[0]].get("names")
        if isinstance(n, dict) and len(n) == 1:  # {"motors": [...]}, as some datasets write it
            n = next(iter(n.values()))
        if field not in names and len(srcs) == 1 and isinstance(n, list) and frames[field].ndim == 2 \
                and len(n) == frames[field].shape[-1] and all(isinstance(s, str) for s in n):
            names[field] = n
    for field, nm in names.items():
        if frames[field].shape[-1] != len(nm):
            raise InteropError(f"{source}: size mismatch: {field!r} has {frames[field].shape[-1]} entries but "
                               f"{len(nm)} names")
    succ = (episodes.column("success").to_numpy(zero_copy_only=False).astype(bool)
            if "success" in episodes.column_names else np.ones(len(lengths), bool))
    source_meta = dict((info.get("equibim") or {}).get("source_meta") or {})
    record = {"format": "lerobot", "source": source, "fps": fps, "mapping": fm.to_dict(), "names": names,
              "cameras": cameras, "pairs": [list(p) for p in fm.pairs], "robot_type": info.get("robot_type")}
    if "tasks" in episodes.column_names:
        record["tasks"] = [list(t) if t is not None else [] for t in episodes.column("tasks").to_pylist()]
    return demos_from_frames(frames, ends, succ, {**source_meta, "interop": record}, source)


def _read_video_feature(root: Path, info: Mapping, episodes, key: str, lengths: np.ndarray, fps: float,
                        cache: dict, source: str) -> np.ndarray:
    """Frames [F, H, W, 3] of a ``video`` feature, episode after episode, from the per-episode
    file indices and timestamps of meta/episodes."""
    template = info.get("video_path") or VIDEO_PATH
    cols = [f"videos/{key}/{c}" for c in ("chunk_index", "file_index", "from_timestamp")]
    missing = [c for c in cols if c not in episodes.column_names]
    if missing:
        raise InteropError(f"{source}: missing key {missing[0]!r} in meta/episodes (needed for video {key!r})")
    chunk, file, t0 = (episodes.column(c).to_numpy() for c in cols)
    out = []
    for e, n in enumerate(lengths):
        path = root / template.format(video_key=key, chunk_index=int(chunk[e]), file_index=int(file[e]))
        if path not in cache:
            cache.clear()  # keep one decoded file in memory
            cache[path] = _decode_video(path)
        video = cache[path]
        start = int(round(float(t0[e]) * fps))
        if start + n > video.shape[0]:
            raise InteropError(f"{source}: frame count mismatch: episode {e} needs frames {start}..{start + n - 1} "
                               f"of {path.relative_to(root)}, which has {video.shape[0]} frames")
        out.append(video[start:start + n])
    return np.concatenate(out)


def import_lerobot(src: str | os.PathLike, out: str | os.PathLike, mapping: Mapping | None = None,
                   overwrite: bool = False) -> Demos:
    """:func:`read_lerobot` then save as our dataset at ``out`` (atomically). Returns the demos."""
    demos = read_lerobot(src, mapping)
    save(demos, out, overwrite=overwrite)
    return demos
