"""equibim-jax: EquiBim (left-right symmetry regularisation for bimanual imitation) in JAX.

Importing the package turns on the persistent JAX compilation cache (see
``equibim_jax._cache``); set ``EQUIBIM_JAX_CACHE=0`` to opt out.
"""

from equibim_jax._cache import (
    compilation_cache_dir,
    disable_compilation_cache,
    enable_compilation_cache,
)
from equibim_jax._cache import _enable_from_env

_enable_from_env()
del _enable_from_env

__version__ = "0.1.0"


def __getattr__(name):
    # The task registry loads MuJoCo and MJX, so it is imported on first use.
    if name in ("make_env", "task_names", "make_expert"):
        from equibim_jax import tasks

        return getattr(tasks, name)
    raise AttributeError(f"module 'equibim_jax' has no attribute {name!r}")


__all__ = [
    "__version__",
    "make_env",
    "make_expert",
    "task_names",
    "compilation_cache_dir",
    "disable_compilation_cache",
    "enable_compilation_cache",
]
