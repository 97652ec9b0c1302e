"""The simulator benchmarks' variant syntax and their report sections (no timing runs)."""

from __future__ import annotations

import importlib.util
import pathlib

import pytest

BENCH = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_variant_spec_parses_devices_contacts_and_solver_limits():
    sim = _load("sim")
    assert sim._variant("2:24") == (2, 24, None, None)
    assert sim._variant("1:all") == (1, None, None, None)
    assert sim._variant("2:24:3:4") == (2, 24, 3, 4)
    for bad in ("2:24:3", "x:24", "2:24:a:b"):
        with pytest.raises(ValueError):
            sim._variant(bad)
    with pytest.raises(SystemExit):  # argparse names the bad variant before any timing
        sim.main(["--out", "/dev/null", "--variants", "2:24:3"])


def _sim_result(solver_variant: bool) -> dict:
    r = {"compile_s": 1.0, "run_s": 0.5, "steps_per_s": 5000.0}
    variants = {"2:24": {"devices": 2, "max_contacts": 24, "contacts": 24, "constraint_rows": 160,
                         "solver_iterations": 4, "ls_iterations": 8, "mjx": {"256": r}}}
    if solver_variant:
        variants["2:24:3:4"] = {"devices": 2, "max_contacts": 24, "contacts": 24, "constraint_rows": 160,
                                "solver_iterations": 3, "ls_iterations": 4, "c_steps_per_s_same_solver": 25000.0,
                                "mjx": {"256": {**r, "steps_per_s": 10000.0}}}
    return {"c_steps_per_s": 50000.0, "rollout_steps_per_s": 60000.0, "mjx_steps_per_s": {"256": 5000.0},
            "compile_s": {"mjx_batch_256": 1.0}, "run_s": {"mjx_batch_256": 0.5}, "headline_variant": "2:24",
            "variants": variants, "model": {"iterations": 4, "ls_iterations": 8}, "command": "python benchmarks/sim.py"}


def test_report_shows_solver_limits_and_the_same_limits_ratio():
    report = _load("report")
    text = report.section_sim("sim_x.json", _sim_result(True))
    assert "solver / line-search iterations" in text and "ratio to MuJoCo C, same limits" in text
    row = next(line for line in text.splitlines() if line.startswith("| `2:24:3:4`"))
    assert "| 3 / 4 |" in row and "10,000" in row and "0.200" in row and "0.400" in row
    plain = report.section_sim("sim_x.json", _sim_result(False))
    assert "same limits" not in plain  # variants at the model's limits keep the old table


def test_report_titles_a_solver_comparison():
    report = _load("report")
    rec = {"episodes": 4, "keep": 24, "ref_keep": 24, "solver_iterations": 3, "ls_iterations": 4,
           "success_all": 4, "success_keep": 3, "same_per_episode": False, "qpos_diff_median": 1e-3,
           "qpos_diff_max": 1e-2, "mirror_err_all_median": 1e-4, "mirror_err_all_max": 1e-3,
           "mirror_err_keep_median": 2e-4, "mirror_err_keep_max": 2e-3}
    text = report.section_contacts("solver_x.json", {"command": "python benchmarks/contacts.py", "tasks": {"t": rec}})
    assert text.startswith("## Lower solver iteration limits")
    assert "success, 24 kept, 3 solver it., 4 line-search it." in text and "| 4/4 | 3/4 | no |" in text


def test_mujoco_c_reference_is_a_best_of_repeats_from_one_start():
    import mujoco
    import numpy as np

    sim = _load("sim")
    model = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><freejoint/><geom size='.1'/></body></worldbody></mujoco>")
    q0 = np.array([0, 0, 1, 1, 0, 0, 0], float)
    sps = sim.bench_c(model, q0, np.zeros(0), 50, reps=3)
    assert np.isfinite(sps) and sps > 0


def test_report_states_the_timing_protocol_of_newer_files():
    report = _load("report")
    old = report.section_sim("sim_x.json", _sim_result(False))
    new = report.section_sim("sim_x.json", {**_sim_result(False), "timing": "best of 5"})
    assert "best of 3 later calls" in old and "MuJoCo C: the best of 5 runs" not in old
    assert "best of 5 later calls" in new and "MuJoCo C: the best of 5 runs" in new
