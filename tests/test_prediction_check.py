"""The noise-or-sample prediction check (``equibim_jax.experiments.prediction_check``)."""

from __future__ import annotations

import json

import pytest

from equibim_jax.experiments import prediction_check

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)


def test_bad_sizes_are_refused(tmp_path):
    with pytest.raises(SystemExit):
        prediction_check.main(["--steps", "0", "--out", str(tmp_path / "x.json")])
    assert not (tmp_path / "x.json").exists()


def test_unknown_preset_is_refused_by_name():
    with pytest.raises(ValueError, match="dp_image_joint"):
        prediction_check.run("click_bell", preset="dp_image_joint")
    with pytest.raises(SystemExit):
        prediction_check.main(["--preset", "nope"])


@pytest.mark.slow  # generates demos and compiles four train steps and samplers
def test_tiny_run_reports_every_variant(tmp_path):
    out = tmp_path / "p.json"
    prediction_check.main(["--task", "click_bell", "--steps", "4", "--demos", "2", "--out", str(out),
                           "--no-progress"])
    res = json.loads(out.read_text())
    assert set(res["variants"]) == {"joint/epsilon", "joint/sample", "ee/epsilon", "ee/sample"}
    for name, v in res["variants"].items():
        n_act = 14 if name.startswith("joint") else 20
        assert len(v["open_loop_abs_err_normalized"]) == n_act
        assert v["bc"] and all(b == b for _, b in v["bc"])  # logged and finite
    assert all(0 <= c < 20 for c in res["constant_ee_channels"])
