"""Closed-loop evaluation: rollouts, success statistics, open-loop checks."""

from equibim_jax.evaluation.stats import paired_sign_test, wilson_interval

__all__ = ["wilson_interval", "paired_sign_test"]
