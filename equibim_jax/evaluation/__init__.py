"""Closed-loop evaluation: rollouts, success statistics, tables."""

from equibim_jax.evaluation.stats import wilson_interval

__all__ = ["wilson_interval"]
