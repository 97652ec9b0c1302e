"""tests/run_by_file.py: a file that crashes the interpreter or hangs fails alone."""

import json
import re
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def test_crash_and_hang_fail_their_files_and_the_rest_still_runs(tmp_path):
    d = tmp_path / "cases"
    d.mkdir()
    (d / "test_ok.py").write_text("def test_a():\n    assert 1 + 1 == 2\n")
    (d / "test_crash.py").write_text("import os, signal\n\ndef test_b():\n    os.kill(os.getpid(), signal.SIGSEGV)\n")
    (d / "test_hang.py").write_text("import time\n\ndef test_c():\n    time.sleep(120)\n")
    durations = tmp_path / "durations.json"
    res = subprocess.run([sys.executable, str(HERE / "run_by_file.py"), "-j", "2", "-m", "not slow",
                          "--timeout", "15", "--durations-file", str(durations), "--paths", str(d)],
                         capture_output=True, text=True, timeout=300)
    out = res.stdout
    assert res.returncode == 1, out + res.stderr
    assert "1 of 3 files passed" in out, out
    lines = {Path(line.split()[5]).name: line for line in out.splitlines() if re.match(r"\[\s*\d+/3\]", line)}
    assert lines["test_ok.py"].split()[2] == "ok", out
    assert lines["test_crash.py"].split()[2] == "FAIL" and lines["test_hang.py"].split()[2] == "FAIL", out
    assert "killed after 15 s" in out  # the hang was stopped by the file limit
    assert set(json.loads(durations.read_text())) == {str(d / f) for f in lines}


def test_a_fresh_clone_orders_files_by_the_committed_durations(tmp_path):
    """No durations of a previous run: the committed per-file seconds put the longest first;
    a previous run's durations, where there are any, take precedence."""
    d = tmp_path / "cases"
    d.mkdir()
    for name in ("test_a.py", "test_b.py", "test_c.py"):
        (d / name).write_text("def test_x():\n    pass\n")
    committed = tmp_path / "committed.json"
    committed.write_text(json.dumps({str(d / "test_b.py"): 100.0, str(d / "test_a.py"): 1.0}))

    def order(durations):
        res = subprocess.run([sys.executable, str(HERE / "run_by_file.py"), "-j", "1", "-m", "not slow",
                              "--durations-file", str(durations), "--committed-durations", str(committed),
                              "--paths", str(d)], capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stdout + res.stderr
        return [Path(line.split()[5]).name for line in res.stdout.splitlines() if re.match(r"\[\s*\d+/3\]", line)]

    # b (100 s) before a (1 s); c, unknown, keeps its collection place after them
    assert order(tmp_path / "none.json") == ["test_b.py", "test_a.py", "test_c.py"]
    previous = tmp_path / "previous.json"
    previous.write_text(json.dumps({str(d / "test_a.py"): 500.0}))
    assert order(previous) == ["test_a.py", "test_b.py", "test_c.py"]


def test_xla_level_0_only_for_the_default_suite_or_files_that_declare_it(tmp_path, monkeypatch):
    """conftest._want_o0: level 0 for `-m "not slow"`, or when every file named declares
    `XLA_O0 = True` at module level; the default level otherwise; the env variable wins."""
    import conftest

    o0 = tmp_path / "test_o0.py"
    o0.write_text('"""A compile-bound file."""\n\nXLA_O0 = True  # level 0 pays off here\n')
    plain = tmp_path / "test_plain.py"
    plain.write_text("# XLA_O0 = True is only a comment here\nX = 1\n")
    monkeypatch.delenv("EQUIBIM_TEST_XLA_O0", raising=False)
    assert conftest._want_o0("not slow", [])
    assert conftest._want_o0("slow", [str(o0)]) and conftest._want_o0("slow", [f"{o0}::test_a", "-q"])
    assert not conftest._want_o0("slow", [str(plain)])
    assert not conftest._want_o0("slow", [str(o0), str(plain)])  # one process, one level: the default
    assert not conftest._want_o0("slow", [str(tmp_path)]) and not conftest._want_o0("slow", [])
    monkeypatch.setenv("EQUIBIM_TEST_XLA_O0", "0")
    assert not conftest._want_o0("not slow", [str(o0)])
    monkeypatch.setenv("EQUIBIM_TEST_XLA_O0", "1")
    assert conftest._want_o0("slow", [str(plain)])
