"""XLA compiler options for the train step (CPU only).

On XLA:CPU, fusions handed to YNNPACK cover dots, element-wise ops and reductions. For the
diffusion-policy train step, keeping only the dots in YNNPACK fusions
(``xla_cpu_experimental_ynn_fusion_type=LIBRARY_FUSION_TYPE_DOT``) is the faster choice on
small CPUs; ``benchmarks/train.py --compare-xla-tuning`` measures both (figures in
``benchmarks/README.md``). MJX physics gets slower when reductions leave YNNPACK
process-wide, so the option is passed per ``jit``, to the train step and loop only.

``EQUIBIM_JAX_XLA_TUNING=0`` turns it off. Other backends get no options.
"""

from __future__ import annotations

import os

import jax

TRAIN_CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_DOT"}


def tuning_enabled() -> bool:
    """Whether ``EQUIBIM_JAX_XLA_TUNING`` allows the options (default: yes)."""
    return os.environ.get("EQUIBIM_JAX_XLA_TUNING", "1").strip().lower() not in ("0", "false", "no", "off")


def train_compiler_options() -> dict[str, str] | None:
    """``compiler_options`` for ``jax.jit`` of a train step: :data:`TRAIN_CPU_OPTIONS` on
    the CPU backend when tuning is enabled, else ``None``."""
    if not tuning_enabled() or jax.default_backend() != "cpu":
        return None
    return dict(TRAIN_CPU_OPTIONS)
