"""Persistent JAX compilation cache, on by default.

MJX steps and the U-Net train step take 15-35 s to compile on CPU; the cache makes the
second run start in seconds. The cache lives outside the source tree, in
``$EQUIBIM_JAX_CACHE_DIR`` or ``~/.cache/equibim_jax/xla``. Set ``EQUIBIM_JAX_CACHE=0`` to
turn it off before importing the package, or call :func:`disable_compilation_cache`.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

_STATE = {"dir": None}


def default_cache_dir() -> Path:
    env = os.environ.get("EQUIBIM_JAX_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "equibim_jax" / "xla"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on the persistent compilation cache at ``path`` (default: :func:`default_cache_dir`)."""
    d = Path(path).expanduser() if path is not None else default_cache_dir()
    d.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(d))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _STATE["dir"] = d
    return d


def disable_compilation_cache() -> None:
    """Turn the persistent compilation cache off for this process."""
    jax.config.update("jax_compilation_cache_dir", None)
    _STATE["dir"] = None


def compilation_cache_dir() -> Path | None:
    """The active cache directory, or None when the cache is off."""
    return _STATE["dir"]


def _enable_from_env() -> None:
    if os.environ.get("EQUIBIM_JAX_CACHE", "1").lower() in ("0", "false", "off", "no"):
        return
    try:
        enable_compilation_cache()
    except OSError:  # read-only home: run without a cache rather than fail
        pass
