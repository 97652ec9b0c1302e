"""Checkpoints: TrainState + normaliser + config (JSON), with orbax-checkpoint.

Layout: ``<directory>/<step>/{state,normalizer,config,shapes}``; ``config`` and
``shapes`` (path -> [shape, dtype] of every state array) are JSON, read and checked
before any array is. Orbax writes each checkpoint
into a temporary ``<step>.orbax-checkpoint-tmp-*`` folder and renames it when complete,
so a crash mid-write leaves no folder that looks like a finished step;
:func:`latest_step` ignores the temporary folders.

Only the array leaves of the state are stored (``step, params, ema_params,
opt_state``); the static ``policy`` and ``tx`` come from the template state the caller
builds from the same config (:func:`read_checkpoint_config` reads it first). Restoring into that template is exact (bitwise).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from equibim_jax.config import config_to_dict
from equibim_jax.data.normalizer import Normalizer
from equibim_jax.training.train_step import TrainState

__all__ = [
    "CheckpointError",
    "save_checkpoint",
    "read_checkpoint_config",
    "restore_checkpoint",
    "latest_step",
]


class CheckpointError(RuntimeError):
    """A checkpoint is missing, incomplete, corrupt, or does not match the expected config."""


def _diff(expected: Any, saved: Any, path: str = "") -> list[str]:
    if isinstance(expected, Mapping) and isinstance(saved, Mapping):
        out = []
        for k in sorted(set(expected) | set(saved)):
            p = f"{path}.{k}" if path else str(k)
            if k not in saved:
                out.append(f"{p}: missing in checkpoint")
            elif k not in expected:
                out.append(f"{p}: only in checkpoint ({saved[k]!r})")
            else:
                out.extend(_diff(expected[k], saved[k], p))
        return out
    return [] if expected == saved else [f"{path}: expected {expected!r}, checkpoint has {saved!r}"]


def _state_tree(state: TrainState) -> dict[str, Any]:
    return {
        "step": state.step,
        "params": state.params,
        "ema_params": state.ema_params,
        "opt_state": state.opt_state,
    }


def _shape_manifest(tree: Any) -> dict[str, list]:
    """``{path: [shape, dtype]}`` of every leaf, to check a template before reading arrays."""
    return {
        jax.tree_util.keystr(path): [list(np.shape(x)), str(np.dtype(x.dtype))]
        for path, x in jax.tree_util.tree_leaves_with_path(tree)
    }


def _manager(directory: Path, max_to_keep: int | None = None) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(
        directory,
        options=ocp.CheckpointManagerOptions(
            max_to_keep=max_to_keep, create=True, enable_async_checkpointing=False
        ),
    )


def latest_step(directory: str | os.PathLike) -> int | None:
    """Largest completed step saved under ``directory`` (temporary folders ignored), or None."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    steps = [int(p.name) for p in directory.iterdir() if p.is_dir() and p.name.isdigit()]
    return max(steps) if steps else None


def save_checkpoint(
    directory: str | os.PathLike,
    state: TrainState,
    normalizer: Normalizer,
    config: Any,
    *,
    step: int | None = None,
    max_to_keep: int | None = None,
) -> Path:
    """Save ``state``, ``normalizer`` and ``config`` atomically as ``<directory>/<step>``.

    Args:
      directory: checkpoint root (created if needed).
      state: the :class:`TrainState` (its array leaves are saved).
      normalizer: the fitted :class:`Normalizer`.
      config: a frozen-dataclass config, or a dict of them (saved as JSON).
      step: checkpoint number; defaults to ``int(state.step)``.
      max_to_keep: keep only this many most recent checkpoints (None keeps all).
    Returns:
      path of the finished checkpoint folder.
    Raises:
      CheckpointError: if that step already exists.
    """
    directory = Path(directory).absolute()
    step = int(jax.device_get(state.step)) if step is None else int(step)
    if (directory / str(step)).exists():
        raise CheckpointError(f"checkpoint {directory / str(step)} already exists")
    config_json = config_to_dict(config)
    json.dumps(config_json)  # fail before writing anything if it is not JSON-able
    mngr = _manager(directory, max_to_keep)
    try:
        mngr.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(_state_tree(state)),
                normalizer=ocp.args.StandardSave(normalizer.to_state_dict()),
                config=ocp.args.JsonSave(config_json),
                shapes=ocp.args.JsonSave(_shape_manifest(_state_tree(state))),
            ),
        )
        mngr.wait_until_finished()
    finally:
        mngr.close()
    return directory / str(step)


def _resolve_step(directory: Path, step: int | None) -> tuple[int, Path]:
    if step is None:
        step = latest_step(directory)
        if step is None:
            raise FileNotFoundError(f"no completed checkpoint under {directory}")
    path = directory / str(step)
    if not path.is_dir():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    return step, path


def read_checkpoint_config(directory: str | os.PathLike, step: int | None = None) -> dict[str, Any]:
    """The JSON config saved with a checkpoint (latest completed one by default), read
    without touching any array.

    Raises:
      FileNotFoundError: no such checkpoint. CheckpointError: unreadable config.
    """
    directory = Path(directory).absolute()
    step, path = _resolve_step(directory, step)
    mngr = _manager(directory)
    try:
        return mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
    except Exception as e:  # orbax raises assorted types for broken files
        raise CheckpointError(f"checkpoint {path}: cannot read its config ({e})") from e
    finally:
        mngr.close()


def restore_checkpoint(
    directory: str | os.PathLike,
    template: TrainState,
    *,
    expected_config: Any = None,
    step: int | None = None,
    ignore_config_keys: tuple[str, ...] = (),
) -> tuple[TrainState, Normalizer, dict[str, Any]]:
    """Restore a checkpoint into the structure of ``template``.

    Args:
      directory: checkpoint root.
      template: a state built from the same config (e.g. ``create_train_state``); its
        tree structure, shapes, dtypes and static ``policy``/``tx`` are used.
      expected_config: if given, the saved config must equal ``config_to_dict`` of it.
      step: which checkpoint; defaults to the latest completed one.
      ignore_config_keys: dotted config paths not compared (e.g. ``"train.total_steps"``).
    Returns:
      ``(state, normalizer, config_dict)``.
    Raises:
      FileNotFoundError: no such directory or no completed checkpoint / step.
      CheckpointError: the checkpoint is incomplete or corrupt, or its config or array
        shapes do not match.
    """
    directory = Path(directory).absolute()
    step, path = _resolve_step(directory, step)
    mngr = _manager(directory)
    try:
        try:
            meta = mngr.restore(
                step,
                args=ocp.args.Composite(
                    config=ocp.args.JsonRestore(), shapes=ocp.args.JsonRestore()
                ),
            )
            saved_config, saved_shapes = meta["config"], meta["shapes"]
        except Exception as e:  # orbax raises assorted types for broken files
            raise CheckpointError(
                f"checkpoint {path}: cannot read config or shape manifest ({e})"
            ) from e
        if expected_config is not None:
            problems = [
                d
                for d in _diff(config_to_dict(expected_config), saved_config)
                if not any(d.startswith(k + ":") or d.startswith(k + ".") for k in ignore_config_keys)
            ]
            if problems:
                raise CheckpointError(
                    f"checkpoint {path} was saved with a different config:\n  "
                    + "\n  ".join(problems)
                )
        # Check shapes against the small JSON manifest before orbax reads any array: a
        # mismatch found mid-read leaves tensorstore callbacks pending on a closed loop.
        expected_shapes = _shape_manifest(_state_tree(template))
        if saved_shapes != expected_shapes:
            diffs = _diff(expected_shapes, saved_shapes)
            raise CheckpointError(
                f"checkpoint {path}: arrays do not match the template ({len(diffs)} "
                "differences; a different model or optimiser config?):\n  "
                + "\n  ".join(diffs[:8])
            )
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _state_tree(template))
        try:
            restored = mngr.restore(
                step,
                args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(abstract),
                    normalizer=ocp.args.StandardRestore(),
                ),
            )
        except Exception as e:
            raise CheckpointError(
                f"checkpoint {path}: cannot restore state/normaliser into the template "
                f"(corrupt files or a different model/optimiser?): {type(e).__name__}: {e}"
            ) from e
    finally:
        mngr.close()
    tree = restored["state"]
    # Orbax checks tree structure but may cast mismatching shapes; verify them ourselves.
    bad = [
        f"{jax.tree_util.keystr(p)}: {a.shape} vs template {b.shape}"
        for (p, a), b in zip(
            jax.tree_util.tree_leaves_with_path(tree), jax.tree.leaves(abstract), strict=True
        )
        if a.shape != b.shape or a.dtype != b.dtype
    ]
    if bad:
        raise CheckpointError(f"checkpoint {path}: arrays do not match the template: {bad[:5]}")
    # Orbax returns arrays committed to a device; a fresh state's arrays are uncommitted,
    # and jit keys its cache on that, so the restored state would recompile the train
    # step. Re-create them uncommitted (a bitwise copy).
    tree = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), tree)
    state = template.replace(
        step=tree["step"],
        params=tree["params"],
        ema_params=tree["ema_params"],
        opt_state=tree["opt_state"],
    )
    return state, Normalizer.from_state_dict(restored["normalizer"]), saved_config
