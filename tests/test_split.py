"""Outcomes split by a property of the start (``equibim_jax.experiments.split``)."""

from __future__ import annotations

import pytest

from equibim_jax.config import ConfigError
from equibim_jax.experiments.split import markdown, split_outcomes, start_info

N = 6
OPTS = {"obs": ["qpos"], "action": "joint", "side": "both"}


def _results(base_trained, base_mirrored, eq_trained, eq_mirrored) -> dict:
    ev = lambda t, m: {"trained": {"per_episode": t}, "mirrored": {"per_episode": m}}  # noqa: E731
    return {"cells": {"c": {"evals": {"d": {"baseline": ev(base_trained, base_mirrored),
                                            "equibim": ev(eq_trained, eq_mirrored)}}}},
            "configs": {"c": {"task": {"name": "drumstick_hook", "options": OPTS},
                              "evals": [["d", OPTS]], "eval": {"seed": 3, "episodes": N}}}}


def test_split_groups_each_episode_by_its_own_start_and_the_mirror_flips_the_side():
    info = start_info("drumstick_hook", OPTS, 3, N, "side")
    tr, mi = info["trained"], info["mirrored"]
    assert tr.shape == (N,) and set(tr.tolist()) <= {-1.0, 1.0}
    assert (mi == -tr).all()  # the mirror image of a start has the stick on the other side
    # baseline: succeeds exactly on the trained-side starts with the stick on the left;
    # equibim: succeeds everywhere
    left = (tr > 0).tolist()
    split = split_outcomes(_results(left, [False] * N, [True] * N, [True] * N), "c", "side")
    g = split["groups"]
    n_left_tr = int((tr > 0).sum())
    assert g["1.0"]["episodes"] == {"trained": n_left_tr, "mirrored": N - n_left_tr}
    assert g["1.0"]["arms"]["baseline"]["successes"] == n_left_tr
    assert g["-1.0"]["arms"]["baseline"]["successes"] == 0
    assert g["1.0"]["arms"]["equibim"]["successes"] == N and g["-1.0"]["arms"]["equibim"]["episodes"] == N
    t = g["-1.0"]["sign_tests"]["equibim"]
    assert (t["b_only"], t["a_only"]) == (N, 0)
    assert "| -1.0 |" in markdown(split)


def test_split_names_bad_input():
    r = _results([True] * N, [True] * N, [True] * N, [True] * N)
    with pytest.raises(ConfigError, match="no cell"):
        split_outcomes(r, "nope", "side")
    with pytest.raises(ConfigError, match="no evaluation"):
        split_outcomes(r, "c", "side", evaluation="x")
    with pytest.raises(ConfigError, match="has no 'nope'"):
        split_outcomes(r, "c", "nope")
    r["cells"]["c"]["evals"]["d"]["equibim"]["trained"]["per_episode"] = [True] * (N - 1)
    with pytest.raises(ConfigError, match="outcomes"):
        split_outcomes(r, "c", "side")
