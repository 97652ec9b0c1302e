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
