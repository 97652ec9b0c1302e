import os
import sys

# Tests run on the CPU; two host devices let sharding code be exercised.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One CPU device per test process (pytest-xdist already runs one process per core): the
# CLI's one-device-per-core default (equibim_jax._sharding.maybe_use_cpu_cores) stays off
# for in-process main() calls and for subprocesses; tests that want devices set XLA_FLAGS.
os.environ["EQUIBIM_JAX_CPU_DEVICES"] = "off"
sys.path.insert(0, os.path.dirname(__file__))
