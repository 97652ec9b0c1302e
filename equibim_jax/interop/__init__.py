"""Real data in and out: other dataset formats, and ``S`` for data without a simulated env.

- :mod:`.dp3`: Diffusion Policy / DP3 ``ReplayBuffer`` zarr (``data/<key>``,
  ``meta/episode_ends``).
- :mod:`.lerobot`: LeRobotDataset v3 (parquet frames, mp4 videos, ``meta/info.json``).
- :mod:`.mapping`: the declared mapping of their features onto our fields.
- :mod:`.symmetry`: ``S`` of an imported dataset from a mirror map JSON
  (``equibim symmetry --out``), checked against the dataset's names, sizes and cameras.

Commands: ``equibim export --format dp3|lerobot SRC OUT``, ``equibim import --format
dp3|lerobot SRC OUT [--mapping mapping.json]``, ``equibim train --data IMPORTED --symmetry
map.json``. pyarrow and PyAV are optional (``pip install 'equibim-jax[interop]'``) and
imported only when a format needs them. See docs/data.md.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

from equibim_jax.interop.mapping import FeatureMapping, InteropError, load_mapping
from equibim_jax.interop.symmetry import MapEnv, map_env, symmetry_ops_from_map, training_env

FORMATS = ("dp3", "lerobot")

__all__ = ["FORMATS", "FeatureMapping", "InteropError", "MapEnv", "export_dataset", "import_dataset", "load_mapping",
           "map_env", "read_dataset", "symmetry_ops_from_map", "training_env"]


def _check_format(fmt: str) -> None:
    if fmt not in FORMATS:
        raise InteropError(f"unknown format {fmt!r}; valid formats: {list(FORMATS)}")


def export_dataset(fmt: str, src, out: str | os.PathLike, overwrite: bool = False, **options) -> Path:
    """Export our dataset ``src`` (path or Demos) to ``out`` in format ``fmt``
    (``"dp3"`` or ``"lerobot"``; ``options`` go to :func:`.lerobot.export_lerobot`)."""
    _check_format(fmt)
    if fmt == "dp3":
        if options:
            raise InteropError(f"options {sorted(options)} apply to --format lerobot only")
        from equibim_jax.interop.dp3 import export_dp3

        return export_dp3(src, out, overwrite=overwrite)
    from equibim_jax.interop.lerobot import export_lerobot

    return export_lerobot(src, out, overwrite=overwrite, **options)


def read_dataset(fmt: str, src: str | os.PathLike, mapping: Mapping | str | os.PathLike | None = None):
    """Read ``src`` in format ``fmt`` into our Demos. ``mapping``: a dict or a JSON file path."""
    _check_format(fmt)
    if mapping is not None and not isinstance(mapping, Mapping):
        mapping = load_mapping(mapping)
    if fmt == "dp3":
        from equibim_jax.interop.dp3 import read_dp3

        return read_dp3(src, mapping)
    from equibim_jax.interop.lerobot import read_lerobot

    return read_lerobot(src, mapping)


def import_dataset(fmt: str, src: str | os.PathLike, out: str | os.PathLike,
                   mapping: Mapping | str | os.PathLike | None = None, overwrite: bool = False):
    """:func:`read_dataset` then save it as our dataset at ``out`` (atomically). Returns the Demos."""
    from equibim_jax.data.dataset import save

    demos = read_dataset(fmt, src, mapping)
    save(demos, out, overwrite=overwrite)
    return demos
