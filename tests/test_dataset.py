"""Dataset round trip, atomic overwrite and corruption rejection."""

import json
import os

import numpy as np
import pytest

from equibim_jax.data.dataset import DatasetError, Demos, load, save


def _demos(e=3, t=5, seed=0):
    rng = np.random.default_rng(seed)
    return Demos(
        obs={"qpos": rng.normal(size=(e, t, 14)).astype(np.float32),
             "point_cloud": rng.normal(size=(e, t, 8, 3)).astype(np.float32)},
        action=rng.normal(size=(e, t, 14)).astype(np.float32),
        length=np.array([5, 3, 4], np.int32)[:e],
        success=np.ones(e, bool),
        side=np.array([1.0, -1.0, 1.0], np.float32)[:e],
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
    np.testing.assert_array_equal(back.side, d.side)
    assert back.meta["n_steps"] == 12 and back.meta["seed"] == 0
    with pytest.raises(DatasetError, match="expected task='stamp_seal'"):
        load(p, expect={"task": "stamp_seal"})


def test_no_silent_overwrite_and_atomic_replace(tmp_path):
    p = tmp_path / "demos.zarr"
    save(_demos(seed=0), p)
    with pytest.raises(FileExistsError):
        save(_demos(seed=1), p)
    # A failing write (bad metadata) leaves the old dataset intact.
    with pytest.raises(DatasetError, match="JSON"):
        _demos_bad_meta()
    assert load(p).meta["seed"] == 0
    save(_demos(seed=1), p, overwrite=True)
    assert load(p).meta["seed"] == 1
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".")]  # no temp dirs left


def _demos_bad_meta():
    d = _demos()
    return Demos(obs=d.obs, action=d.action, length=d.length, success=d.success, side=d.side,
                 meta={"bad": object()})


def test_validation_errors():
    d = _demos()
    with pytest.raises(DatasetError, match="NaN"):
        Demos(obs=d.obs, action=np.full_like(d.action, np.nan), length=d.length, success=d.success,
              side=d.side, meta={})
    with pytest.raises(DatasetError, match="obs/qpos has shape"):
        Demos(obs={"qpos": d.obs["qpos"][:, :2]}, action=d.action, length=d.length,
              success=d.success, side=d.side, meta={})
    with pytest.raises(DatasetError, match="episode lengths"):
        Demos(obs=d.obs, action=d.action, length=np.array([6, 1, 1]), success=d.success,
              side=d.side, meta={})


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
