"""Dataset round trip, atomic overwrite (and its failure paths) and corruption rejection."""

import ctypes
import dataclasses
import errno
import json
import os
import sys

import numpy as np
import pytest
import zarr

from equibim_jax.data import dataset as ds
from equibim_jax.data.dataset import DatasetError, Demos, load, save

LINUX = sys.platform.startswith("linux")


def _demos(e=3, t=5, seed=0):
    rng = np.random.default_rng(seed)
    return Demos(
        obs={"qpos": rng.normal(size=(e, t, 14)).astype(np.float32),
             "point_cloud": rng.normal(size=(e, t, 8, 3)).astype(np.float32)},
        action=rng.normal(size=(e, t, 14)).astype(np.float32),
        length=np.array([5, 3, 4], np.int32)[:e],
        success=np.ones(e, bool),
        meta={"task": "place_empty_cup", "seed": seed},
    )


def test_round_trip(tmp_path):
    d = _demos()
    p = save(d, tmp_path / "demos.zarr")
    back = load(p, expect={"task": "place_empty_cup"})
    for k in d.obs:
        np.testing.assert_array_equal(back.obs[k], d.obs[k])
    np.testing.assert_array_equal(back.action, d.action)
    np.testing.assert_array_equal(back.length, d.length)
    np.testing.assert_array_equal(back.success, d.success)
    assert sorted(os.listdir(p)) == ["action", "length", "obs", "success", "zarr.json"]
    assert back.meta["n_steps"] == 12 and back.meta["seed"] == 0
    with pytest.raises(DatasetError, match="expected task='stamp_seal'"):
        load(p, expect={"task": "stamp_seal"})


def _assert_is(demos, d):
    for k in d.obs:
        np.testing.assert_array_equal(demos.obs[k], d.obs[k])
    np.testing.assert_array_equal(demos.action, d.action)
    assert demos.meta["seed"] == d.meta["seed"]


def _leftovers(directory):
    """Temporary or backup entries beside the dataset."""
    return [f for f in os.listdir(directory) if f.startswith(".")]


def test_no_silent_overwrite(tmp_path):
    p = tmp_path / "demos.zarr"
    save(_demos(seed=0), p)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save(_demos(seed=1), p)
    _assert_is(load(p), _demos(seed=0))


def test_overwrite_exchanges_atomically(tmp_path, monkeypatch):
    p = tmp_path / "demos.zarr"
    save(_demos(seed=0), p)
    real_exchange, swaps = ds._exchange, []

    def exchange(a, b):
        assert b == p and load(p).meta["seed"] == 0  # the old dataset is in place up to the swap
        assert load(a).meta["seed"] == 1  # and the new one is complete before it
        swapped = real_exchange(a, b)
        swaps.append(swapped)
        if swapped:  # one step: the new dataset in place, the old one at the temporary name
            assert load(p).meta["seed"] == 1 and load(a).meta["seed"] == 0
        return swapped

    real_replace, renames = os.replace, []

    def replace(a, b, **kw):
        renames.append((os.fspath(a), os.fspath(b)))
        return real_replace(a, b, **kw)

    monkeypatch.setattr(ds, "_exchange", exchange)
    monkeypatch.setattr(os, "replace", replace)
    save(_demos(seed=1), p, overwrite=True)
    monkeypatch.undo()
    _assert_is(load(p), _demos(seed=1))
    assert not _leftovers(tmp_path)
    assert len(swaps) == 1
    if LINUX:
        assert swaps == [True], "renameat2(RENAME_EXCHANGE) was not used on Linux"
        assert not [r for r in renames if str(p) in r], f"the dataset was renamed: {renames}"


@pytest.mark.parametrize("how", ["no_function", "ENOSYS", "EINVAL"])
def test_overwrite_falls_back_without_exchange(tmp_path, monkeypatch, how):
    def renameat2(*_):  # what libc returns where the kernel or filesystem lacks the flag
        ctypes.set_errno(getattr(errno, how))
        return -1

    monkeypatch.setattr(ds, "_renameat2", lambda: None if how == "no_function" else renameat2)
    p = tmp_path / "demos.zarr"
    save(_demos(seed=0), p)
    save(_demos(seed=1), p, overwrite=True)
    _assert_is(load(p), _demos(seed=1))
    assert not _leftovers(tmp_path)


@pytest.mark.skipif(not LINUX, reason="renameat2 is Linux-only")
def test_exchange_errors_are_raised(tmp_path):
    (tmp_path / "a").mkdir()
    with pytest.raises(OSError, match="renameat2.*No such file") as err:
        ds._exchange(tmp_path / "a", tmp_path / "missing")
    assert err.value.errno == errno.ENOENT


def test_failed_write_keeps_old_dataset(tmp_path, monkeypatch):
    p = tmp_path / "demos.zarr"
    save(_demos(seed=0), p)
    real, calls = zarr.Group.create_array, []

    def create_array(self, *args, **kwargs):  # the first array is written, the second fails
        calls.append(args[0] if args else kwargs.get("name"))
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device (simulated)")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(zarr.Group, "create_array", create_array)
    with pytest.raises(OSError, match="simulated"):
        save(_demos(seed=1), p, overwrite=True)
    monkeypatch.undo()
    assert len(calls) == 2
    _assert_is(load(p), _demos(seed=0))
    assert not _leftovers(tmp_path)


@pytest.mark.parametrize("where", ["exchange", "fallback_second_rename"])
def test_failed_swap_keeps_old_dataset(tmp_path, monkeypatch, where):
    p = tmp_path / "demos.zarr"
    save(_demos(seed=0), p)

    def fail(*_, **__):
        raise OSError(errno.EIO, "I/O error (simulated)")

    if where == "exchange":
        monkeypatch.setattr(ds, "_exchange", fail)
    else:  # no exchange: the old dataset is moved away, then moving the new one in fails
        monkeypatch.setattr(ds, "_exchange", lambda a, b: False)
        real_replace = os.replace
        monkeypatch.setattr(os, "replace", lambda a, b, **kw: fail() if os.fspath(a).endswith(".tmp")
                            and os.fspath(b) == os.fspath(p) else real_replace(a, b, **kw))
    with pytest.raises(OSError, match="simulated"):
        save(_demos(seed=1), p, overwrite=True)
    monkeypatch.undo()
    _assert_is(load(p), _demos(seed=0))
    assert not _leftovers(tmp_path)


def test_validation_errors():
    d = _demos()
    with pytest.raises(DatasetError, match="NaN"):
        Demos(obs=d.obs, action=np.full_like(d.action, np.nan), length=d.length, success=d.success,
              meta={})
    with pytest.raises(DatasetError, match="obs/qpos has shape"):
        Demos(obs={"qpos": d.obs["qpos"][:, :2]}, action=d.action, length=d.length,
              success=d.success, meta={})
    with pytest.raises(DatasetError, match="episode lengths"):
        Demos(obs=d.obs, action=d.action, length=np.array([6, 1, 1]), success=d.success,
              meta={})
    with pytest.raises(DatasetError, match="JSON"):
        Demos(obs=d.obs, action=d.action, length=d.length, success=d.success, meta={"bad": object()})
    with pytest.raises(DatasetError, match="success has shape"):
        Demos(obs=d.obs, action=d.action, length=d.length, success=d.success[:2], meta={})


def test_corruption_is_rejected(tmp_path):
    p = save(_demos(), tmp_path / "demos.zarr")
    with pytest.raises(DatasetError, match="no dataset"):
        load(tmp_path / "missing.zarr")
    # Tamper with the metadata counts.
    meta_file = p / "zarr.json"
    meta = json.loads(meta_file.read_text())
    meta["attributes"]["equibim"]["n_steps"] = 99
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="metadata says"):
        load(p)
    meta["attributes"]["equibim"]["format"] = "something-else"
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="is not an equibim-demos dataset"):
        load(p)
    # Delete an array chunk's metadata: the array can no longer be read.
    p2 = save(_demos(), tmp_path / "demos2.zarr")
    (p2 / "action" / "zarr.json").unlink()
    with pytest.raises(DatasetError, match="corrupt"):
        load(p2)


def test_old_and_unknown_versions_are_rejected(tmp_path):
    p = save(_demos(), tmp_path / "demos.zarr")
    meta_file = p / "zarr.json"
    meta = json.loads(meta_file.read_text())
    assert meta["attributes"]["equibim"]["version"] == 2
    meta["attributes"]["equibim"]["version"] = 1
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"version 1, .* version 2 .*regenerate it with `equibim generate`"):
        load(p)
    meta["attributes"]["equibim"]["version"] = 3
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="format version 3; this code reads version 2"):
        load(p)


def test_action_spaces(tmp_path):
    d = _demos()
    assert d.action_spaces == ("joint",) and d.in_action_space("joint") is d
    with pytest.raises(DatasetError, match=r"holds \['joint'\] actions, not 'ee'"):
        d.in_action_space("ee")
    with pytest.raises(DatasetError, match="must be 'joint' or 'ee'"):
        d.in_action_space("torque")
    ee = np.random.default_rng(1).normal(size=(3, 5, 20)).astype(np.float32)
    d2 = dataclasses.replace(d, action_ee=ee, meta={**d.meta, "task_options": {"action": "joint"}})
    back = load(save(d2, tmp_path / "d.zarr"))
    assert back.action_spaces == ("joint", "ee") and back.meta["action_spaces"] == ["joint", "ee"]
    np.testing.assert_array_equal(back.in_action_space("ee").action, ee)
    assert back.in_action_space("ee").meta["task_options"]["action"] == "ee"
    # a stale layout entry in the metadata does not override the layout written
    d3 = dataclasses.replace(d, meta={**d.meta, "n_episodes": 99, "action_spaces": ["joint", "ee"]})
    assert load(save(d3, tmp_path / "d3.zarr")).action_spaces == ("joint",)
    with pytest.raises(DatasetError, match="action_ee has shape"):
        dataclasses.replace(d, action_ee=ee[:, :2])
    with pytest.raises(DatasetError, match="action_ee contains NaN"):
        dataclasses.replace(d, action_ee=np.full_like(ee, np.nan))
