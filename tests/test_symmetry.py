"""Tests of the symmetry operators and of S derived from MJCF."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import mjcf_fixtures as fx
from equibim_jax import symmetry as sy

floats = st.floats(-10, 10, allow_nan=False, width=64)
MIRRORS = [
    sy.Mirror.from_axis("y"),
    sy.Mirror.from_axis("x", 0.25),
    sy.Mirror((1.0, 2.0, -0.5), (0.1, -0.3, 0.2)),  # oblique plane, off the origin
]


def _vecs(n_last):
    return hnp.arrays(np.float64, st.tuples(st.integers(1, 4), st.just(n_last)), elements=floats)


def _random_rotations(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    r = np.zeros((n, 9))
    for i in range(n):
        mujoco.mju_quat2Mat(r[i], q[i])
    return q, r.reshape(n, 3, 3)


@pytest.fixture(autouse=True)
def _x64():
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", False)


# --- the plane ------------------------------------------------------------------------
def test_mirror_matrix_and_homogeneous():
    m = sy.Mirror((0.0, 2.0, 0.0), (0.0, 0.5, 0.0))
    np.testing.assert_allclose(m.matrix, np.diag([1.0, -1.0, 1.0]))
    h = m.homogeneous
    p = np.array([0.3, 0.9, -0.2, 1.0])
    np.testing.assert_allclose(h @ p, [0.3, 0.1, -0.2, 1.0])  # y=0.9 -> 2*0.5-0.9
    with pytest.raises(ValueError, match="non-zero"):
        sy.Mirror((0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="3 finite"):
        sy.Mirror((0.0, 1.0))


# --- involutions (property tests) ------------------------------------------------------
@settings(max_examples=40, deadline=None)
@given(x=_vecs(3), mi=st.integers(0, len(MIRRORS) - 1))
def test_point_vector_involutions(x, mi):
    m = MIRRORS[mi]
    for op in (sy.reflect_points, sy.reflect_polar, sy.reflect_axial):
        y = op(m, x)
        np.testing.assert_allclose(op(m, y), x, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), mi=st.integers(0, len(MIRRORS) - 1), li=st.integers(0, 2))
def test_rotation_involutions_and_quat_matches_matrix(seed, mi, li):
    m = MIRRORS[mi]
    loc = sy.axis_reflection(li)
    rng = np.random.default_rng(seed)
    q, r = _random_rotations(rng, 5)
    r2 = np.asarray(sy.reflect_rotmat(m, r, loc))
    np.testing.assert_allclose(np.asarray(sy.reflect_rotmat(m, r2, loc)), r, atol=1e-9)
    q2 = np.asarray(sy.reflect_quat(m, q, loc))
    np.testing.assert_allclose(np.asarray(sy.reflect_quat(m, q2, loc)), q, atol=1e-9)
    # The quaternion rule gives the same rotation as the matrix rule M R L.
    for i in range(5):
        rq = np.zeros(9)
        mujoco.mju_quat2Mat(rq, q2[i])
        np.testing.assert_allclose(rq.reshape(3, 3), r2[i], atol=1e-9)
        assert np.linalg.det(r2[i]) == pytest.approx(1.0)
    # 6D and 7D poses.
    r6 = np.concatenate([r[:, :, 0], r[:, :, 1]], -1)
    out6 = np.asarray(sy.reflect_rot6d(m, r6, loc))
    np.testing.assert_allclose(np.asarray(sy.rot6d_to_matrix(out6)), r2, atol=1e-9)
    pose = np.concatenate([rng.normal(size=(5, 3)), r6], -1)
    np.testing.assert_allclose(sy.reflect_pose_6d(m, sy.reflect_pose_6d(m, pose, loc), loc), pose, atol=1e-9)
    pose7 = np.concatenate([rng.normal(size=(5, 3)), q], -1)
    np.testing.assert_allclose(sy.reflect_pose_quat(m, sy.reflect_pose_quat(m, pose7, loc), loc), pose7, atol=1e-9)


def test_quaternion_rule_for_y_plane_matches_design():
    q = jnp.array([0.1, 0.2, 0.3, 0.4])
    out = sy.reflect_quat(sy.Mirror.from_axis("y"), q, np.diag([1.0, -1.0, 1.0]))
    np.testing.assert_allclose(out, [0.1, -0.2, 0.3, -0.4])


def test_oblique_local_reflection_6d_uses_third_column():
    m = MIRRORS[2]
    n = np.array([1.0, 1.0, 1.0]) / np.sqrt(3)
    loc = np.eye(3) - 2 * np.outer(n, n)
    _, r = _random_rotations(np.random.default_rng(3), 4)
    r6 = np.concatenate([r[:, :, 0], r[:, :, 1]], -1)
    out = sy.rot6d_to_matrix(sy.reflect_rot6d(m, r6, loc))
    np.testing.assert_allclose(out, sy.reflect_rotmat(m, r, loc), atol=1e-9)


# --- composition with rigid transforms -------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), mi=st.integers(0, len(MIRRORS) - 1))
def test_points_compose_with_rigid_transforms(seed, mi):
    """S T S is the rigid motion with rotation M R M (det +1): S(T(p)) = (M R M) S(p) + t'."""
    m = MIRRORS[mi]
    rng = np.random.default_rng(seed)
    _, r = _random_rotations(rng, 1)
    r, t = r[0], rng.normal(size=3)
    p = rng.normal(size=(7, 3))
    mm = m.matrix
    r_conj = mm @ r @ mm
    assert np.linalg.det(r_conj) == pytest.approx(1.0)
    # t' from the plane geometry: S(T(S(0))) written out with p0.
    p0 = np.asarray(m.point)
    s0 = p0 - mm @ p0  # S(0)
    t_conj = p0 + mm @ (r @ s0 + t - p0)
    lhs = np.asarray(sy.reflect_points(m, p @ r.T + t))
    rhs = np.asarray(sy.reflect_points(m, p)) @ r_conj.T + t_conj
    np.testing.assert_allclose(lhs, rhs, atol=1e-9)
    # Distances are preserved; a vector between two points reflects as a polar vector.
    np.testing.assert_allclose(
        np.asarray(sy.reflect_points(m, p[1:])) - np.asarray(sy.reflect_points(m, p[:-1])),
        sy.reflect_polar(m, p[1:] - p[:-1]),
        atol=1e-9,
    )
    # Cross product of polar vectors is axial.
    a, b = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(
        np.cross(sy.reflect_polar(m, a), sy.reflect_polar(m, b)), sy.reflect_axial(m, np.cross(a, b)), atol=1e-9
    )


# --- images and point clouds -----------------------------------------------------------
def test_image_flip_known_pixels_nhwc_nchw():
    img = np.zeros((2, 3, 4, 3), np.uint8)  # N H W C
    img[0, 1, 0] = [255, 0, 0]  # red at the left of row 1
    img[1, 2, 3] = [0, 0, 9]
    out = np.asarray(sy.flip_image(img, "NHWC"))
    assert out[0, 1, 3].tolist() == [255, 0, 0] and out[0, 1, 0].tolist() == [0, 0, 0]
    assert out[1, 2, 0].tolist() == [0, 0, 9]
    chw = np.transpose(img, (0, 3, 1, 2))
    out2 = np.asarray(sy.flip_image(chw, "NCHW"))
    np.testing.assert_array_equal(np.transpose(out2, (0, 2, 3, 1)), out)
    np.testing.assert_array_equal(sy.flip_image(out, "NHWC"), img)
    with pytest.raises(ValueError, match="layout"):
        sy.flip_image(img, "HWNC")


def _cam_to_world(x_ax, y_ax, pos):
    """Camera-to-world [4, 4] from the camera's x and y axes in the world and its position."""
    x_ax = np.asarray(x_ax, float) / np.linalg.norm(x_ax)
    y_ax = np.asarray(y_ax, float) - np.dot(y_ax, x_ax) * x_ax
    y_ax /= np.linalg.norm(y_ax)
    t = np.eye(4)
    t[:3, :3] = np.stack([x_ax, y_ax, np.cross(x_ax, y_ax)], 1)  # columns: camera axes
    t[:3, 3] = pos
    return t


def _to_cam(t, p):
    """World points [..., 3] into the frame of camera-to-world ``t`` [4, 4]."""
    return (p - t[:3, 3]) @ t[:3, :3]


def _to_world(t, p):
    return p @ t[:3, :3].T + t[:3, 3]


def test_point_cloud_camera_hand_checked_off_plane():
    # Mirror y = 0; camera at y = 0.3 with x axis = world +y, y axis = world -x, z = world z.
    m = sy.Mirror.from_axis("y")
    t = _cam_to_world([0, 1, 0], [-1, 0, 0], [0.0, 0.3, 0.0])
    # Camera (0.1, 0.2, 0.5) is world (-0.2, 0.4, 0.5); its mirror image (-0.2, -0.4, 0.5) is
    # camera (-0.4 - 0.3, 0.2, 0.5) = (-0.7, 0.2, 0.5). Mirroring about a plane through the
    # camera would give camera x = -0.1 instead (world y = 0.2).
    out = np.asarray(sy.reflect_point_cloud_camera(m, np.array([[0.1, 0.2, 0.5]]), t))
    np.testing.assert_allclose(out, [[-0.7, 0.2, 0.5]], atol=1e-12)


@pytest.mark.parametrize("mirror", MIRRORS, ids=["y", "x+0.25", "oblique"])
def test_point_cloud_camera_off_plane_matches_world_reflection(mirror):
    rng = np.random.default_rng(3)
    # A pitched and yawed camera at y = 0.3 (off every plane in MIRRORS).
    t = _cam_to_world([np.sin(0.4), -np.cos(0.4), 0.0], [0.8 * np.cos(0.4), 0.8 * np.sin(0.4), 0.6],
                      [-0.2, 0.3, 0.75])
    world = rng.normal(size=(2, 4, 50, 3))
    cam = np.concatenate([_to_cam(t, world), rng.uniform(size=(2, 4, 50, 3))], -1)  # xyz + rgb
    out = np.asarray(sy.reflect_point_cloud_camera(mirror, cam, t))
    assert out.shape == cam.shape
    np.testing.assert_allclose(_to_world(t, out[..., :3]), sy.reflect_points(mirror, world), atol=1e-12)
    np.testing.assert_array_equal(out[..., 3:], cam[..., 3:])
    # An involution, also jitted and with one camera pose per batch element.
    np.testing.assert_allclose(sy.reflect_point_cloud_camera(mirror, out, t), cam, atol=1e-12)
    ts = np.stack([t, _cam_to_world([0, 0, 1], [1, 0, 0], [0.5, -0.4, 0.2])])  # [2, 4, 4]
    cam2 = np.stack([_to_cam(ts[i], world[i]) for i in range(2)])  # [2, 4, 50, 3]
    f = jax.jit(lambda p, tt: sy.reflect_point_cloud_camera(mirror, p, tt[:, None]))
    out2 = np.asarray(f(cam2, ts))
    for i in range(2):
        np.testing.assert_allclose(_to_world(ts[i], out2[i]), sy.reflect_points(mirror, world[i]), atol=1e-12)
    np.testing.assert_allclose(f(out2, ts), cam2, atol=1e-12)
    with pytest.raises(ValueError, match="4, 4"):
        sy.reflect_point_cloud_camera(mirror, cam, t[:3])


def test_point_cloud_camera_on_plane_is_x_flip():
    m = sy.Mirror.from_axis("y")
    # Head camera of robot A: on y = 0, x axis (0, -1, 0), pitched down.
    t = _cam_to_world([0, -1, 0], [0.8, 0, 0.6], [-0.2, 0.0, 0.75])
    world = np.random.default_rng(0).normal(size=(3, 50, 3))
    cam = _to_cam(t, world)
    out = np.asarray(sy.reflect_point_cloud_camera(m, cam, t))
    np.testing.assert_allclose(out, cam * np.array([-1.0, 1.0, 1.0]), atol=1e-12)
    np.testing.assert_allclose(_to_world(t, out), sy.reflect_point_cloud(m, world), atol=1e-12)


def test_operators_jit_vmap_and_batch_dims():
    m = sy.Mirror.from_axis("y")
    x = jnp.asarray(np.random.default_rng(1).normal(size=(2, 3, 5, 7)))
    f = jax.jit(jax.vmap(lambda v: sy.reflect_pose_quat(m, v, np.diag([1.0, -1.0, 1.0]))))
    out = f(x)
    assert out.shape == x.shape
    np.testing.assert_allclose(out, sy.reflect_pose_quat(m, x, np.diag([1.0, -1.0, 1.0])))


# --- JointMap / Symmetry -----------------------------------------------------------------
def test_jointmap_apply_and_errors():
    jm = sy.JointMap([1, 0, 2], [-1, -1, 1], [0.0, 0.0, 0.5], ("a", "b", "c"))
    x = jnp.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(jm(x), [[-2.0, -1.0, 3.5]])
    assert not jm.is_involution()  # offset 0.5 with sign +1 is not an involution
    jm2 = sy.JointMap([1, 0, 2], [-1, -1, -1], [0.0, 0.0, 0.5])
    assert jm2.is_involution()
    np.testing.assert_allclose(jm2(jm2(x)), x)
    with pytest.raises(ValueError, match="permutation"):
        sy.JointMap([0, 0], [1, 1], [0, 0])
    with pytest.raises(ValueError, match="signs"):
        sy.JointMap([0, 1], [1, 2], [0, 0])
    with pytest.raises(ValueError, match="size 3"):
        jm(jnp.zeros(4))
    sel = jm2.select([0, 1])
    np.testing.assert_allclose(sel(jnp.array([1.0, 2.0])), [-2.0, -1.0])
    with pytest.raises(ValueError, match="closed"):
        jm2.select([0, 2])


def test_symmetry_structure_on_batch_pytree():
    m = sy.Mirror.from_axis("y")
    jm = sy.JointMap([1, 0], [-1, -1], [0, 0])
    s = sy.Symmetry(
        {"qpos": jm, "image": sy.image_op("NHWC"), "point_cloud": sy.point_cloud_op(m),
         "ee": sy.arm_swap_pose_op(m, np.diag([1.0, -1.0, 1.0]), "quat", extra=1)},
        passthrough=("episode",),
    )
    rng = np.random.default_rng(0)
    batch = {
        "qpos": rng.normal(size=(4, 2, 2)),
        "image": rng.integers(0, 255, size=(4, 2, 8, 8, 3)).astype(np.uint8),
        "point_cloud": rng.normal(size=(4, 2, 32, 3)),
        "ee": rng.normal(size=(4, 2, 16)),
        "episode": np.arange(4),
    }
    out = jax.jit(s)(batch)
    back = s(out)
    for k in batch:
        np.testing.assert_allclose(np.asarray(back[k]), batch[k], atol=1e-9, err_msg=k)
    # Arms are swapped: new arm A pose is the mirrored old arm B pose.
    np.testing.assert_allclose(out["ee"][..., :7], sy.reflect_pose_quat(m, batch["ee"][..., 8:15], np.diag([1.0, -1.0, 1.0])))
    with pytest.raises(KeyError, match="no operator for field 'depth'"):
        s({"depth": np.zeros((1, 4, 4))})


# --- derive / verify ---------------------------------------------------------------------
def _jid(model, name):
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)


def test_derive_side_by_side_signs_and_swaps():
    model = fx.load(fx.side_by_side_xml())
    ms = sy.derive_symmetry(model, sy.Mirror.from_axis("y"))
    expect = {"l_yaw": ("r_yaw", -1), "l_pitch": ("r_pitch", 1), "l_roll": ("r_roll", -1),
              "l_finger_a": ("r_finger_b", 1), "l_finger_b": ("r_finger_a", 1)}
    for a, (b, s) in expect.items():
        j = _jid(model, a)
        assert ms.joints[j] == _jid(model, b), a
        assert ms.joint_signs[j] == s, a
        assert ms.joints[_jid(model, b)] == j
    assert sy.verify_symmetry(model, ms, n=64) <= 1e-6
    # The cup (free joint) maps its position as a point and is its own mirror body.
    cup = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "cup")
    assert ms.bodies[cup] == cup
    q = model.qpos0.copy()
    qm = np.asarray(ms.qpos(q))
    adr = model.jnt_qposadr[_jid(model, "cup")]
    np.testing.assert_allclose(qm[adr : adr + 3], q[adr : adr + 3] * [1, -1, 1])
    # qvel and ctrl maps follow the joint map; all are involutions.
    for jm in (ms.qpos, ms.qvel, ms.ctrl):
        assert jm.is_involution()
    u = np.random.default_rng(0).uniform(-1, 1, model.nu)
    um = np.asarray(ms.ctrl(u))
    a_l = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "l_yaw")
    a_r = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "r_yaw")
    assert um[a_r] == pytest.approx(-u[a_l])
    head = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "head")
    assert ms.cameras[head] == head


def test_derive_facing_each_other_plane_x():
    model = fx.load(fx.facing_xml())
    ms = sy.derive_symmetry(model, sy.Mirror.from_axis("x"))
    expect = {"a_yaw": ("b_yaw", -1), "a_pitch": ("b_pitch", 1), "a_roll": ("b_roll", -1),
              "a_finger_a": ("b_finger_b", 1)}
    for a, (b, s) in expect.items():
        j = _jid(model, a)
        assert ms.joints[j] == _jid(model, b) and ms.joint_signs[j] == s, a
    assert sy.verify_symmetry(model, ms, n=64) <= 1e-6


def test_rounded_constants_accepted_by_default_tol():
    model = fx.load(fx.facing_xml('euler="0 0 3.1416"'))
    ms = sy.derive_symmetry(model, sy.Mirror.from_axis("x"))
    res = sy.verify_symmetry(model, ms, n=64)
    assert 1e-7 < res < 1e-4  # pi rounded to 3.1416 leaves a few micrometres
    with pytest.raises(sy.SymmetryError):
        sy.derive_symmetry(model, sy.Mirror.from_axis("x"), tol=1e-7)


@pytest.mark.parametrize(
    "kw, names",
    [
        # one link 1 cm longer: the next joint's anchor is 1 cm off its mirror
        (dict(right_l1="0.31"), ["r_link2", "r_roll", "0.01 m"]),
        (dict(right_pitch_axis="0 0 1"), ["l_pitch", "r_pitch"]),  # one axis changed
        (dict(right_roll_range="-2 0.5"), ["r_roll"]),  # one axis flipped (range not mirrored)
    ],
)
def test_asymmetric_model_raises_and_names_joint(kw, names):
    model = fx.load(fx.side_by_side_xml(**kw))
    with pytest.raises(sy.SymmetryError) as e:
        sy.derive_symmetry(model, sy.Mirror.from_axis("y"))
    for n in names:
        assert n in str(e.value)


def test_wrong_plane_raises_not_wrong_map():
    model = fx.load(fx.side_by_side_xml())
    with pytest.raises(sy.SymmetryError, match="l_yaw"):
        sy.derive_symmetry(model, sy.Mirror.from_axis("x"))
    with pytest.raises(sy.SymmetryError):
        sy.derive_symmetry(model, sy.Mirror.from_axis("y", 0.05))


def test_verify_detects_a_wrong_map():
    model = fx.load(fx.side_by_side_xml(with_cup=False))
    ms = sy.derive_symmetry(model, sy.Mirror.from_axis("y"))
    import dataclasses

    bad_q = sy.JointMap(ms.qpos.perm, -ms.qpos.signs, ms.qpos.offsets)
    bad = dataclasses.replace(ms, qpos=bad_q)
    assert sy.verify_symmetry(model, bad, n=16) > 1e-2


def test_geom_colour_asymmetry_is_reported_or_refused():
    """Images mirror as a flip only if mirrored geoms look the same: a geom of another colour
    is reported (kinematics are still exact), and refused with dynamics="strict"."""
    xml = fx.side_by_side_xml(with_cup=False)
    model = fx.load(xml)
    g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "r_link2")
    geom = [i for i in range(model.ngeom) if model.geom_bodyid[i] == g][0]
    model.geom_rgba[geom] = [0.1, 0.2, 0.9, 1.0]
    ms = sy.derive_symmetry(model, sy.Mirror.from_axis("y"))
    assert not ms.dynamics_exact and ms.residual <= 1e-9
    assert ms.geoms[geom] == -1
    (item,) = [a for a in ms.dynamics.items if a.element == f"#{geom}"]
    assert item.kind == "geom" and "colour" in item.detail and "r_link2" in item.detail
    with pytest.raises(sy.SymmetryError, match="same type, size and colour"):
        sy.derive_symmetry(model, sy.Mirror.from_axis("y"), dynamics="strict")
