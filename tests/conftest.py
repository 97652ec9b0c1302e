import os
import sys

# Tests run on the CPU; two host devices let sharding code be exercised.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One CPU device per test process (pytest-xdist already runs one process per core): the
# CLI's one-device-per-core default (equibim_jax._sharding.maybe_use_cpu_cores) stays off
# for in-process main() calls and for subprocesses; tests that want devices set XLA_FLAGS.
os.environ["EQUIBIM_JAX_CPU_DEVICES"] = "off"
sys.path.insert(0, os.path.dirname(__file__))

# XLA's LLVM optimisation level for this test process. The default suite's run time is mostly
# XLA compilation (a fresh machine has no compile cache), and level 0 compiles MJX and
# network programs markedly faster while running them slower, a net gain for the default
# suite's short programs. The slow suite, and any run that does not deselect it, keeps XLA's
# default level, so the shipped configuration is what `make test-slow` tests.
# EQUIBIM_TEST_XLA_O0=1 or 0 forces the choice either way.
_O0_FLAG = "--xla_backend_optimization_level=0"


def _want_o0(markexpr: str) -> bool:
    forced = os.environ.get("EQUIBIM_TEST_XLA_O0", "").strip().lower()
    if forced:
        return forced not in ("0", "false", "no", "off")
    return "not slow" in " ".join(markexpr.split())


def pytest_configure(config):
    # Runs before test modules are imported, so before any jax backend reads XLA_FLAGS.
    if _want_o0(config.getoption("markexpr") or ""):
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_backend_optimization_level" not in flags:
            os.environ["XLA_FLAGS"] = f"{flags} {_O0_FLAG}".strip()
