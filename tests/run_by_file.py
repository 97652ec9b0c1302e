"""Run a pytest selection one test file per process, a few processes at a time.

``make test-slow`` uses it for the slow suite. Each file gets a fresh interpreter, so a
file that crashes the interpreter (a segfault in native code) or hangs fails that file
alone, with its output, instead of stalling a shared pytest-xdist worker pool; and memory
held by one file's compiled programs is returned when it ends.

Usage::

    python tests/run_by_file.py [-j 2] [--timeout SECONDS] [-m slow] [--paths P ...] [PYTEST_ARGS ...]

Exit status 0 when every file passed (or was skipped entirely), 1 otherwise. Files run
longest-first by the durations of the previous run (kept in ``.pytest_cache``); a file
that has none there (every file, in a fresh clone) takes its figure from the committed
``tests/slow_durations.json`` (per-file seconds of a cold slow-suite run, two files at a
time), so the longest files start first on a new machine too; files in neither keep their
collection order after the others.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DURATIONS = ROOT / ".pytest_cache" / "run_by_file_durations.json"
COMMITTED_DURATIONS = ROOT / "tests" / "slow_durations.json"


def _read_durations(path: Path) -> dict[str, float]:
    """``{file: seconds}`` from a JSON file, or ``{}`` when it is missing or unreadable."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): float(v) for k, v in d.items()} if isinstance(d, dict) else {}


def collect(marker: str, extra: list[str], paths: list[str]) -> list[str]:
    """The test files holding at least one test selected by ``-m marker``, in collection order
    (as paths relative to the repository, or absolute when outside it)."""
    cmd = [sys.executable, "-m", "pytest", "-m", marker, "--collect-only", "-q", *extra, *paths]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if res.returncode not in (0, 5):  # 5: nothing collected
        sys.stdout.write(res.stdout + res.stderr)
        raise SystemExit(f"collection failed (exit {res.returncode})")
    files: list[str] = []
    for line in res.stdout.splitlines():
        if "::" in line:
            f = line.split("::", 1)[0]
            if not (ROOT / f).exists():  # ids are relative to pytest's rootdir, a folder above the paths
                bases = [b for d in paths for b in (Path(d), *Path(d).parents)]
                f = next((str(b / f) for b in bases if (b / f).is_file()), f)
            if f not in files:
                files.append(f)
    return files


def run_file(path: str, marker: str, extra: list[str], timeout: float) -> tuple[str, int, float, str]:
    """``(path, exit code, seconds, output)``; exit code -9 when it ran past ``timeout``."""
    cmd = [sys.executable, "-m", "pytest", "-m", marker, "-q", "-p", "no:cacheprovider",
           "--durations=5", path, *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        out += f"\n[run_by_file] {path}: killed after {timeout:.0f} s\n"
        code = -9
    return path, code, time.perf_counter() - t0, out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("-j", "--jobs", type=int, default=2, help="files run at once (default 2)")
    p.add_argument("-m", "--marker", default="slow", help='pytest -m expression (default "slow")')
    p.add_argument("--timeout", type=float, default=2400.0,
                   help="seconds before a file's process is killed and the file counted failed")
    p.add_argument("--paths", nargs="+", default=[], help="where to collect (default: the testpaths)")
    p.add_argument("--durations-file", type=Path, default=DURATIONS,
                   help="where the per-file durations that order the next run are kept")
    p.add_argument("--committed-durations", type=Path, default=COMMITTED_DURATIONS,
                   help="per-file seconds used for files without a previous duration (a fresh clone)")
    a, extra = p.parse_known_args(argv)
    if a.jobs < 1:
        p.error(f"--jobs must be >= 1, got {a.jobs}")
    files = collect(a.marker, extra, [str(Path(x).resolve()) for x in a.paths])
    if not files:
        print(f"no tests selected by -m {a.marker!r}")
        return 0
    previous = _read_durations(a.durations_file)
    order = {**_read_durations(a.committed_durations), **previous}
    files.sort(key=lambda f: -order.get(f, 0.0))  # stable: collection order for unknown files
    print(f"{len(files)} files, {a.jobs} at a time, -m {a.marker!r}", flush=True)
    t0 = time.perf_counter()
    lock = threading.Lock()
    results = []

    def one(f):
        r = run_file(f, a.marker, extra, a.timeout)
        path, code, secs, out = r
        ok = code in (0, 5)
        with lock:
            results.append(r)
            tail = out.strip().splitlines()[-1] if out.strip() else ""
            print(f"[{len(results):>3}/{len(files)}] {'ok  ' if ok else 'FAIL'} {secs:7.1f} s  {path}  {tail}",
                  flush=True)
            if not ok:
                print(out, flush=True)
        return r

    with ThreadPoolExecutor(a.jobs) as pool:
        list(pool.map(one, files))
    failed = [r[0] for r in results if r[1] not in (0, 5)]
    try:
        a.durations_file.parent.mkdir(parents=True, exist_ok=True)
        a.durations_file.write_text(json.dumps({**previous, **{r[0]: round(r[2], 1) for r in results}}, indent=1))
    except OSError:
        pass
    print(f"{len(files) - len(failed)} of {len(files)} files passed in {time.perf_counter() - t0:.0f} s"
          + (f"; failed: {' '.join(failed)}" if failed else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
