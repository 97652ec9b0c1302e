"""One CPU device per core for the CLI (equibim_jax._sharding.maybe_use_cpu_cores)."""

import os
import subprocess
import sys

import pytest

from equibim_jax._sharding import cpu_devices_requested, maybe_use_cpu_cores

_PROBE = """
import jax  # imported first, as the CLI does: the flag must still take effect
from equibim_jax._sharding import data_mesh, maybe_use_cpu_cores, mesh_shape, train_mesh
n = maybe_use_cpu_cores()
print(n, jax.device_count(), maybe_use_cpu_cores(), mesh_shape(data_mesh())["data"], mesh_shape(train_mesh())["data"])
"""


def _run(**env):
    e = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "EQUIBIM_JAX_CPU_DEVICES")}
    e.update(env)
    r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, env=e, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.split()


def test_requested_count_parsing():
    assert cpu_devices_requested({"EQUIBIM_JAX_CPU_DEVICES": "3"}) == 3
    assert cpu_devices_requested({"EQUIBIM_JAX_CPU_DEVICES": "off"}) == 1
    assert cpu_devices_requested({"EQUIBIM_JAX_CPU_DEVICES": "0"}) == 1
    assert 1 <= cpu_devices_requested({}) <= 8
    with pytest.raises(ValueError, match="EQUIBIM_JAX_CPU_DEVICES"):
        cpu_devices_requested({"EQUIBIM_JAX_CPU_DEVICES": "many"})


def test_flag_is_added_before_the_backend_starts_and_respected_after():
    # three devices asked for, whatever this machine has; the second call is a no-op; the
    # data mesh spans them, training keeps one device (train_mesh)
    assert _run(EQUIBIM_JAX_CPU_DEVICES="3") == ["3", "3", "0", "3", "1"]
    assert _run(EQUIBIM_JAX_CPU_DEVICES="off") == ["0", "1", "0", "1", "1"]
    # a count the user already set in XLA_FLAGS wins, and then training uses every device
    assert _run(EQUIBIM_JAX_CPU_DEVICES="3", XLA_FLAGS="--xla_force_host_platform_device_count=2") == \
        ["0", "2", "0", "2", "2"]


def test_no_change_once_a_backend_has_started():
    import jax

    jax.devices()  # this process's backend is up
    env = {"EQUIBIM_JAX_CPU_DEVICES": "4"}
    assert maybe_use_cpu_cores(env) == 0 and "XLA_FLAGS" not in env
