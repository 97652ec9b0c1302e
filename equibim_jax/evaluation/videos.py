"""Paired videos of closed-loop evaluation episodes: an episode beside its mirrored twin.

Episode ``i`` of an evaluation (:func:`~equibim_jax.evaluation.evaluate.evaluate_policies`)
uses key ``i`` of ``jax.random.split(jax.random.key(seed), episodes)`` on both sides; the
mirrored side starts from ``env.mirror_state`` of the trained side's start. To film chosen
episodes, :func:`render_episodes` reruns only those episodes with the same keys (a second,
deterministic rollout pass that records ``qpos`` after every control step), then renders
each recorded ``qpos`` with the env's ray-cast renderer (its head camera, at any square
size). :func:`paired_frames` puts the two sides next to each other (width ``2 W``, no
separator) with a label on each, and :func:`write_video` writes GIF (Pillow) or mp4
(PyAV, imported only when an mp4 is asked for).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax.sim.env import Env

__all__ = ["check_episodes", "render_episodes", "paired_frames", "write_video", "write_paired_videos",
           "VIDEO_FORMATS"]

VIDEO_FORMATS = ("gif", "mp4")


def check_episodes(episodes: Sequence[int], n_episodes: int) -> tuple[int, ...]:
    """Validate video episode indices against an evaluation of ``n_episodes`` episodes.

    Returns:
      the indices as a tuple of ints, in the given order.
    Raises:
      ValueError: an index that is not an integer, is negative, is ``>= n_episodes``, or
        repeats.
    """
    out = []
    for e in episodes:
        if isinstance(e, bool) or int(e) != e:
            raise ValueError(f"video episode indices must be integers, got {e!r}")
        e = int(e)
        if not 0 <= e < n_episodes:
            raise ValueError(f"video episode {e} does not exist: the evaluation runs {n_episodes} "
                             f"episodes per side, numbered 0 to {n_episodes - 1}")
        if e in out:
            raise ValueError(f"video episode {e} is given twice")
        out.append(e)
    return tuple(out)


def _frame_renderer(env: Env, size: int):
    """``render(data, qpos [nq]) -> uint8 [size, size, 3]``: the scene of ``data`` (an
    ``mjx.Data`` of ``env``) with its ``qpos`` replaced, seen by the env's head camera."""
    from mujoco import mjx

    from equibim_jax.sim.render import CameraConfig, make_renderer

    renderer = make_renderer(env.mj_model, CameraConfig(camera=env.camera, width=int(size), height=int(size),
                                                        outputs=("rgb",)))

    def render(data, qpos):
        d = data.replace(qpos=qpos)
        d = mjx.camlight(env.mjx_model, mjx.kinematics(env.mjx_model, d))
        rgb = renderer.rgb(d)
        if rgb.dtype != jnp.uint8:
            rgb = jnp.clip(rgb * 255.0 + 0.5, 0, 255).astype(jnp.uint8)
        return rgb

    return render


def render_episodes(env: Env, policy, normalizer, params: Any, key: jax.Array, n_episodes: int,
                    episodes: Sequence[int], size: int = 128, mirror_noise: bool = False,
                    temporal_ensemble: float | None = None, length: int | None = None,
                    rollout=None, batch: int | None = None) -> list[dict]:
    """Rerun chosen evaluation episodes on both sides and render every control step.

    Episode ``i`` uses ``jax.random.split(key, n_episodes)[i]``, the key the evaluation
    gave it, on both sides (the mirrored side from the mirror image of the start), so the
    same arguments give the same episodes as the evaluation.

    Args:
      env, policy, normalizer, params: as for ``make_policy_rollout``.
      key: the evaluation's key (``jax.random.key(EvalConfig.seed)``).
      n_episodes: the evaluation's episodes per side. episodes: the indices to film.
      size: square frame side in pixels. mirror_noise, temporal_ensemble: as the evaluation.
      length: control steps (default: the env's ``episode_length``).
      rollout: a ``make_policy_rollout(..., record_qpos=True)`` of these arguments to reuse
        (e.g. the one the evaluation ran: its compiled program is then reused too); built
        otherwise. batch: the evaluation's batch (``EvalConfig.batch``): the episodes are
        rerun in batches of its shape (padded), so a reused rollout is not recompiled.
    Returns:
      per chosen episode, ``{"episode": i, "frames": uint8 [T + 1, size, size, 3],
      "mirror_frames": uint8 [T + 1, size, size, 3], "success": bool, "mirror_success": bool,
      "success_t": bool [T], "mirror_success_t": bool [T], "nan_actions": int,
      "mirror_nan_actions": int}``; frame 0 is the start, frame ``t`` the state after ``t``
      control steps, ``T = ceil(length / Ta) * Ta``.
    """
    from equibim_jax.evaluation.rollout import make_policy_rollout

    episodes = check_episodes(episodes, n_episodes)
    if not episodes:
        return []
    if int(size) < 8:
        raise ValueError(f"video size must be >= 8 pixels, got {size}")
    from equibim_jax._sharding import data_mesh, replicate, round_up, shard_batch, to_host
    from equibim_jax.evaluation.rollout import _runner

    if rollout is None:
        rollout = make_policy_rollout(env, policy, normalizer, length=length, mirror_noise=mirror_noise,
                                      record_qpos=True, temporal_ensemble=temporal_ensemble)
    keys = jax.random.split(key, n_episodes)[jnp.asarray(episodes)]
    both_keys = jnp.concatenate([keys, keys])
    flags = jnp.concatenate([jnp.zeros(len(episodes), bool), jnp.ones(len(episodes), bool)])
    # Batches shaped as the evaluation's (``rollout._run_paired``): same program, no recompile.
    mesh = data_mesh()
    total = 2 * len(episodes)
    chunk = round_up(min(int(batch or total), 2 * n_episodes), mesh)
    pad = (-total) % chunk
    fill = np.arange(pad) % total
    all_keys, all_flags = jnp.concatenate([both_keys, both_keys[fill]]), jnp.concatenate([flags, flags[fill]])
    run, rep = _runner(rollout), replicate(params, mesh)
    parts = [to_host(run(rep, *shard_batch((all_keys[i : i + chunk], all_flags[i : i + chunk]), mesh)))
             for i in range(0, total + pad, chunk)]
    out = {f: np.concatenate([np.asarray(p[f]) for p in parts])[:total]
           for f in ("success", "success_t", "nan_actions", "qpos_t")}
    render = _frame_renderer(env, size)

    @jax.jit
    def film(k, mirrored, qpos_t):  # one episode: [T, nq] -> [T + 1, size, size, 3]
        s = env.reset(jax.random.split(k)[0])  # the rollout's reset key
        s = jax.tree.map(lambda a, b: jnp.where(mirrored, b, a), s, env.mirror_state(s))
        q = jnp.concatenate([s.data.qpos[None], qpos_t], axis=0)
        return jax.lax.map(lambda qq: render(s.data, qq), q)

    frames = [np.asarray(film(both_keys[j], flags[j], out["qpos_t"][j])) for j in range(2 * len(episodes))]
    n = len(episodes)
    return [{"episode": e, "frames": frames[j], "mirror_frames": frames[n + j],
             "success": bool(out["success"][j]), "mirror_success": bool(out["success"][n + j]),
             "success_t": np.asarray(out["success_t"][j], bool),
             "mirror_success_t": np.asarray(out["success_t"][n + j], bool),
             "nan_actions": int(out["nan_actions"][j]), "mirror_nan_actions": int(out["nan_actions"][n + j])}
            for j, e in enumerate(episodes)]


def _label(frame: np.ndarray, text: str, ok: bool) -> np.ndarray:
    """``frame`` (uint8 [H, W, 3]) with ``text`` in its top-left corner, on a green patch
    once the episode has succeeded and a dark one before."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img)
    box = draw.textbbox((2, 1), text)
    draw.rectangle((0, 0, box[2] + 2, box[3] + 2), fill=(30, 140, 60) if ok else (40, 40, 40))
    draw.text((2, 1), text, fill=(255, 255, 255))
    return np.asarray(img)


def paired_frames(episode: dict, label: bool = True) -> np.ndarray:
    """The episode (left) beside its mirrored twin (right), frame by frame.

    Args:
      episode: one entry of :func:`render_episodes`.
      label: write ``"ep i trained"`` / ``"ep i mirrored"`` on each half (with ``"ok"``
        on a green patch from the step the episode succeeds), and a time bar along the
        bottom row (frame ``t`` of ``T`` fills ``t / T`` of it; it also keeps consecutive
        frames distinct, which GIF encoders would otherwise merge).
    Returns:
      uint8 ``[T + 1, H, 2 W, 3]``.
    """
    a, b = np.asarray(episode["frames"]), np.asarray(episode["mirror_frames"])
    if a.shape != b.shape:
        raise ValueError(f"the two sides' frames differ in shape: {a.shape} and {b.shape}")
    if label:
        i = episode["episode"]
        ok_a = np.concatenate([[False], np.asarray(episode["success_t"], bool)])
        ok_b = np.concatenate([[False], np.asarray(episode["mirror_success_t"], bool)])
        a = np.stack([_label(f, f"ep {i} trained" + (" ok" if s else ""), s) for f, s in zip(a, ok_a)])
        b = np.stack([_label(f, f"ep {i} mirrored" + (" ok" if s else ""), s) for f, s in zip(b, ok_b)])
    pair = np.concatenate([a, b], axis=2)
    if label and len(pair) > 1:  # a time bar along the bottom row: frame t fills t / T of it
        w = pair.shape[2]
        for t in range(len(pair)):
            pair[t, -1, : max(1, round(w * t / (len(pair) - 1)))] = (255, 200, 0)
    return pair


def write_video(frames: np.ndarray, path: str | Path, fps: int = 20) -> Path:
    """Write uint8 ``frames [N, H, W, 3]`` as a video, atomically (a temporary file in the
    same folder, then a rename). The format follows the suffix: ``.gif`` (Pillow, looping;
    Pillow merges equal consecutive frames into one longer frame) or ``.mp4`` (PyAV, H.264, ``yuv420p``: ``H`` and ``W`` must be even).

    Raises:
      ValueError: another suffix, bad shapes or dtype, odd sizes for mp4.
      ImportError: mp4 asked for and PyAV (``av``) is not installed.
    """
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in VIDEO_FORMATS:
        raise ValueError(f"video format must be one of {VIDEO_FORMATS} (the file suffix), got {path.name!r}")
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise ValueError(f"frames must be uint8 [N >= 1, H, W, 3], got {frames.dtype} {frames.shape}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if fmt == "mp4":
        try:
            import av
        except ImportError as e:
            raise ImportError("writing mp4 needs PyAV: pip install av (it is in the dev and interop extras), "
                              "or write a .gif") from e
        if frames.shape[1] % 2 or frames.shape[2] % 2:
            raise ValueError(f"mp4 (yuv420p) needs even frame sizes, got {frames.shape[2]}x{frames.shape[1]}")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        if fmt == "gif":
            from PIL import Image

            imgs = [Image.fromarray(f) for f in frames]
            imgs[0].save(tmp, format="GIF", save_all=True, append_images=imgs[1:], loop=0,
                         duration=max(1, int(round(1000 / fps))))
        else:
            with av.open(tmp, mode="w", format="mp4") as container:
                stream = container.add_stream("libx264", rate=int(fps))
                stream.width, stream.height = frames.shape[2], frames.shape[1]
                stream.pix_fmt = "yuv420p"
                for f in frames:
                    for packet in stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                        container.mux(packet)
                for packet in stream.encode():
                    container.mux(packet)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_paired_videos(env: Env, policy, normalizer, params: Any, config, episodes: Sequence[int],
                        out_dir: str | Path, size: int = 128, fmt: str = "gif", fps: int = 20,
                        every: int = 1, label: bool = True, rollout=None) -> list[dict]:
    """Film chosen episodes of an evaluation and write one paired video per episode.

    Args:
      env, policy, normalizer, params: the evaluated policy.
      config: the evaluation's ``EvalConfig`` (seed, episodes, mirror_noise, temporal_ensemble).
      episodes: indices to film, each in ``[0, config.episodes)``.
      out_dir: videos go to ``out_dir/episode_<i>.<fmt>``.
      size: frame side of each half (pixels). fmt: ``"gif"`` or ``"mp4"``.
      fps: playback rate. every: keep every ``every``-th frame (and the last).
      rollout: the evaluation's ``record_qpos`` rollout to reuse (see :func:`render_episodes`).
    Returns:
      per episode ``{"episode", "path", "frames" (written), "width", "height", "success",
      "mirror_success", "nan_actions", "mirror_nan_actions"}``.
    """
    if fmt not in VIDEO_FORMATS:
        raise ValueError(f"video format must be one of {VIDEO_FORMATS}, got {fmt!r}")
    if int(every) < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if fmt == "mp4" and int(size) % 2:
        raise ValueError(f"mp4 needs an even video size, got {size}")
    if fmt == "mp4":  # fail before the rollouts, not after
        try:
            import av  # noqa: F401
        except ImportError as e:
            raise ImportError("writing mp4 needs PyAV: pip install av, or use --video-format gif") from e
    episodes = check_episodes(episodes, config.episodes)
    eps = render_episodes(env, policy, normalizer, params, jax.random.key(config.seed), config.episodes,
                          episodes, size=size, mirror_noise=config.mirror_noise,
                          temporal_ensemble=config.temporal_ensemble, rollout=rollout, batch=config.batch)
    out = []
    for ep in eps:
        pair = paired_frames(ep, label=label)
        idx = sorted(set(range(0, len(pair), int(every))) | {len(pair) - 1})
        path = write_video(pair[idx], Path(out_dir) / f"episode_{ep['episode']:03d}.{fmt}", fps=fps)
        out.append({"episode": ep["episode"], "path": str(path), "frames": len(idx),
                    "width": int(pair.shape[2]), "height": int(pair.shape[1]),
                    "success": ep["success"], "mirror_success": ep["mirror_success"],
                    "nan_actions": ep["nan_actions"], "mirror_nan_actions": ep["mirror_nan_actions"]})
    return out
