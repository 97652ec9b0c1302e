import os
import re
import sys
from pathlib import Path

# Tests run on the CPU; two host devices let sharding code be exercised.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One CPU device per test process (pytest-xdist already runs one process per core): the
# CLI's one-device-per-core default (equibim_jax._sharding.maybe_use_cpu_cores) stays off
# for in-process main() calls and for subprocesses; tests that want devices set XLA_FLAGS.
os.environ["EQUIBIM_JAX_CPU_DEVICES"] = "off"
sys.path.insert(0, os.path.dirname(__file__))

# XLA's LLVM optimisation level for this test process. A fresh machine has no compile cache,
# and most of the suite's time is XLA compilation; level 0 compiles MJX and network programs
# markedly faster and runs them slower. It is the net gain for
# - the default suite (the README's test command, which deselects `slow`): short programs;
# - a slow test file whose programs are compile-bound (networks, a few short episodes): it
#   declares so with a module-level line `XLA_O0 = True`, which is read from the file's text
#   before anything is imported, when the run names only such files (`make test-slow` runs
#   one file per process).
# Every other run keeps XLA's default level, so the slow suite's physics-heavy files (the
# tasks' scripted experts over many episodes, whose run time level 0 would triple) still
# test the configuration users run. EQUIBIM_TEST_XLA_O0=1 or 0 forces the choice either way.
_O0_FLAG = "--xla_backend_optimization_level=0"
_O0_LINE = re.compile(r"^XLA_O0\s*=\s*True\b", re.M)


def _file_wants_o0(arg: str) -> bool:
    """Whether a command-line path (or node id) names a test file that declares `XLA_O0 = True`."""
    path = Path(arg.split("::", 1)[0])
    if path.suffix != ".py" or not path.is_file():
        return False
    try:
        return bool(_O0_LINE.search(path.read_text()))
    except OSError:
        return False


def _want_o0(markexpr: str, args=()) -> bool:
    forced = os.environ.get("EQUIBIM_TEST_XLA_O0", "").strip().lower()
    if forced:
        return forced not in ("0", "false", "no", "off")
    if "not slow" in " ".join(markexpr.split()):
        return True
    args = [a for a in args if not a.startswith("-")]
    return bool(args) and all(_file_wants_o0(a) for a in args)


def pytest_configure(config):
    # Runs before test modules are imported, so before any jax backend reads XLA_FLAGS.
    if _want_o0(config.getoption("markexpr") or "", config.args):
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_backend_optimization_level" not in flags:
            os.environ["XLA_FLAGS"] = f"{flags} {_O0_FLAG}".strip()
