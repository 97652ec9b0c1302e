"""Smoke test of ``benchmarks/train.py``'s policy mode: a tiny dp3 with the mirrored branch,
one repeat, into a temporary file; the JSON has the keys ``benchmarks/report.py`` reads.
The PyTorch twin runs too when torch is importable."""

from __future__ import annotations

import importlib.util
import json
import os
import pathlib

import pytest
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_policy_mode_writes_the_keys(tmp_path):
    out = tmp_path / "bench.json"
    has_torch = importlib.util.find_spec("torch") is not None
    cmd = [sys.executable, str(ROOT / "benchmarks" / "train.py"), "--policies", "dp3", "--tiny",
           "--batch", "4", "--k", "1", "--repeats", "1", "--infer-repeats", "1",
           "--policy-variants", "sym", "--no-step-compile", "--matmul-n", "256", "--out", str(out)]
    if has_torch:
        cmd.append("--vs-torch")
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    subprocess.run(cmd, check=True, cwd=ROOT, env=env, capture_output=True, timeout=300)
    d = json.loads(out.read_text())
    for k in ("matmul_2048_fp32", "policies", "targets", "host", "versions", "command"):
        assert k in d, k
    r = d["policies"]["dp3"]
    for k in ("params", "step_ms_sym", "compile_s_loop_sym", "gflop_per_step_sym", "gflops_sym",
              "fraction_of_matmul_sym", "infer_ms_per_chunk", "peak_mem_mb", "targets_met"):
        assert k in r, k
    assert r["params"] > 0 and r["step_ms_sym"] > 0 and r["gflop_per_step_sym"] > 0
    if has_torch:
        assert r["params_torch"] == r["params"]
        assert r["torch_step_ms_sym"] > 0 and "ratio_vs_torch_sym" in r
