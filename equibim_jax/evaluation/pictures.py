"""Pictures of the task suite: a grid of head-camera frames and one GIF per task.

Each task's scripted expert runs one episode from a seeded start and one from the mirror
image of that start (``env.mirror_state``), with the head camera rendered every step
(the package's ray-cast renderer, the same one that makes the policies' images). The grid
shows, per task, the first and the last frame of both episodes; the GIF plays the episode
beside its mirror image. Images are written with Pillow (GIF encoding, PNG); the grid is
laid out with matplotlib.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Sequence
from pathlib import Path

import jax
import numpy as np

__all__ = ["expert_frames", "make_pictures", "task_gif", "task_grid"]


def expert_frames(task: str, seed: int = 0, image_size: int = 128, options: dict | None = None) -> dict:
    """Head-camera frames of one expert episode and of its mirror image.

    Args:
      task: a registered task with an expert.
      seed: PRNG seed of the start (``jax.random.key(seed)``).
      image_size: square frame side (pixels).
      options: further task options (``make_env``).

    Returns:
      ``{"frames": uint8 [T + 1, H, W, 3], "mirror_frames": uint8 [T + 1, H, W, 3],
      "success": bool, "mirror_success": bool}``; frame 0 is the start, frame ``t`` the
      state after ``t`` control steps, ``T`` the expert's script plus 10 steps.
    """
    from equibim_jax.experts import make_rollout
    from equibim_jax.tasks import make_env, make_expert

    env = make_env(task, **{**dict(options or {}), "obs": ("image",), "image_size": int(image_size)})
    expert = make_expert(env)
    length = min(expert.horizon + 10, env.config.episode_length)
    roll = make_rollout(env, expert, length=length, obs=True)

    @jax.jit
    def run(key):
        s0 = env.reset(key)
        s0m = env.mirror_state(s0)
        both = jax.tree.map(lambda a, b: jax.numpy.stack([a, b]), s0, s0m)
        final, traj = jax.vmap(roll.from_state)(both)
        # traj["obs"] holds the frame each action was chosen from; add the final frame
        frames = jax.numpy.concatenate([traj["obs"]["image"], final.obs["image"][:, None]], axis=1)
        return frames, final.info["success"]

    frames, success = jax.device_get(run(jax.random.key(seed)))
    def to_u8(f):  # the renderer gives uint8, or float32 in [0, 1]
        f = np.asarray(f)
        return f if f.dtype == np.uint8 else np.clip(f * 255.0 + 0.5, 0, 255).astype(np.uint8)

    return {"frames": to_u8(frames[0]), "mirror_frames": to_u8(frames[1]),
            "success": bool(success[0]), "mirror_success": bool(success[1])}


def task_gif(frames: dict, out: str | Path, every: int = 5, fps: int = 12, max_bytes: int = 1_000_000) -> Path:
    """Write the episode beside its mirror image as a looping GIF.

    Args:
      frames: :func:`expert_frames`'s result.
      out: the ``.gif`` path (written atomically).
      every: keep every ``every``-th frame (and the last).
      fps: playback frames per second.
      max_bytes: the GIF is re-encoded with fewer frames until it is at most this big.

    Returns:
      the path written.
    """
    from PIL import Image

    from equibim_jax._io import atomic_write_bytes

    pair = np.concatenate([frames["frames"], np.full_like(frames["frames"][:, :, :4], 255),
                           frames["mirror_frames"]], axis=2)  # [T, H, 2W + 4, 3]
    while True:
        idx = sorted(set(range(0, len(pair), every)) | {len(pair) - 1})
        imgs = [Image.fromarray(pair[i]).quantize(colors=64, method=Image.Quantize.MEDIANCUT) for i in idx]
        buf = io.BytesIO()
        imgs[0].save(buf, format="GIF", save_all=True, append_images=imgs[1:], loop=0,
                     duration=int(1000 / fps), optimize=True)
        if buf.tell() <= max_bytes or every >= len(pair):
            break
        every *= 2
    atomic_write_bytes(out, buf.getvalue())
    return Path(out)


def task_grid(frames: dict[str, dict], out: str | Path, dpi: int = 100) -> Path:
    """A grid of first and last frames: per task four panels, episode start, episode end,
    mirrored start, mirrored end (tasks in two side-by-side columns when there are more
    than three). Written atomically as PNG.

    Args:
      frames: ``{task: expert_frames(task, ...)}``.
      out: the ``.png`` path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from equibim_jax._io import atomic_write_bytes

    tasks = list(frames)
    cols = ("start", "end", "mirrored start", "mirrored end")
    groups = 2 if len(tasks) > 3 else 1  # tasks side by side, four columns each
    rows = -(-len(tasks) // groups)
    fig, axes = plt.subplots(rows, 4 * groups, figsize=(4 * groups * 1.6, rows * 1.75), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for i, task in enumerate(tasks):
        r, g = i % rows, i // rows
        f = frames[task]
        imgs = (f["frames"][0], f["frames"][-1], f["mirror_frames"][0], f["mirror_frames"][-1])
        ok = (None, f["success"], None, f["mirror_success"])
        for c, (img, s) in enumerate(zip(imgs, ok)):
            ax = axes[r, 4 * g + c]
            ax.axis("on")
            ax.imshow(img)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=8)
            if c == 0:
                ax.set_ylabel(task, fontsize=7)
            if s is not None:
                ax.text(0.03, 0.05, "success" if s else "failure", transform=ax.transAxes, fontsize=6,
                        color="white", bbox={"facecolor": "green" if s else "red", "pad": 1, "lw": 0})
    fig.tight_layout(pad=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(out, buf.getvalue())
    return Path(out)


def make_pictures(tasks: Sequence[str] | Iterable[str], out_dir: str | Path, seed: int = 0,
                  image_size: int = 128, cache_dir: str | Path | None = None, progress: bool = True,
                  grid: str = "tasks.png") -> dict:
    """:func:`expert_frames` for each task, then the grid ``out_dir/<grid>`` and
    ``out_dir/gifs/<task>.gif``. With ``cache_dir``, each task's frames are kept there
    (``<task>_<seed>_<size>.npz``) and reused, so an interrupted run resumes.

    Returns:
      ``{task: {"success": bool, "mirror_success": bool, "gif": path, "gif_bytes": int}}``.
    """
    from tqdm.auto import tqdm

    out_dir = Path(out_dir)
    frames, summary = {}, {}
    for task in tqdm(list(tasks), desc="pictures", disable=not progress):
        cached = Path(cache_dir) / f"{task}_{seed}_{image_size}.npz" if cache_dir else None
        if cached is not None and cached.exists():
            with np.load(cached) as z:
                f = {k: z[k] for k in z.files}
            f = {**f, "success": bool(f["success"]), "mirror_success": bool(f["mirror_success"])}
        else:
            f = expert_frames(task, seed, image_size)
            if cached is not None:
                cached.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(cached, **f)
        frames[task] = f
        gif = task_gif(f, out_dir / "gifs" / f"{task}.gif")
        summary[task] = {"success": f["success"], "mirror_success": f["mirror_success"],
                         "gif": str(gif), "gif_bytes": gif.stat().st_size}
    task_grid(frames, out_dir / grid)
    return summary
