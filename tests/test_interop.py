"""Real data in and out: DP3 zarr and LeRobot v3 round trips, import validation, and S from a
mirror map for an imported dataset (equibim_jax.interop). Synthetic data only."""

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("pyarrow")
pytest.importorskip("av")

from equibim_jax.data.dataset import Demos, load, save  # noqa: E402
from equibim_jax.interop import InteropError, export_dataset, import_dataset, map_env, read_dataset  # noqa: E402
from equibim_jax.interop.mapping import describe  # noqa: E402

VIDEO_MAE = 4.0
"""Largest accepted mean absolute error of a video round trip, in uint8 units (H.264, CRF 18,
4:2:0 chroma on smooth 32 x 32 test images)."""
JOINTS = 14  # robot_a: 2 x (6 arm joints + 1 gripper opening)


def _images(rng, n, h=32, w=32):
    """Smooth uint8 images [n, h, w, 3] (what a camera sees; noise would not survive any codec)."""
    y, x = np.mgrid[0:h, 0:w] / h
    ph = rng.uniform(0, 6, (n, 3))
    img = 128 + 90 * np.sin(1.5 * x[None, :, :, None] + y[None, :, :, None] * np.arange(1, 4) + ph[:, None, None, :])
    return np.clip(img, 0, 255).astype(np.uint8)


def _demos(seed=0, e=3, t=12, images=True):
    """A tiny dataset of ours as `equibim generate` would write for place_empty_cup (robot_a)."""
    rng = np.random.default_rng(seed)
    obs = {"qpos": rng.normal(size=(e, t, JOINTS)).astype(np.float32),
           "point_cloud": rng.normal(size=(e, t, 16, 3)).astype(np.float32)}
    if images:
        obs["image"] = _images(rng, e * t).reshape(e, t, 32, 32, 3)
        obs["wrist_image"] = _images(rng, e * t * 2).reshape(e, t, 2, 32, 32, 3)
    return Demos(obs=obs, action=rng.normal(size=(e, t, JOINTS)).astype(np.float32),
                 length=np.array([t, t - 3, t - 5][:e], np.int32), success=np.array([True, False, True][:e]),
                 meta={"task": "place_empty_cup", "task_options": {"obs": list(obs)}, "action_space": "joint"},
                 action_ee=rng.normal(size=(e, t, 20)).astype(np.float32))


def _valid(a, length):
    return np.concatenate([a[i, :n] for i, n in enumerate(length)])


def _assert_same(a: Demos, b: Demos, image_mae=0.0):
    np.testing.assert_array_equal(a.length, b.length)
    np.testing.assert_array_equal(a.success, b.success)
    assert set(a.obs) == set(b.obs)
    np.testing.assert_array_equal(_valid(a.action, a.length), _valid(b.action, b.length))
    np.testing.assert_array_equal(_valid(a.action_ee, a.length), _valid(b.action_ee, b.length))
    for k in a.obs:
        x, y = _valid(a.obs[k], a.length), _valid(b.obs[k], b.length)
        assert x.shape == y.shape and x.dtype == y.dtype, k
        if k in ("image", "wrist_image") and image_mae:
            err = np.abs(x.astype(np.int16) - y.astype(np.int16)).mean()
            assert err <= image_mae, (k, err)
        else:
            np.testing.assert_array_equal(x, y, err_msg=k)


def test_dp3_round_trip(tmp_path):
    import zarr

    d = _demos()
    save(d, tmp_path / "ours.zarr")
    export_dataset("dp3", tmp_path / "ours.zarr", tmp_path / "dp3.zarr")
    assert (tmp_path / "dp3.zarr/.zgroup").exists()  # zarr format 2, as the ReplayBuffer reads it
    g = zarr.open_group(str(tmp_path / "dp3.zarr"), mode="r")
    assert g["meta/episode_ends"].dtype == np.int64
    np.testing.assert_array_equal(g["meta/episode_ends"][:], np.cumsum(d.length))
    assert sorted(g["data"].array_keys()) == ["action", "action_ee", "img", "img_wrist_left", "img_wrist_right",
                                              "point_cloud", "state"]
    np.testing.assert_array_equal(g["data/state"][:], _valid(d.obs["qpos"], d.length))
    assert g["data/img"].shape == (int(d.length.sum()), 32, 32, 3)
    rec = g.attrs["equibim"]["mapping"]
    assert rec["features"]["state"] == "qpos" and rec["features"]["img_wrist_right"] == "wrist_image[1]"
    assert rec["names"]["qpos"][6] == "gripper_left"
    back = import_dataset("dp3", tmp_path / "dp3.zarr", tmp_path / "back.zarr")
    _assert_same(d, back)
    _assert_same(d, load(tmp_path / "back.zarr"))
    assert back.meta["task"] == "place_empty_cup"
    assert back.meta["interop"]["cameras"] == {"image": ["head"], "wrist_image": ["wrist_left", "wrist_right"]}
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary directory left behind
    with pytest.raises(FileExistsError):
        export_dataset("dp3", tmp_path / "ours.zarr", tmp_path / "dp3.zarr")


def test_lerobot_round_trip(tmp_path):
    import pyarrow.parquet as pq

    d = _demos()
    export_dataset("lerobot", d, tmp_path / "lr")
    info = json.loads((tmp_path / "lr/meta/info.json").read_text())
    n = int(d.length.sum())
    assert info["codebase_version"] == "v3.0" and info["total_frames"] == n and info["total_episodes"] == 3
    assert info["fps"] > 0 and "{chunk_index:03d}" in info["data_path"] and "{video_key}" in info["video_path"]
    f = info["features"]
    assert f["observation.state"] == {"dtype": "float32", "shape": [JOINTS], "names": describe(d)["names"]["qpos"]}
    assert f["observation.images.head"]["dtype"] == "video" and f["observation.images.head"]["shape"] == [32, 32, 3]
    assert f["observation.point_cloud"]["shape"] == [16, 3]
    for k in ("action", "episode_index", "frame_index", "timestamp", "index", "task_index"):
        assert k in f
    for cam in ("head", "wrist_left", "wrist_right"):
        assert (tmp_path / f"lr/videos/observation.images.{cam}/chunk-000/file-000.mp4").stat().st_size > 0
    data = pq.read_table(tmp_path / "lr/data/chunk-000/file-000.parquet")
    assert data.num_rows == n
    np.testing.assert_array_equal(data.column("frame_index").to_numpy()[:5], np.arange(5))
    np.testing.assert_allclose(data.column("timestamp").to_numpy()[1], 1 / info["fps"], rtol=1e-6)
    eps = pq.read_table(tmp_path / "lr/meta/episodes/chunk-000/file-000.parquet").to_pydict()
    assert eps["length"] == d.length.tolist() and eps["dataset_to_index"] == np.cumsum(d.length).tolist()
    assert eps["videos/observation.images.head/from_timestamp"][1] == pytest.approx(d.length[0] / info["fps"])
    tasks = pq.read_table(tmp_path / "lr/meta/tasks.parquet").to_pydict()
    assert tasks == {"task_index": [0], "task": ["place_empty_cup"]}
    back = import_dataset("lerobot", tmp_path / "lr", tmp_path / "back.zarr")
    _assert_same(d, back, image_mae=VIDEO_MAE)
    assert back.meta["interop"]["fps"] == info["fps"]


def _foreign_dp3(path, n_eps=2, t=5, state_dtype=np.float32, ends=None, pc_dim=6):
    """A ReplayBuffer zarr as DP3's own scripts write it (no equibim attributes)."""
    import zarr

    rng = np.random.default_rng(1)
    f = n_eps * t
    g = zarr.open_group(str(path), mode="w", zarr_format=2)
    g.create_array("data/state", shape=(f, JOINTS), dtype=state_dtype)[:] = rng.normal(size=(f, JOINTS))
    g.create_array("data/action", shape=(f, JOINTS), dtype=np.float32)[:] = rng.normal(size=(f, JOINTS))
    g.create_array("data/point_cloud", shape=(f, 8, pc_dim), dtype=np.float32)[:] = rng.normal(size=(f, 8, pc_dim))
    g.create_array("data/img", shape=(f, 16, 16, 3), dtype=np.uint8)[:] = rng.integers(0, 255, (f, 16, 16, 3))
    e = np.arange(1, n_eps + 1, dtype=np.int64) * t if ends is None else np.asarray(ends, np.int64)
    g.create_array("meta/episode_ends", shape=e.shape, dtype=np.int64)[:] = e
    return path


def test_dp3_foreign_defaults_and_mapping(tmp_path):
    src = _foreign_dp3(tmp_path / "dp3.zarr")
    d = read_dataset("dp3", src)
    assert sorted(d.obs) == ["image", "point_cloud", "qpos"] and d.obs["point_cloud"].shape == (2, 5, 8, 6)
    np.testing.assert_array_equal(d.length, [5, 5])
    assert d.success.all()  # DP3 keeps successful demonstrations only
    names = [f"j{i}" for i in range(JOINTS)]
    (tmp_path / "m.json").write_text(json.dumps({"features": {"state": "qpos", "action": "action"},
                                                 "names": {"qpos": names}}))
    d2 = read_dataset("dp3", src, tmp_path / "m.json")
    assert sorted(d2.obs) == ["qpos"] and d2.meta["interop"]["names"]["qpos"] == names


def test_import_errors_name_the_problem(tmp_path):
    import zarr

    src = _foreign_dp3(tmp_path / "a.zarr", ends=[5, 3])
    with pytest.raises(InteropError, match="ragged episode ends"):
        read_dataset("dp3", src)
    src = _foreign_dp3(tmp_path / "b.zarr", ends=[5, 9])
    with pytest.raises(InteropError, match="frame count mismatch"):
        read_dataset("dp3", src)
    src = _foreign_dp3(tmp_path / "c.zarr", state_dtype=np.int32)
    with pytest.raises(InteropError, match="wrong dtype"):
        read_dataset("dp3", src)
    src = _foreign_dp3(tmp_path / "d.zarr")
    with pytest.raises(InteropError, match="missing key data/joint_state"):
        read_dataset("dp3", src, {"features": {"joint_state": "qpos", "action": "action"}})
    with pytest.raises(InteropError, match="size mismatch"):
        read_dataset("dp3", src, {"names": {"qpos": ["a", "b"]}})
    with pytest.raises(InteropError, match="no source feature maps to 'action'"):
        read_dataset("dp3", src, {"features": {"state": "qpos"}})
    del zarr.open_group(str(src), mode="a")["meta/episode_ends"]
    with pytest.raises(InteropError, match="missing key meta/episode_ends"):
        read_dataset("dp3", src)


def test_lerobot_import_errors(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    d = _demos(images=False)
    export_dataset("lerobot", d, tmp_path / "lr", fps=10)
    info_p = tmp_path / "lr/meta/info.json"
    info = json.loads(info_p.read_text())
    ep_p = tmp_path / "lr/meta/episodes/chunk-000/file-000.parquet"
    eps = pq.read_table(ep_p)
    # an episode length that disagrees with the data rows
    bad = eps.set_column(eps.column_names.index("length"), "length", pa.array([12, 10, 7], pa.int64()))
    shutil.copytree(tmp_path / "lr", tmp_path / "lr2")
    pq.write_table(bad, tmp_path / "lr2/meta/episodes/chunk-000/file-000.parquet")
    with pytest.raises(InteropError, match="frame count mismatch: episode 1"):
        read_dataset("lerobot", tmp_path / "lr2")
    info_p.write_text(json.dumps({**info, "codebase_version": "v2.1"}))
    with pytest.raises(InteropError, match="v3"):
        read_dataset("lerobot", tmp_path / "lr")
    info_p.write_text(json.dumps({**info, "total_frames": 999}))
    with pytest.raises(InteropError, match="total_frames"):
        read_dataset("lerobot", tmp_path / "lr")
    info_p.write_text(json.dumps(info))
    with pytest.raises(InteropError, match="missing key 'observation.velocity'"):
        read_dataset("lerobot", tmp_path / "lr", {"features": {"observation.velocity": "qvel", "action": "action"}})
    (tmp_path / "lr/meta/info.json").unlink()
    with pytest.raises(InteropError, match="missing meta/info.json"):
        read_dataset("lerobot", tmp_path / "lr")


def test_lerobot_missing_video_frames(tmp_path):
    d = _demos(e=2)
    export_dataset("lerobot", d, tmp_path / "lr")
    # a video cut short: re-encode the head camera with fewer frames than the episodes need
    from equibim_jax.interop.lerobot import DEFAULT_VIDEO, _encode_video

    p = tmp_path / "lr/videos/observation.images.head/chunk-000/file-000.mp4"
    _encode_video(p, _valid(d.obs["image"], d.length)[:10], 50.0, DEFAULT_VIDEO)
    with pytest.raises(InteropError, match="frame count mismatch: episode 0 needs frames 0..11 .* has 10 frames"):
        read_dataset("lerobot", tmp_path / "lr")


@pytest.fixture(scope="module")
def mirror_map(tmp_path_factory):
    """The mirror map JSON of robot_a, as `equibim symmetry --out` writes it."""
    from equibim_jax.sim import load_robot, robot_info
    from equibim_jax.symmetry import derive_symmetry, save_mirror_map

    model, mirror = load_robot("robot_a")
    path = tmp_path_factory.mktemp("map") / "map.json"
    save_mirror_map(derive_symmetry(model, mirror, n_verify=16), path, ee_sites=tuple(robot_info("robot_a").ee_sites))
    return path


def test_symmetry_from_map_matches_the_env(tmp_path, mirror_map):
    """S built from the map for an imported dataset equals the simulated env's S, field by field."""
    from equibim_jax.sim.env import Env, EnvConfig

    d = _demos()
    export_dataset("lerobot", d, tmp_path / "lr")
    imported = read_dataset("lerobot", tmp_path / "lr")
    ops = map_env(imported, mirror_map).symmetry_ops(("qpos", "point_cloud", "image", "wrist_image"))
    env = Env(EnvConfig(robot="robot_a"))
    ref = {"qpos": env.joint_action_symmetry, "action": env.joint_action_symmetry}
    from equibim_jax.symmetry import camera_pair_op, image_op, point_cloud_op

    ref.update(image=image_op("HWC"), wrist_image=camera_pair_op("HWC"), point_cloud=point_cloud_op(env.mirror))
    rng = np.random.default_rng(0)
    for k, op in ops.items():
        x = imported.obs[k][0, :3] if k != "action" else imported.action[0, :3]
        x = x + (rng.normal(size=x.shape).astype(np.float32) if x.dtype.kind == "f" else 0)
        np.testing.assert_allclose(np.asarray(op(x)), np.asarray(ref[k](x)), atol=1e-6, err_msg=k)
    # and the map-built S is an involution with non-trivial action on the joints
    q = imported.obs["qpos"][0, 0]
    assert not np.allclose(np.asarray(ops["qpos"](q)), q)
    np.testing.assert_allclose(np.asarray(ops["qpos"](ops["qpos"](q))), q, atol=1e-5)


def test_symmetry_map_mismatch_errors(tmp_path, mirror_map):
    d = _demos()
    imported = read_dataset("dp3", export_dataset("dp3", d, tmp_path / "x.zarr"))
    rec = imported.meta["interop"]

    def with_record(**kw):
        return Demos(obs=imported.obs, action=imported.action, length=imported.length, success=imported.success,
                     meta={"interop": {**rec, **kw}}, action_ee=imported.action_ee)

    names = list(rec["names"]["qpos"])
    with pytest.raises(InteropError, match="entry 'elbow_x' is neither a joint of the mirror map"):
        map_env(with_record(names={"qpos": ["elbow_x"] + names[1:], "action": names}), mirror_map)
    with pytest.raises(InteropError, match="size mismatch: 'qpos' has 14 entries but 13 names"):
        map_env(with_record(names={"qpos": names[:13], "action": names}), mirror_map)
    with pytest.raises(InteropError, match=r"camera\(s\) \['front'\] of 'image' are not in the mirror map"):
        map_env(with_record(cameras={**rec["cameras"], "image": ["front"]}), mirror_map)
    with pytest.raises(InteropError, match="'wrist_left' of 'image' is not its own mirror image"):
        map_env(with_record(cameras={**rec["cameras"], "image": ["wrist_left"]}), mirror_map)
    with pytest.raises(InteropError, match="not mirror partners"):
        map_env(with_record(cameras={**rec["cameras"], "wrist_image": ["wrist_left", "head"]}), mirror_map)
    with pytest.raises(InteropError, match="no entry names"):
        map_env(with_record(names={}), mirror_map)
    ok = map_env(imported, mirror_map)
    with pytest.raises(InteropError, match="reads 'depth', which the dataset does not have"):
        ok.symmetry_ops(("depth",))


def test_cli_export_import(tmp_path, capsys):
    from equibim_jax.cli import main

    save(_demos(images=False), tmp_path / "ours.zarr")
    main(["export", "--format", "dp3", str(tmp_path / "ours.zarr"), str(tmp_path / "dp3.zarr")])
    main(["import", "--format", "dp3", str(tmp_path / "dp3.zarr"), str(tmp_path / "back.zarr")])
    assert "3 episodes" in capsys.readouterr().out
    _assert_same(load(tmp_path / "ours.zarr"), load(tmp_path / "back.zarr"))
    with pytest.raises(SystemExit) as e:
        main(["import", "--format", "lerobot", str(tmp_path / "dp3.zarr"), str(tmp_path / "x.zarr")])
    assert e.value.code == 2 and "missing meta/info.json" in capsys.readouterr().err


def test_train_on_imported_dataset_with_mirror_map(tmp_path, mirror_map, capsys):
    """`equibim train --data IMPORTED --symmetry map.json` runs L_sym on data without a simulated env."""
    from equibim_jax.cli import main
    from equibim_jax.config import config_to_dict
    from equibim_jax.policies import DP3Config, EncoderConfig, UNetConfig
    from equibim_jax.sim import robot_info
    from equibim_jax.training import TrainConfig

    info = robot_info("robot_a")
    names = [*info.arm_joints[0], "gripper_left", *info.arm_joints[1], "gripper_right"]
    src = _foreign_dp3(tmp_path / "dp3.zarr", n_eps=3, t=12, pc_dim=3)
    (tmp_path / "mapping.json").write_text(json.dumps({"names": {"qpos": names, "action": names},
                                                       "cameras": {"img": "head"}}))
    main(["import", "--format", "dp3", str(src), str(tmp_path / "data.zarr"), "--mapping", str(tmp_path / "mapping.json")])
    data = str(tmp_path / "data.zarr")
    # without a map there is no S for imported data: a clear error, exit status 2
    with pytest.raises(SystemExit) as e:
        main(["train", "--data", data, "--out", str(tmp_path / "run0")])
    assert e.value.code == 2 and "pass --symmetry map.json" in capsys.readouterr().err
    policy = DP3Config(obs_horizon=2, pred_horizon=4, action_horizon=2,
                       encoder=EncoderConfig(state_hidden=(8,), state_out=8, pc_hidden=(8,), pc_out=8),
                       unet=UNetConfig(down_dims=(8,), kernel_size=3, n_groups=2, step_embed_dim=8))
    train = TrainConfig(batch_size=4, sym_batch_size=4, warmup_steps=1, total_steps=4, steps_per_dispatch=2,
                        sym_weight=1.0, sym_warmup_steps=0)
    (tmp_path / "cfg.json").write_text(json.dumps({"policy": config_to_dict(policy), "train": config_to_dict(train)}))
    main(["train", "--config", str(tmp_path / "cfg.json"), "--data", data, "--out", str(tmp_path / "run"),
          "--symmetry", str(mirror_map)])
    rows = [json.loads(r) for r in (tmp_path / "run/train.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [2, 4]
    assert all(np.isfinite(r["sym"]) and r["sym"] > 0 for r in rows)
    cfg = json.loads((tmp_path / "run/config.json").read_text())
    assert cfg["task"]["name"] == "imported" and cfg["task"]["options"]["symmetry"] == str(mirror_map)


def test_lerobot_foreign_layout(tmp_path):
    """A v3 dataset as LeRobot writes it without us: variable-size list columns, names as
    {"motors": [...]}, images stored as PNG in the parquet, two episodes split over two data files."""
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq
    from PIL import Image

    rng = np.random.default_rng(2)
    lengths, d = [4, 3], 6
    names = [f"m{i}" for i in range(d)]
    imgs = _images(rng, sum(lengths), 8, 10)
    state = rng.normal(size=(sum(lengths), d)).astype(np.float32)
    action = rng.normal(size=(sum(lengths), d)).astype(np.float32)

    def png(a):
        b = io.BytesIO()
        Image.fromarray(a).save(b, format="PNG")
        return {"bytes": b.getvalue(), "path": None}

    start = 0
    for e, n in enumerate(lengths):
        rows = slice(start, start + n)
        (tmp_path / f"lr/data/chunk-000").mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table({
            "observation.state": pa.array(state[rows].tolist(), pa.list_(pa.float32())),
            "action": pa.array(action[rows].tolist(), pa.list_(pa.float32())),
            "observation.images.top": pa.array([png(a) for a in imgs[rows]]),
            "episode_index": pa.array([e] * n, pa.int64()), "frame_index": pa.array(range(n), pa.int64()),
            "timestamp": pa.array(np.arange(n) / 10, pa.float32()), "index": pa.array(range(start, start + n)),
            "task_index": pa.array([0] * n, pa.int64())}), tmp_path / f"lr/data/chunk-000/file-{e:03d}.parquet")
        start += n
    (tmp_path / "lr/meta/episodes/chunk-000").mkdir(parents=True)
    pq.write_table(pa.table({"episode_index": [1, 0], "length": [lengths[1], lengths[0]],
                             "tasks": [["fold"], ["fold"]]}), tmp_path / "lr/meta/episodes/chunk-000/file-000.parquet")
    feats = {"observation.state": {"dtype": "float32", "shape": [d], "names": {"motors": names}},
             "action": {"dtype": "float32", "shape": [d], "names": {"motors": names}},
             "observation.images.top": {"dtype": "image", "shape": [8, 10, 3], "names": ["height", "width", "channel"]},
             **{k: {"dtype": "int64", "shape": [1], "names": None} for k in ("episode_index", "frame_index", "index",
                                                                             "task_index")}}
    (tmp_path / "lr/meta/info.json").write_text(json.dumps({"codebase_version": "v3.0", "fps": 10, "features": feats,
                                                            "total_episodes": 2, "total_frames": 7}))
    got = read_dataset("lerobot", tmp_path / "lr")
    np.testing.assert_array_equal(got.length, lengths)
    np.testing.assert_array_equal(_valid(got.obs["qpos"], got.length), state)
    np.testing.assert_array_equal(_valid(got.action, got.length), action)
    np.testing.assert_array_equal(_valid(got.obs["image"], got.length), imgs)  # PNG is lossless
    np.testing.assert_array_equal(got.obs["qpos"][1, 3], state[-1])  # padded with the last step
    rec = got.meta["interop"]
    assert rec["names"] == {"qpos": names, "action": names} and rec["cameras"] == {"image": ["top"]}
    assert rec["fps"] == 10 and rec["tasks"] == [["fold"], ["fold"]] and "task" not in got.meta
