"""S for robot models written the way published ones are: kinematics strict, dynamics and
geometry reported (ALOHA-like facing arms), an approximate map for two identical arms that
are only nearly mirror images (SO-101-like), and the portable mirror map (JSON)."""

import json
import os
import re
import warnings

import mujoco
import numpy as np
import pytest

import mjcf_fixtures as fx
from equibim_jax import symmetry as sy
from equibim_jax.sim import load_robot

X_PLANE = sy.Mirror((1.0, 0.0, 0.0))
Y_PLANE = sy.Mirror.from_axis("y")


def _id(model, obj, name):
    i = mujoco.mj_name2id(model, obj, name)
    assert i >= 0, name
    return i


def _jid(model, name):
    return _id(model, mujoco.mjtObj.mjOBJ_JOINT, name)


def _bid(model, name):
    return _id(model, mujoco.mjtObj.mjOBJ_BODY, name)


@pytest.fixture(scope="module")
def aloha():
    model = fx.load(fx.aloha_like_xml())
    return model, sy.derive_symmetry(model, X_PLANE)


@pytest.fixture(scope="module")
def so101():
    model = fx.load(fx.so101_pair_xml())
    with pytest.warns(sy.SymmetryWarning, match="wrist_roll") as rec:
        sym = sy.derive_symmetry(model, Y_PLANE, approximate=True)
    return model, sym, [str(w.message) for w in rec]


# --- the robots written here stay exact in kinematics and dynamics ------------------------
@pytest.mark.parametrize("name", ["robot_a", "robot_b"])
def test_own_robots_exact_in_kinematics_and_dynamics(name):
    model, mirror = load_robot(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error", sy.SymmetryWarning)
        sym = sy.derive_symmetry(model, mirror)
        strict = sy.derive_symmetry(model, mirror, dynamics="strict")
    for s in (sym, strict):
        assert s.residual <= 1e-9 and s.dynamics_exact and s.dynamics.items == ()
        assert s.warnings == () and not s.approximate
        assert s.dynamics.max_com_offset_m <= 1e-12 and s.dynamics.max_inertia_rel <= 1e-12
        assert np.all(s.geoms >= 0) and np.all(s.body_residual <= 1e-9)
    np.testing.assert_array_equal(sym.qpos.perm, strict.qpos.perm)
    np.testing.assert_array_equal(sym.qpos.signs, strict.qpos.signs)


# --- ALOHA-like: facing arms, mirror plane x = 0 --------------------------------------------
def test_aloha_like_kinematics_strict_dynamics_reported(aloha):
    model, sym = aloha
    # pi written as 3.1416 leaves micrometres; strict kinematics accepts that.
    assert 1e-7 < sym.residual < 1e-4 and not sym.approximate
    expect = {"waist": -1, "shoulder": 1, "elbow": 1, "forearm_roll": -1, "wrist_angle": 1, "wrist_rotate": -1}
    for j, s in expect.items():
        a = _jid(model, f"left/{j}")
        assert sym.joints[a] == _jid(model, f"right/{j}") and sym.joint_signs[a] == s, j
    # Fingers: the left arm's left finger is the mirror of the right arm's right finger.
    a = _jid(model, "left/left_finger")
    assert sym.joints[a] == _jid(model, "right/right_finger") and sym.joint_signs[a] == -1
    act = lambda n: _id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, n)
    assert sym.ctrl.perm[act("right/right_finger")] == act("left/left_finger")
    assert sym.ctrl.signs[act("right/right_finger")] == -1
    u = np.random.default_rng(0).uniform(model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1])
    um = np.asarray(sym.ctrl(u))
    assert np.all(um >= model.actuator_ctrlrange[:, 0] - 1e-6) and np.all(um <= model.actuator_ctrlrange[:, 1] + 1e-6)
    assert sy.verify_symmetry(model, sym, n=32) < 1e-4


def test_aloha_like_massless_mounts_not_compared_by_inertial_frame(aloha):
    model, sym = aloha
    lb, rb = _bid(model, "left/base_link"), _bid(model, "right/base_link")
    # The fixture does what it says: massless bases, one with an inertial frame far away.
    assert model.body_mass[lb] == 0 and model.body_mass[rb] == 0
    d = mujoco.MjData(model)
    mujoco.mj_kinematics(model, d)
    assert np.linalg.norm(d.xipos[rb] - d.xipos[lb] * [-1, 1, 1]) > 0.5
    assert sym.bodies[lb] == rb and sym.body_residual[lb] < 1e-4
    assert not [a for a in sym.dynamics.items if "base_link" in a.element or "base_link" in str(a.mirror)]


def test_aloha_like_dynamic_report_sizes(aloha):
    model, sym = aloha
    assert not sym.dynamics_exact
    (com,) = sym.dynamics.of_kind("com")
    assert {com.element, com.mirror} == {"left/lower_forearm_link", "right/lower_forearm_link"}
    assert com.value == pytest.approx(fx.ALOHA_COM_OFFSET, abs=1e-5)
    assert sym.dynamics.max_com_offset_m == pytest.approx(fx.ALOHA_COM_OFFSET, abs=1e-5)
    assert sym.dynamics.of_kind("mass") == () and sym.dynamics.of_kind("inertia") == ()
    # Every mesh geom is chiral and unmatched; every primitive geom has its mirror.
    mesh = {g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH}
    assert {g for g in range(model.ngeom) if sym.geoms[g] < 0} == mesh and len(mesh) == 8
    geoms = sym.dynamics.of_kind("geom")
    assert len(geoms) == 8 and all("chiral" in a.detail and a.value > 1e-3 for a in geoms)
    assert "lower_forearm_link" in sym.report()


def test_aloha_like_refused_with_strict_dynamics():
    model = fx.load(fx.aloha_like_xml())
    with pytest.raises(sy.SymmetryError) as e:
        sy.derive_symmetry(model, X_PLANE, dynamics="strict")
    msg = str(e.value)
    assert "lower_forearm_link" in msg and "0.014 m" in msg and "chiral" in msg
    # Without the COM offset and with mirrored (here: no) meshes, strict dynamics passes.
    exact = fx.load(re.sub(r'type="mesh" mesh="\w+"', 'type="sphere" size="0.01"', fx.aloha_like_xml(com_y=0.0)))
    sym = sy.derive_symmetry(exact, X_PLANE, dynamics="strict")
    assert sym.dynamics_exact


def test_aloha_like_cameras_pair_and_flip(aloha):
    model, sym = aloha
    cam = lambda n: _id(model, mujoco.mjtObj.mjOBJ_CAMERA, n)
    assert sym.cameras[cam("cam_high")] == cam("cam_high")
    assert sym.cameras[cam("left/wrist_cam")] == cam("right/wrist_cam")
    assert sym.camera_flip == ("horizontal", "horizontal", "horizontal")


# --- SO-101-like: identical arms side by side, only nearly mirror images --------------------
def test_so101_pair_strict_refuses_and_names_the_joint():
    model = fx.load(fx.so101_pair_xml())
    with pytest.raises(sy.SymmetryError) as e:
        sy.derive_symmetry(model, Y_PLANE)
    assert "l_shoulder_lift" in str(e.value) and "0.036 m" in str(e.value)


def test_so101_pair_approximate_signs_ranges_and_residual(so101):
    model, sym, warned = so101
    assert sym.approximate and sym.tol == sy.APPROX_TOL
    expect = {"shoulder_pan": -1, "shoulder_lift": 1, "elbow_flex": 1, "wrist_flex": 1, "wrist_roll": -1,
              "gripper": 1}
    for j, s in expect.items():
        a, b = _jid(model, f"l_{j}"), _jid(model, f"r_{j}")
        assert sym.joints[a] == b and sym.joints[b] == a and sym.joint_signs[a] == s, j
        np.testing.assert_array_equal(sym.qpos.offsets[model.jnt_qposadr[a]], 0.0)
    # The reported residual is the built-in offset: 2 x 1.8 cm from the upper arm on.
    off = 2 * fx.SO_LIFT_OFFSET
    assert sym.residual == pytest.approx(off, abs=1e-9)
    for p in "lr":
        for b in ("base", "shoulder"):
            assert sym.body_residual[_bid(model, f"{p}_{b}")] <= 1e-9, b
        for b in ("upper_arm", "lower_arm", "wrist", "gripper", "jaw"):
            assert sym.body_residual[_bid(model, f"{p}_{b}")] == pytest.approx(off, abs=1e-9), b
    np.testing.assert_allclose(sym.site_residual, off, atol=1e-9)
    # The asymmetric wrist-roll range is intersected, with warnings (joint and actuator).
    assert len(warned) == 2 and any("ctrlrange" in w for w in warned)
    for p in "lr":
        np.testing.assert_allclose(sym.joint_ranges[_jid(model, f"{p}_wrist_roll")], [-2.744, 2.744])
        a = _id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, f"{p}_wrist_roll")
        np.testing.assert_allclose(sym.ctrl_ranges[a], [-2.744, 2.744])
    assert sym.warnings == tuple(warned)
    # Geometry: the off-centre base box and the chiral gripper mesh are reported.
    unmatched = {model.geom_bodyid[g] for g in range(model.ngeom) if sym.geoms[g] < 0}
    assert unmatched == {_bid(model, n) for n in ("l_base", "r_base", "l_gripper", "r_gripper")}
    assert not sym.dynamics_exact
    # verify_symmetry samples inside the intersected ranges and agrees.
    assert sy.verify_symmetry(model, sym, n=16) == pytest.approx(off, abs=1e-9)


@pytest.mark.parametrize("lift_y", [0.005, 0.012])
def test_so101_pair_residual_tracks_offset(lift_y):
    model = fx.load(fx.so101_pair_xml(lift_y=lift_y, roll_range="-2.8 2.8", box_y=0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", sy.SymmetryWarning)  # symmetric ranges: no concession
        sym = sy.derive_symmetry(model, Y_PLANE, approximate=True, n_verify=16)
    assert sym.residual == pytest.approx(2 * lift_y, abs=1e-9)
    assert sym.warnings == ()


def test_so101_pair_approximate_beyond_tol_lists_bodies():
    model = fx.load(fx.so101_pair_xml())
    with pytest.raises(sy.SymmetryError) as e, warnings.catch_warnings():
        warnings.simplefilter("ignore", sy.SymmetryWarning)
        sy.derive_symmetry(model, Y_PLANE, approximate=True, tol=0.02, n_verify=8)
    msg = str(e.value)
    assert "body 'l_upper_arm' residual 0.036 m" in msg and "site 'r_ee' residual 0.036 m" in msg
    assert "l_shoulder" not in msg.replace("l_shoulder_lift", "")  # the shoulder itself is fine


def test_approximate_on_exact_model_equals_strict():
    model = fx.load(fx.side_by_side_xml())
    strict = sy.derive_symmetry(model, Y_PLANE)
    with warnings.catch_warnings():
        warnings.simplefilter("error", sy.SymmetryWarning)
        approx = sy.derive_symmetry(model, Y_PLANE, approximate=True)
    for f in ("bodies", "joints", "joint_signs", "geoms", "sites"):
        np.testing.assert_array_equal(getattr(approx, f), getattr(strict, f), err_msg=f)
    np.testing.assert_array_equal(approx.qpos.perm, strict.qpos.perm)
    assert approx.residual <= 1e-9 and approx.dynamics_exact


# --- meshes and planes -----------------------------------------------------------------------
def _two_meshes_xml(left_mesh, right_mesh):
    return f"""
<mujoco>
  <asset>
    <mesh name="chiral" vertex="0 0 0  0.05 0 0  0 0.03 0  0 0 0.02"/>
    <mesh name="chiral_mirrored" vertex="0 0 0  0.05 0 0  0 -0.03 0  0 0 0.02"/>
    <mesh name="wedge" vertex="0 -0.02 0  0 0.02 0  0.05 0 0  0 -0.02 0.03  0 0.02 0.03  0.05 0 0.03"/>
  </asset>
  <worldbody>
    <body name="l" pos="0 0.2 0"><joint name="l" axis="0 0 1"/><geom type="mesh" mesh="{left_mesh}"/></body>
    <body name="r" pos="0 -0.2 0"><joint name="r" axis="0 0 1"/><geom type="mesh" mesh="{right_mesh}"/></body>
  </worldbody>
</mujoco>"""


@pytest.mark.parametrize("left, right, matched", [
    ("chiral", "chiral", False),  # the same chiral mesh on both sides
    ("chiral", "chiral_mirrored", True),  # a chiral mesh and its mirror image
    ("wedge", "wedge", True),  # a mesh that is its own mirror image
])
def test_mesh_geoms_compare_vertex_sets(left, right, matched):
    model = fx.load(_two_meshes_xml(left, right))
    sym = sy.derive_symmetry(model, Y_PLANE)
    assert sym.residual <= 1e-9
    assert bool(np.all(sym.geoms >= 0)) == matched
    assert sym.dynamics_exact == matched


def test_mirror_plane_off_the_origin():
    a = fx._arm("a_", "-0.15 0 0", roll_range="-1 1", yaw_range="-1 1")
    b = fx._arm("b_", "0.65 0 0", rot='quat="0 0 0 1"', roll_range="-1 1", yaw_range="-1 1")
    model = fx.load(fx._model([a, b], table_pos="0.25 0 -0.02"))
    sym = sy.derive_symmetry(model, sy.Mirror((1.0, 0.0, 0.0), (0.25, 0.0, 0.0)), dynamics="strict")
    assert sym.residual <= 1e-9 and sym.dynamics_exact
    assert sym.joints[_jid(model, "a_yaw")] == _jid(model, "b_yaw")


# --- the portable mirror map -----------------------------------------------------------------
def test_mirror_map_json_round_trip(aloha, tmp_path):
    model, sym = aloha
    path = tmp_path / "map.json"
    sy.save_mirror_map(sym, path, ee_sites=("left/ee", "right/ee"))
    assert os.listdir(tmp_path) == ["map.json"]  # written atomically, no temporary left over
    d = json.loads(path.read_text())
    assert d["format_version"] == sy.FORMAT_VERSION
    for k, n in (("qpos", model.nq), ("qvel", model.nv), ("ctrl", model.nu)):
        assert len(d[k]["perm"]) == len(d[k]["sign"]) == len(d[k]["offset"]) == n
    assert d["qpos"]["perm"] == sym.qpos.perm.tolist() and d["ctrl"]["sign"] == sym.ctrl.signs.tolist()
    assert d["residual_m"] == pytest.approx(sym.residual)
    assert {b["body"]: b["residual_m"] for b in d["bodies"]}["left/gripper_link"] == pytest.approx(
        sym.body_residual[_bid(model, "left/gripper_link")])
    assert d["dynamics"]["exact"] is False and len(d["dynamics"]["unmatched_geoms"]) == 8
    assert [c["flip"] for c in d["cameras"]] == ["horizontal"] * 3
    assert [(p["site"], p["mirror"]) for p in d["ee_action"]["pairs"]] == [("left/ee", "right/ee"),
                                                                            ("right/ee", "left/ee")]
    loaded = sy.load_mirror_map(path, model)
    for f in ("bodies", "joints", "joint_signs", "geoms", "sites", "cameras"):
        np.testing.assert_array_equal(getattr(loaded, f), getattr(sym, f), err_msg=f)
    np.testing.assert_allclose(loaded.body_local, sym.body_local, atol=1e-11)
    np.testing.assert_allclose(loaded.site_local, sym.site_local, atol=1e-11)
    q = np.random.default_rng(1).normal(size=model.nq)
    np.testing.assert_allclose(loaded.qpos(q), sym.qpos(q))
    assert loaded.dynamics == sym.dynamics and loaded.camera_flip == sym.camera_flip
    assert loaded.residual <= loaded.tol
    # The method forms, and a map read without a model (unchecked).
    sym.save(tmp_path / "m2.json")
    assert sy.ModelSymmetry.load(tmp_path / "m2.json").qpos.perm.tolist() == sym.qpos.perm.tolist()


def test_mirror_map_approximate_round_trip(so101, tmp_path):
    model, sym, _ = so101
    sym.save(tmp_path / "so.json")
    d = json.loads((tmp_path / "so.json").read_text())
    assert d["approximate"] is True and d["residual_m"] == pytest.approx(0.036)
    assert len(d["warnings"]) == 2
    loaded = sy.ModelSymmetry.load(tmp_path / "so.json", model)
    np.testing.assert_allclose(loaded.joint_ranges, sym.joint_ranges)
    np.testing.assert_allclose(loaded.ctrl_ranges, sym.ctrl_ranges)
    assert loaded.residual == pytest.approx(0.036, abs=1e-9)


def test_loaded_map_is_checked_against_its_model(aloha, tmp_path):
    model, sym = aloha
    path = tmp_path / "map.json"
    sym.save(path)
    with pytest.raises(sy.SymmetryError, match="nq=16, but this model has nq=10"):
        sy.load_mirror_map(path, fx.load(fx.facing_xml()))
    renamed = fx.load(fx.aloha_like_xml().replace('"left/elbow"', '"left/elbow_joint"'))
    with pytest.raises(sy.SymmetryError, match="joint 2 is 'left/elbow' in the mirror map but 'left/elbow_joint'"):
        sy.load_mirror_map(path, renamed)
    moved = fx.load(fx.aloha_like_xml())
    moved.body_pos[_bid(moved, "right/base_link")] += [0.01, 0.0, 0.0]  # same names, 1 cm off
    with pytest.raises(sy.SymmetryError, match=r"residual 0.01 m exceeds the map's tolerance 0.0005 m(.|\n)*"
                                               r"body 'left/base_link' residual 0.01 m"):
        sy.load_mirror_map(path, moved)
    d = json.loads(path.read_text())
    d["format_version"] = 99
    (tmp_path / "future.json").write_text(json.dumps(d))
    with pytest.raises(sy.SymmetryError, match="format_version 99"):
        sy.load_mirror_map(tmp_path / "future.json")
