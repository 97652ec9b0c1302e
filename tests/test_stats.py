"""Wilson score interval: values worked out by hand, and argument checks."""

import math

import pytest

from equibim_jax.evaluation.stats import wilson_interval


@pytest.mark.parametrize(
    "successes,n,expected",
    [
        # z = 1.96, z^2 = 3.8416. 0/10: centre = half = 0.19208 / 1.38416 = 0.138770.
        (0, 10, (0.0, 0.277540)),
        # 5/10: centre 0.5, half = (1.96 / 1.38416) * sqrt(0.025 + 0.0096040) = 0.263411.
        (5, 10, (0.236589, 0.763411)),
        (10, 10, (0.722460, 1.0)),
        # 8/20: denom 1.19208, centre 0.49604 / 1.19208 = 0.416113,
        # half = 1.644185 * sqrt(0.012 + 0.002401) = 0.197309.
        (8, 20, (0.218804, 0.613422)),
        # 1/1: centre (1 + 1.9208) / 4.8416 = 0.603272, half = 0.404825 * sqrt(0.9604) = 0.396728.
        (1, 1, (0.206544, 1.0)),
    ],
)
def test_wilson_hand_values(successes, n, expected):
    lo, hi = wilson_interval(successes, n)
    assert lo == pytest.approx(expected[0], abs=2e-6)
    assert hi == pytest.approx(expected[1], abs=2e-6)


def test_wilson_contains_point_estimate_and_narrows_with_n():
    widths = []
    for n in (10, 100, 1000):
        lo, hi = wilson_interval(3 * n // 10, n)
        assert lo < 0.3 < hi
        widths.append(hi - lo)
    assert widths[0] > widths[1] > widths[2]


@pytest.mark.parametrize("n", [1, 7, 10, 32, 100, 1000])
def test_wilson_ends_bracket_the_rate_exactly_at_all_or_none(n):
    # 100/100 once gave hi = 0.9999999999999999 < 1.0 and a plot's error bar went negative.
    for k in (0, n):
        lo, hi = wilson_interval(k, n)
        assert 0.0 <= lo <= k / n <= hi <= 1.0


def test_wilson_z_changes_width():
    lo1, hi1 = wilson_interval(5, 10, z=1.0)
    lo2, hi2 = wilson_interval(5, 10, z=2.576)
    assert hi1 - lo1 < hi2 - lo2
    # z = 1: half = (1 / 1.1) * sqrt(0.025 + 0.0025) = 0.150756.
    assert hi1 == pytest.approx(0.5 + 0.150756, abs=1e-6)


@pytest.mark.parametrize(
    "args,match",
    [
        ((0, 0), "n must be positive"),
        ((3, -1), "n must be positive"),
        ((11, 10), r"successes must lie in \[0, n\]"),
        ((-1, 10), r"successes must lie in \[0, n\]"),
        ((2.5, 10), "must be an integer"),
    ],
)
def test_wilson_errors(args, match):
    with pytest.raises(ValueError, match=match):
        wilson_interval(*args)


def test_wilson_bad_z():
    with pytest.raises(ValueError, match="z must be"):
        wilson_interval(1, 2, z=0.0)
    with pytest.raises(ValueError, match="z must be"):
        wilson_interval(1, 2, z=math.nan)


def test_paired_sign_test_hand_values():
    from equibim_jax.evaluation import paired_sign_test

    # 10 discordant pairs, all for b: P(X >= 10) = 2^-10; two-sided doubles it.
    r = paired_sign_test([False] * 32, [True] * 10 + [False] * 22)
    assert (r["pairs"], r["discordant"], r["a_only"], r["b_only"]) == (32, 10, 0, 10)
    assert r["p_b_better"] == pytest.approx(2**-10)
    assert r["p_two_sided"] == pytest.approx(2**-9)
    # 8 pairs for a, 2 for b, 20 concordant: P(X >= 2) = 1 - 11/1024; two-sided 2 * 56/1024.
    a = [True] * 8 + [False] * 2 + [True] * 10 + [False] * 10
    b = [False] * 8 + [True] * 2 + [True] * 10 + [False] * 10
    r = paired_sign_test(a, b)
    assert (r["discordant"], r["a_only"], r["b_only"]) == (10, 8, 2)
    assert r["p_b_better"] == pytest.approx(1 - 11 / 1024)
    assert r["p_two_sided"] == pytest.approx(112 / 1024)
    # No discordant pair: no evidence either way.
    r = paired_sign_test([True, False], [True, False])
    assert r["p_b_better"] == 1.0 and r["p_two_sided"] == 1.0
    with pytest.raises(ValueError, match="equal-length"):
        paired_sign_test([True], [True, False])
    with pytest.raises(ValueError, match="equal-length"):
        paired_sign_test([], [])
