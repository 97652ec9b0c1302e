"""The ``equibim export`` and ``equibim import`` commands (wired in ``equibim_jax.cli``)."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Literal

import tyro

from equibim_jax.config import ConfigError


def _as_config_error(fn):
    """Run ``fn``; a data, mapping or missing-dependency error becomes a ConfigError (exit 2)."""
    from equibim_jax.data.dataset import DatasetError

    try:
        return fn()
    except (DatasetError, FileExistsError, ImportError) as e:
        raise ConfigError(str(e)) from None


@dataclasses.dataclass
class Export:
    """Write one of our datasets as a DP3 / Diffusion Policy ReplayBuffer zarr (--format dp3) or a
    LeRobotDataset v3 (--format lerobot: parquet frames, mp4 videos, meta/). See docs/data.md."""

    src: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="SRC")]
    """Our dataset (a .zarr written by `equibim generate` or `equibim import`)."""
    out: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Directory to write."""
    format: Literal["dp3", "lerobot"]
    """Target format."""
    overwrite: bool = False
    """Replace an existing --out."""
    fps: float | None = None
    """LeRobot: frames per second (default: the dataset's own rate)."""
    task: str | None = None
    """LeRobot: the task string of every episode (default: the dataset's task name)."""
    video_codec: str = "libx264"
    """LeRobot: video codec (PyAV encoder name, e.g. libx264, libsvtav1)."""
    crf: int = 18
    """LeRobot: video quality (lower is closer to the original)."""

    def run(self) -> None:
        from equibim_jax.interop import export_dataset

        opts = {}
        if self.format == "lerobot":
            opts = {"fps": self.fps, "task": self.task, "video": {"codec": self.video_codec, "crf": self.crf}}
        elif (self.fps, self.task) != (None, None):
            raise ConfigError("--fps and --task apply to --format lerobot only")
        out = _as_config_error(lambda: export_dataset(self.format, self.src, self.out, overwrite=self.overwrite,
                                                      **opts))
        print(f"wrote {out} ({self.format})")


@dataclasses.dataclass
class Import:
    """Read a DP3 / Diffusion Policy ReplayBuffer zarr (--format dp3) or a LeRobotDataset v3
    (--format lerobot) into one of our datasets, mapping its features onto our fields
    (--mapping mapping.json; defaults per format). See docs/data.md."""

    src: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="SRC")]
    """The dataset to read."""
    out: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Our dataset to write (a .zarr directory)."""
    format: Literal["dp3", "lerobot"]
    """Source format."""
    mapping: str | None = None
    """JSON mapping of source features onto our fields (entries laid over the format's defaults)."""
    overwrite: bool = False
    """Replace an existing --out."""

    def run(self) -> None:
        from equibim_jax.interop import import_dataset

        d = _as_config_error(lambda: import_dataset(self.format, self.src, self.out, self.mapping,
                                                    overwrite=self.overwrite))
        rec = d.meta["interop"]
        print(f"wrote {self.out}: {d.n_episodes} episodes, {d.n_steps} steps; fields "
              f"{ {k: list(v.shape[2:]) for k, v in d.obs.items()} }, action {d.action.shape[-1]}; "
              f"cameras {rec.get('cameras') or 'none'}")
