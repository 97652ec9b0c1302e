"""Success-rate statistics for closed-loop evaluation.

Closed-loop success is a binomial proportion over few trials (tens to hundreds of
episodes), where the normal-approximation interval is poor near 0 and 1. The Wilson
score interval behaves well there and is what we report in tables.
"""

from __future__ import annotations

import math

__all__ = ["wilson_interval", "paired_sign_test"]


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
    # Float rounding can put an end a hair outside [0, 1] or on the wrong side of p at
    # p = 0 or p = 1; clamp so the interval always contains p (no negative error bars).
    return max(0.0, min(center - half, p)), min(1.0, max(center + half, p))


def paired_sign_test(a, b) -> dict:
    """Exact sign test on paired episodes (McNemar's exact test): does ``b`` beat ``a``?

    Episode ``i`` of ``a`` and of ``b`` share their initial state. Only the discordant pairs
    (one succeeds, the other fails) carry information; under the null hypothesis each goes
    either way with probability 1/2.

    Args:
      a, b: equal-length sequences of booleans (per-episode success).
    Returns:
      ``{"pairs", "discordant", "a_only", "b_only", "p_b_better", "p_two_sided"}``:
      ``p_b_better = P(X >= b_only)`` for ``X ~ Binomial(discordant, 1/2)``;
      ``p_two_sided = min(1, 2 * P(X >= max(a_only, b_only)))``. Both are 1 when no pair
      is discordant. For example 10 pairs all for ``b``: ``p_b_better = 2**-10 = 0.00098``.
    Raises:
      ValueError: if the lengths differ or the sequences are empty.
    """
    a, b = [bool(x) for x in a], [bool(x) for x in b]
    if len(a) != len(b) or not a:
        raise ValueError(f"paired_sign_test: need two equal-length non-empty sequences, got {len(a)} and {len(b)}")
    a_only = sum(x and not y for x, y in zip(a, b))
    b_only = sum(y and not x for x, y in zip(a, b))
    n = a_only + b_only

    def tail(k: int) -> float:  # P(X >= k), X ~ Binomial(n, 1/2)
        return sum(math.comb(n, i) for i in range(k, n + 1)) / 2**n

    return {"pairs": len(a), "discordant": n, "a_only": a_only, "b_only": b_only,
            "p_b_better": tail(b_only) if n else 1.0,
            "p_two_sided": min(1.0, 2 * tail(max(a_only, b_only))) if n else 1.0}
