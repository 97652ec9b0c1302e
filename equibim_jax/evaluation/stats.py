"""Success-rate statistics for closed-loop evaluation.

Closed-loop success is a binomial proportion over few trials (tens to hundreds of
episodes), where the normal-approximation interval is poor near 0 and 1. The Wilson
score interval behaves well there and is what we report in tables.
"""

from __future__ import annotations

import math

__all__ = ["wilson_interval"]


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a binomial success rate.

    Args:
      successes: number of successful episodes, an integer in ``[0, n]``.
      n: number of episodes, a positive integer.
      z: the standard-normal quantile; 1.96 gives a two-sided 95% interval.

    Returns:
      ``(lo, hi)``, floats with ``0 <= lo <= successes / n <= hi <= 1``.
      For example 0/10 -> (0.0, 0.2775), 5/10 -> (0.2366, 0.7634).

    Raises:
      ValueError: if ``n <= 0``, ``successes`` is outside ``[0, n]``, either is not an
        integer, or ``z`` is not a positive finite number.
    """
    for name, value in (("successes", successes), ("n", n)):
        if isinstance(value, bool) or int(value) != value:
            raise ValueError(f"wilson_interval: {name} must be an integer, got {value!r}")
    successes, n = int(successes), int(n)
    if n <= 0:
        raise ValueError(f"wilson_interval: n must be positive (no episodes run), got n={n}")
    if not 0 <= successes <= n:
        raise ValueError(
            f"wilson_interval: successes must lie in [0, n]; got successes={successes}, n={n}"
        )
    if not (math.isfinite(z) and z > 0):
        raise ValueError(f"wilson_interval: z must be a positive finite number, got {z!r}")
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    center = (p + z2 / (2 * n)) / denom
    half = (z / denom) * math.sqrt(p * (1.0 - p) / n + z2 / (4 * n * n))
    # Rounding can push the ends a hair past [0, 1] at p = 0 or p = 1.
    return max(0.0, center - half), min(1.0, center + half)
