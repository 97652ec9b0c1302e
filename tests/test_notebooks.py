"""The notebooks in notebooks/ run top to bottom without errors (nbclient), in a kernel
that is this interpreter (a kernel spec written to a temporary JUPYTER_PATH, so a fresh
clone needs no `ipykernel install`)."""

import json
import sys
from pathlib import Path

import pytest

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
KERNEL = "equibim-test-python"


@pytest.fixture
def kernel_here(tmp_path, monkeypatch):
    """A kernel spec named ``KERNEL`` that runs ``sys.executable``, found through JUPYTER_PATH."""
    spec = tmp_path / "kernels" / KERNEL
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "equibim tests", "language": "python"}))
    monkeypatch.setenv("JUPYTER_PATH", str(tmp_path))
    monkeypatch.delenv("MPLBACKEND", raising=False)  # the kernel's inline backend: figures become outputs
    return KERNEL


def _run(name: str, kernel: str, timeout: int) -> "object":
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), \
        f"{name} is committed with outputs: clear them"
    client = nbclient.NotebookClient(nb, kernel_name=kernel, timeout=timeout,
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()  # raises CellExecutionError with the cell and traceback on any error
    return nb


def _text(nb) -> str:
    out = []
    for c in nb.cells:
        for o in c.get("outputs", []):
            out.append(o.get("text", "") + str(o.get("data", {}).get("text/plain", "")))
    return "\n".join(out)


@pytest.mark.slow  # a few minutes: generation, training and evaluation compile from scratch
def test_quickstart_notebook_runs(kernel_here):
    nb = _run("quickstart.ipynb", kernel_here, timeout=600)
    text = _text(nb)
    assert "forward-kinematics residual" in text and "trained 300 steps" in text
    assert "trained   success" in text and "mirrored  success" in text and "notebook wall time" in text
    kinds = {o.get("output_type") for c in nb.cells for o in c.get("outputs", [])}
    assert "display_data" in kinds  # the figures and the video were drawn


@pytest.mark.slow
def test_results_notebook_runs(kernel_here):
    nb = _run("results.ipynb", kernel_here, timeout=300)
    text = _text(nb)
    assert "docs/results" in text and "benchmarks/results" in text
    if (ROOT / "docs" / "results" / "experts_200.json").exists():
        assert "200/200" in text
    kinds = {o.get("output_type") for c in nb.cells for o in c.get("outputs", [])}
    assert "display_data" in kinds  # the plots were drawn
