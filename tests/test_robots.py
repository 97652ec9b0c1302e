"""The two robot models: loading, MJX compatibility, derived mirror symmetry, collision
filtering, gripper maps, and a physical friction grasp (MuJoCo C and MJX)."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from mujoco.mjx._src import collision_driver

from equibim_jax.sim import robots
from equibim_jax.sim.ik import make_ee_fk, make_ik
from equibim_jax.sim.robots import (
    OBJECT_CONAFFINITY,
    OBJECT_CONTYPE,
    load_robot,
    object_collision,
    robot_info,
    robot_names,
    robot_spec,
)
from equibim_jax.symmetry import Mirror, derive_symmetry, reflect_rotmat, verify_symmetry

NAMES = ["robot_a", "robot_b"]
PRIMITIVES = {
    int(mujoco.mjtGeom.mjGEOM_PLANE),
    int(mujoco.mjtGeom.mjGEOM_BOX),
    int(mujoco.mjtGeom.mjGEOM_CAPSULE),
    int(mujoco.mjtGeom.mjGEOM_SPHERE),
}


def test_names_and_unknown():
    assert robot_names() == ["robot_a", "robot_b"]
    with pytest.raises(ValueError, match="robot_a"):
        load_robot("robot_c")
    with pytest.raises(ValueError, match="valid names"):
        robot_info("nope")
    with pytest.raises(ValueError):
        robot_spec("nope")


@pytest.mark.parametrize("name", NAMES)
def test_load_and_layout(name):
    m, mirror = load_robot(name)
    info = robot_info(name)
    assert isinstance(m, mujoco.MjModel)
    assert mirror == Mirror.from_axis("y") == info.mirror
    # robot joints first, in the documented order; actuators in the same order
    names = info.joint_names()
    assert m.nq == m.nv == info.nq_robot == len(names)
    for i, jn in enumerate(names):
        assert m.jnt_qposadr[m.joint(jn).id] == i
    assert m.nu == info.nu
    assert tuple(m.actuator(a).name for a in range(m.nu)) == info.actuator_names()
    for a in range(m.nu):  # each actuator drives the joint of the same name
        assert m.joint(int(m.actuator_trnid[a, 0])).name == m.actuator(a).name
    # sites, camera, keyframe, materials
    for s in info.ee_sites:
        assert m.site(s).id >= 0
    for side in range(2):
        assert m.site_bodyid[m.site(info.ee_sites[side]).id] == m.body(info.ee_bodies[side]).id
    assert m.nmat >= 1
    assert m.key(info.home_key).id >= 0
    assert abs(m.opt.timestep - info.sim_dt) < 1e-12
    assert info.substeps * info.sim_dt == pytest.approx(info.control_dt)
    wmin, wmax = np.asarray(info.workspace_min), np.asarray(info.workspace_max)
    assert np.all(wmin < wmax) and wmin[1] == -wmax[1]  # mirror-symmetric box


@pytest.mark.parametrize("name", NAMES)
def test_camera_on_mirror_plane(name):
    m, _ = load_robot(name)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    cam = m.camera(robot_info(name).camera).id
    pos = d.cam_xpos[cam]
    mat = d.cam_xmat[cam].reshape(3, 3)
    assert pos[1] == 0.0
    # camera x axis (image horizontal) along -y; the other two axes have no y component
    np.testing.assert_allclose(mat[:, 0], [0.0, -1.0, 0.0], atol=1e-12)
    assert abs(mat[1, 1]) < 1e-12 and abs(mat[1, 2]) < 1e-12
    assert mat[2, 2] > 0.5  # looking down (camera -z has a negative world z)
    assert 55 <= m.cam_fovy[cam] <= 70


@pytest.mark.parametrize("name", NAMES)
def test_mjx_put_model(name):
    m, _ = load_robot(name)
    mx = mjx.put_model(m, impl="jax")
    d = mjx.make_data(mx, impl="jax")
    d = jax.jit(mjx.kinematics)(mx, d.replace(qpos=jnp.asarray(m.key_qpos[0], jnp.float32)))
    md = mujoco.MjData(m)
    md.qpos[:] = m.key_qpos[0]
    mujoco.mj_kinematics(m, md)
    np.testing.assert_allclose(np.asarray(d.site_xpos), md.site_xpos, atol=1e-5)


@pytest.mark.parametrize("name", NAMES)
def test_symmetry(name):
    m, mirror = load_robot(name)
    info = robot_info(name)
    sym = derive_symmetry(m, mirror)
    res = verify_symmetry(m, sym, n=256, seed=1)
    print(f"\n{name}: derive residual {sym.residual:.3g} m, verify_symmetry residual {res:.3g} m")
    assert sym.residual <= 1e-6 and res <= 1e-6
    # left <-> right, in the documented order; yaw/roll joints flip sign, pitch joints and
    # fingers keep it
    n = info.n_arm + info.n_gripper
    np.testing.assert_array_equal(sym.qpos.perm, np.r_[n : 2 * n, 0:n])
    np.testing.assert_array_equal(sym.ctrl.perm, np.r_[n : 2 * n, 0:n])
    np.testing.assert_array_equal(sym.qpos.offsets, 0.0)
    flips = {"waist", "forearm_roll", "wrist_rotate", "shoulder_pan", "wrist_roll"}
    for i, jn in enumerate(info.joint_names()):
        want = -1.0 if jn.split("_", 1)[1] in flips else 1.0
        assert sym.qpos.signs[i] == want, jn
    # the home posture is mirror-symmetric, in qpos and ctrl
    home = m.key_qpos[m.key(info.home_key).id]
    np.testing.assert_allclose(np.asarray(sym.qpos(home)), home, atol=1e-7)
    np.testing.assert_allclose(np.asarray(sym.ctrl(m.key_ctrl[0])), m.key_ctrl[0], atol=1e-7)
    # mirrored geoms look the same (so a mirrored scene renders as the flipped image)
    for g in range(m.ngeom):
        g2 = sym.geoms[g]
        assert m.geom_matid[g] == m.geom_matid[g2], m.geom(g).name
        np.testing.assert_array_equal(m.geom_rgba[g], m.geom_rgba[g2])
    # ee sites map onto each other with the local reflection diag(1, -1, 1)
    sl, sr = (m.site(s).id for s in info.ee_sites)
    assert sym.sites[sl] == sr and sym.sites[sr] == sl
    np.testing.assert_allclose(sym.site_local[sl], np.diag(info.ee_local_reflection), atol=1e-9)
    # and the ee poses of a random posture mirror as documented (check with MuJoCo C)
    rng = np.random.default_rng(0)
    q = rng.uniform(m.jnt_range[:, 0], m.jnt_range[:, 1])
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    pos, mat = d.site_xpos[[sl, sr]].copy(), d.site_xmat[[sl, sr]].reshape(2, 3, 3).copy()
    d.qpos[:] = np.asarray(sym.qpos(q))
    mujoco.mj_kinematics(m, d)
    pos_m, mat_m = d.site_xpos[[sr, sl]], d.site_xmat[[sr, sl]].reshape(2, 3, 3)
    np.testing.assert_allclose(pos_m, pos * [1, -1, 1], atol=1e-6)
    np.testing.assert_allclose(
        mat_m, np.asarray(reflect_rotmat(mirror, jnp.asarray(mat), np.diag(info.ee_local_reflection))),
        atol=1e-6,
    )


@pytest.mark.parametrize("name", NAMES)
def test_collision_filter(name):
    m, _ = load_robot(name)
    colliding = [g for g in range(m.ngeom) if m.geom_contype[g] or m.geom_conaffinity[g]]
    names = {m.geom(g).name for g in colliding}
    for g in range(m.ngeom):
        if g in colliding:
            assert m.geom_type[g] in PRIMITIVES
        else:
            assert m.geom_group[g] != 0 or m.geom(g).name == "table_body"
    # only the table, pads/jaws and palms may collide, with the documented bits
    info_ = robot_info(name)
    pads = set(info_.gripper_pads[0] + info_.gripper_pads[1])
    for g in colliding:
        nm = m.geom(g).name
        want = {
            "table": (robots.TABLE_CONTYPE, robots.TABLE_CONAFFINITY),
            "pad": (robots.PAD_CONTYPE, robots.PAD_CONAFFINITY),
            "palm": (robots.PALM_CONTYPE, robots.PALM_CONAFFINITY),
        }["table" if nm == "table" else "pad" if nm in pads else "palm" if "palm" in nm else nm]
        assert (m.geom_contype[g], m.geom_conaffinity[g]) == want, nm
        assert m.geom_condim[g] >= 3
    # every arm link geom is non-colliding
    info = robot_info(name)
    for side in range(2):
        for jn in info.arm_joints[side]:
            b = m.jnt_bodyid[m.joint(jn).id]
            if b == m.body(info.ee_bodies[side]).id:
                continue  # the gripper body holds the palm
            for g in range(m.body_geomadr[b], m.body_geomadr[b] + m.body_geomnum[b]):
                assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0, m.geom(g).name
    # MJX's candidate pairs in the bare robot: the four table-pad pairs only
    pairs = {
        tuple(sorted((m.geom(g1).name, m.geom(g2).name)))
        for g1, g2, _ in collision_driver.geom_pairs(m)
    }
    assert len(pairs) == 4 and all("table" in p for p in pairs), pairs

    # an object built with the documented bits touches table, pads and palms
    spec = robot_spec(name)
    body = spec.worldbody.add_body(name="obj", pos=[0.3, 0.0, 0.02])
    body.add_freejoint(name="obj")
    body.add_geom(name="obj", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02] * 3, mass=0.05,
                  **object_collision())
    m2 = spec.compile()
    assert object_collision() == {"contype": OBJECT_CONTYPE, "conaffinity": OBJECT_CONAFFINITY}
    obj_partners = {
        (m2.geom(g2).name if m2.geom(g1).name == "obj" else m2.geom(g1).name)
        for g1, g2, _ in collision_driver.geom_pairs(m2)
        if "obj" in (m2.geom(g1).name, m2.geom(g2).name)
    }
    palms = {f"{s}_palm" for s in ("left", "right")}
    assert "table" in obj_partners and palms <= obj_partners and len(obj_partners) == 7
    # the home keyframe stays valid: MuJoCo pads it with the object's qpos0
    np.testing.assert_allclose(m2.key_qpos[0][: info.nq_robot], m.key_qpos[0])
    np.testing.assert_allclose(m2.key_qpos[0][info.nq_robot : info.nq_robot + 3], [0.3, 0.0, 0.02])
    # and the scene with a centred object is still mirror-symmetric
    sym = derive_symmetry(m2, Mirror.from_axis("y"))
    assert sym.residual <= 1e-6


@pytest.mark.parametrize("name", NAMES)
def test_gripper_maps(name):
    info = robot_info(name)
    m, _ = load_robot(name)
    closed = np.asarray(info.gripper_ctrl(0.0))
    opened = np.asarray(info.gripper_ctrl(1.0))
    assert closed.shape == (info.n_gripper,)
    np.testing.assert_allclose(closed, info.gripper_closed)
    np.testing.assert_allclose(opened, info.gripper_open)
    np.testing.assert_allclose(np.asarray(info.gripper_ctrl(2.0)), opened)  # clipped
    o = jnp.linspace(0, 1, 7).reshape(7, 1)
    g = info.gripper_ctrl(o)
    assert g.shape == (7, 1, info.n_gripper)
    np.testing.assert_allclose(np.asarray(info.gripper_opening(g))[:, 0], np.asarray(o)[:, 0], atol=1e-6)
    # finger targets stay inside the actuator ctrlrange
    for side in range(2):
        for k, an in enumerate(info.gripper_actuators[side]):
            lo, hi = m.actuator_ctrlrange[m.actuator(an).id]
            assert lo - 1e-6 <= closed[k] <= hi + 1e-6 and lo - 1e-6 <= opened[k] <= hi + 1e-6
    # compose_ctrl puts the pieces where the actuators are, and commutes with the mirror
    rng = np.random.default_rng(0)
    arm = jnp.asarray(rng.uniform(-0.5, 0.5, (2, info.n_arm)), jnp.float32)
    opening = jnp.array([0.2, 0.9])
    ctrl = np.asarray(info.compose_ctrl(arm, opening))
    assert ctrl.shape == (m.nu,)
    for side in range(2):
        for k, an in enumerate(info.arm_actuators[side]):
            assert ctrl[m.actuator(an).id] == pytest.approx(float(arm[side, k]))
        got = ctrl[[m.actuator(an).id for an in info.gripper_actuators[side]]]
        np.testing.assert_allclose(got, np.asarray(info.gripper_ctrl(opening[side])), atol=1e-7)
    sym = derive_symmetry(m, Mirror.from_axis("y"))
    arm_m = jnp.stack([arm[1], arm[0]]) * jnp.asarray(sym.qpos.signs[: info.n_arm], jnp.float32)
    np.testing.assert_allclose(
        np.asarray(sym.ctrl(ctrl)), np.asarray(info.compose_ctrl(arm_m, opening[::-1])), atol=1e-6
    )
    # the documented pad gaps match the geometry, at opening 0, 0.5 and 1
    d = mujoco.MjData(m)
    for o in (0.0, 0.5, 1.0):
        d.qpos[:] = m.key_qpos[0]
        for side in range(2):
            for k, jn in enumerate(info.gripper_joints[side]):
                d.qpos[m.jnt_qposadr[m.joint(jn).id]] = float(info.gripper_ctrl(o)[k])
        mujoco.mj_kinematics(m, d)
        for side in range(2):
            g1, g2 = (m.geom(p).id for p in info.gripper_pads[side])
            ee = m.site(info.ee_sites[side]).id
            ey = d.site_xmat[ee].reshape(3, 3)[:, 1]  # gripper closing axis
            centre_gap = abs(float(np.dot(d.geom_xpos[g1] - d.geom_xpos[g2], ey)))
            gap = centre_gap - m.geom_size[g1][1] - m.geom_size[g2][1]
            assert gap == pytest.approx(float(info.gripper_gap(o)), abs=1e-6)
    assert float(info.opening_for_gap(info.gripper_gap(0.3))) == pytest.approx(0.3, abs=1e-6)
    arm2, grip2 = info.split_qpos(jnp.asarray(m.key_qpos[0]))
    assert arm2.shape == (2, info.n_arm) and grip2.shape == (2, info.n_gripper)


# ----------------------------------------------------------------------------- grasping
_BOX = {"robot_a": (0.30, 0.25, 0.02, 0.030, 0.12), "robot_b": (0.18, 0.17, 0.015, 0.03, 0.07)}


def _grasp_setup(name, sides=("left", "right")):
    """Scene with a 50 g box under the left gripper (and its mirror under the right one),
    the grasp and lift postures from IK, and a control schedule: close 0.5 s, lift 1 s,
    hold 0.5 s."""
    info = robot_info(name)
    bx, by, half, z_grasp, dz = _BOX[name]
    spec = robot_spec(name)
    for side, sy in (("left", by), ("right", -by)):
        if side not in sides:
            continue
        b = spec.worldbody.add_body(name=f"box_{side}", pos=[bx, sy, half])
        b.add_freejoint(name=f"box_{side}")
        b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[half] * 3, mass=0.05, condim=4,
                   friction=[1.0, 0.01, 0.001], rgba=[0.2, 0.8, 0.2, 1], **object_collision())
    m = spec.compile()
    # gripper pointing down, closing along world y
    down = np.stack([[0.0, 0, -1], [0, 1.0, 0], [1.0, 0, 0]], axis=1)
    refl = np.diag(info.ee_local_reflection)
    mir = np.diag([1.0, -1, 1])

    def targets(z):
        rl, rr = down, mir @ down @ refl
        return jnp.asarray(np.stack([
            np.r_[bx, by, z, rl.reshape(9)], np.r_[bx, -by, z, rr.reshape(9)]
        ]), jnp.float32)

    ik = jax.jit(make_ik(m, info, iterations=40))
    home = jnp.asarray(m.key_qpos[0], jnp.float32)
    q_grasp = ik(home, targets(z_grasp))
    q_lift = ik(q_grasp, targets(z_grasp + dz))
    pos, _ = make_ee_fk(m, info)(q_lift)
    assert np.abs(np.asarray(pos[:, 2]) - (z_grasp + dz)).max() < 2e-3  # lift pose reachable

    n_arm, n_g = info.n_arm, info.n_gripper

    def ctrl_of(q, opening):
        arm = jnp.stack([q[:n_arm], q[n_arm + n_g : 2 * n_arm + n_g]])
        return info.compose_ctrl(arm, jnp.array([opening, opening]))

    sched = [ctrl_of(q_grasp, 0.0)] * 25
    sched += [ctrl_of(q_grasp + (k + 1) / 50 * (q_lift - q_grasp), 0.0) for k in range(50)]
    sched += [ctrl_of(q_lift, 0.0)] * 25
    qpos0 = np.array(m.key_qpos[0])
    qpos0[: info.nq_robot] = np.asarray(q_grasp[: info.nq_robot])
    arm_open = np.asarray(info.gripper_ctrl(1.0))
    qpos0[n_arm : n_arm + n_g] = arm_open
    qpos0[2 * n_arm + n_g : 2 * n_arm + 2 * n_g] = arm_open
    bids = [m.body(f"box_{s}").id for s in sides]
    return m, info, qpos0, np.asarray(jnp.stack(sched)), bids, half, dz


@pytest.mark.parametrize("name", NAMES)
def test_grasp_lift_mujoco_c(name):
    """Friction grasp and 10 cm (robot A) / 7 cm (robot B) lift of a 50 g box, MuJoCo C."""
    m, info, qpos0, sched, bids, half, dz = _grasp_setup(name)
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    mujoco.mj_forward(m, d)
    for c in sched:
        d.ctrl[:] = c
        for _ in range(info.substeps):
            mujoco.mj_step(m, d)
    z = d.xpos[bids, 2]
    print(f"\n{name} MuJoCo C: box heights after lift {z.round(4)} (start {half})")
    assert np.all(z > half + dz - 0.02), z
    assert abs(z[0] - z[1]) < 1e-3  # mirrored grasps stay mirrored
    assert abs(d.xpos[bids[0], 1] + d.xpos[bids[1], 1]) < 2e-3


def _mjx_grasp(name):
    # one box (under the left gripper) keeps the compiled contact set, and the compile, small
    m, info, qpos0, sched, bids, half, dz = _grasp_setup(name, sides=("left",))
    mx = mjx.put_model(m, impl="jax")
    dx = mjx.make_data(mx, impl="jax").replace(qpos=jnp.asarray(qpos0, jnp.float32))
    sub = info.substeps

    @jax.jit
    def rollout(dx, sched):
        def ctl(dx, c):
            dx = dx.replace(ctrl=c)
            dx = jax.lax.fori_loop(0, sub, lambda i, d: mjx.step(mx, d), dx)
            return dx, dx.xpos[jnp.asarray(bids)]

        return jax.lax.scan(ctl, dx, sched)

    t0 = time.time()
    _, traj = rollout(dx, jnp.asarray(sched, jnp.float32))
    traj = np.asarray(jax.block_until_ready(traj))
    z = traj[-1, :, 2]
    print(f"\n{name} MJX: box heights after lift {z.round(4)} (start {half}); "
          f"compile + {len(sched) * sub} steps took {time.time() - t0:.1f} s")
    assert np.all(z > half + dz - 0.02), z
    # held during the whole hold phase (no slipping out)
    assert np.all(traj[-25:, :, 2] > half + dz - 0.025)


def test_grasp_lift_mjx_robot_a():
    """The same grasp as in MuJoCo C, in MJX (one compile of a scanned mjx.step)."""
    _mjx_grasp("robot_a")


@pytest.mark.slow
def test_grasp_lift_mjx_robot_b():
    _mjx_grasp("robot_b")


@pytest.mark.parametrize("name", NAMES)
def test_position_servos_track(name):
    """The arm position servos settle a 0.5 rad step within 0.2 s and follow a 0.5 Hz,
    0.3 rad sine (updated every control step) within 0.06 rad (MuJoCo C, gravity on)."""
    m, _ = load_robot(name)
    info = robot_info(name)
    qa = np.concatenate([[m.jnt_qposadr[m.joint(j).id] for j in info.arm_joints[s]] for s in range(2)])
    ca = np.concatenate([[m.actuator(a).id for a in info.arm_actuators[s]] for s in range(2)])
    lo, hi = m.jnt_range[[m.joint(j).id for s in range(2) for j in info.arm_joints[s]]].T
    rng = np.random.default_rng(0)
    d = mujoco.MjData(m)
    for _ in range(3):
        mujoco.mj_resetDataKeyframe(m, d, 0)
        target = np.clip(m.key_qpos[0][qa] + rng.uniform(-0.5, 0.5, len(qa)), lo, hi)
        d.ctrl[ca] = target
        for _ in range(int(round(0.2 / m.opt.timestep))):
            mujoco.mj_step(m, d)
        assert np.abs(d.qpos[qa] - target).max() < 0.02
    mujoco.mj_resetDataKeyframe(m, d, 0)
    worst = 0.0
    for c in range(100):
        target = m.key_qpos[0][qa] + 0.3 * np.sin(np.pi * c * info.control_dt)
        d.ctrl[ca] = target
        for _ in range(info.substeps):
            mujoco.mj_step(m, d)
        if c > 25:
            worst = max(worst, np.abs(d.qpos[qa] - target).max())
    assert worst < 0.06, worst
