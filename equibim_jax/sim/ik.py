"""Pure-JAX damped-least-squares inverse kinematics for the bimanual robots.

Both arms are solved at once (the two arms have the same chain structure, so every array
carries a side axis of size 2 and the system is block-diagonal), with a fixed number of iterations in
``lax.scan``, joint limits enforced by clipping after every step. Everything is pure and
works under ``jit`` and ``vmap``.

Forward kinematics has two backends that give the same numbers:

* ``"chain"`` (default): forward kinematics of the two serial arm chains only, built from
  the model's body/joint/site constants (the same transforms as ``mjx.kinematics``, as
  rotation matrices: per joint ``C0 + sin(t) C1 + (1 - cos(t)) C2``). Task objects and
  fingers are not touched, so its cost does not grow with the scene.
* ``"mjx"``: ``mujoco.mjx.kinematics`` (impl ``jax``) on the whole model. The tests check
  that both backends agree with MuJoCo's ``mj_kinematics`` to float32 precision.

The Jacobian is the analytic one of a chain of hinges (and slides):
``J_p[:, j] = a_j x (p - anchor_j)``, ``J_w[:, j] = a_j`` with world-frame joint axes
``a_j`` and anchors from the forward pass.

Targets
-------
``targets`` is ``[2, D]`` (row 0 the left arm, row 1 the right arm; any leading batch dims
are handled by ``vmap``), with ``D``:

* 3: position only (orientation free);
* 7: position + quaternion ``(w, x, y, z)``;
* 9: position + 6D rotation ``[column 0, column 1]`` of the rotation matrix;
* 12: position + the rotation matrix flattened row-major.

The position is the end-effector site's (the grasp centre); the orientation is the site
frame's (for both robots the site frame is the gripper frame: x = approach direction,
y = the closing direction of the jaws, z = x cross y).

Robot B's arms have 5 joints, so a general 6D pose is not reachable: the solve then
returns the damped least-squares compromise (use ``rot_weight`` to trade orientation for
position). Poses produced by forward kinematics are of course reachable.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from equibim_jax.sim._linalg import cho_factor, cho_solve
from equibim_jax.sim.robots import RobotInfo

__all__ = [
    "ArmChains",
    "make_arm_chains",
    "make_ee_fk",
    "make_ik",
    "targets_to_pos_mat",
    "pose_errors",
    "quat_to_mat",
    "mat_to_quat",
    "rot6d_to_mat",
    "mat_to_rot6d",
]

_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)


# ------------------------------------------------------------------ rotation utils
def quat_to_mat(q: jax.Array) -> jax.Array:
    """Unit quaternion (w, x, y, z) [..., 4] -> rotation matrix [..., 3, 3] (normalised first)."""
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = jnp.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return r.reshape(q.shape[:-1] + (3, 3))


def mat_to_quat(r: jax.Array) -> jax.Array:
    """Rotation matrix [..., 3, 3] -> quaternion (w, x, y, z) [..., 4] with w >= 0."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    tr = m00 + m11 + m22
    # four candidate solutions; pick the numerically largest denominator
    cand = jnp.stack(
        [
            jnp.stack([1 + tr, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                       r[..., 1, 0] - r[..., 0, 1]], -1),
            jnp.stack([r[..., 2, 1] - r[..., 1, 2], 1 + m00 - m11 - m22,
                       r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0]], -1),
            jnp.stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0],
                       1 - m00 + m11 - m22, r[..., 1, 2] + r[..., 2, 1]], -1),
            jnp.stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0],
                       r[..., 1, 2] + r[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # [..., 4, 4]
    diag = jnp.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = jnp.argmax(diag, axis=-1)
    q = jnp.take_along_axis(cand, k[..., None, None], axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return q * jnp.where(q[..., :1] < 0, -1.0, 1.0)


def rot6d_to_mat(r6: jax.Array) -> jax.Array:
    """6D rotation ``[c0, c1]`` [..., 6] -> rotation matrix [..., 3, 3] (Gram-Schmidt)."""
    a, b = r6[..., :3], r6[..., 3:6]
    c0 = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
    b = b - jnp.sum(c0 * b, axis=-1, keepdims=True) * c0
    c1 = b / jnp.linalg.norm(b, axis=-1, keepdims=True)
    return jnp.stack([c0, c1, jnp.cross(c0, c1)], axis=-1)


def mat_to_rot6d(r: jax.Array) -> jax.Array:
    """Rotation matrix [..., 3, 3] -> 6D ``[column 0, column 1]`` [..., 6]."""
    return jnp.concatenate([r[..., :, 0], r[..., :, 1]], axis=-1)


def _rot_log(r: jax.Array) -> jax.Array:
    """Rotation vector (axis * angle) of a rotation matrix [..., 3, 3] -> [..., 3]."""
    v = 0.5 * jnp.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1
    )
    s = jnp.linalg.norm(v, axis=-1, keepdims=True)  # sin(angle)
    c = 0.5 * (jnp.trace(r, axis1=-2, axis2=-1)[..., None] - 1.0)  # cos(angle)
    angle = jnp.arctan2(s, c)
    safe_s = jnp.where(s > 1e-9, s, 1.0)
    factor = jnp.where(s > 1e-9, angle / safe_s, 1.0)
    w = v * factor
    # near a half-turn v vanishes; take the axis from (R + R^T) / 2 - cos I = (1 - cos) a a^T
    b = 0.5 * (r + jnp.swapaxes(r, -1, -2)) - c[..., None] * jnp.eye(3, dtype=r.dtype)
    diag = jnp.diagonal(b, axis1=-2, axis2=-1)
    k = jnp.argmax(diag, axis=-1)
    col = jnp.take_along_axis(b, k[..., None, None], axis=-1)[..., 0]
    axis = col / jnp.maximum(jnp.linalg.norm(col, axis=-1, keepdims=True), 1e-12)
    axis = axis * jnp.where(jnp.sum(axis * v, -1, keepdims=True) < 0, -1.0, 1.0)
    near_pi = (c < -0.99) & (s < 1e-3)
    return jnp.where(near_pi, axis * angle, w)


def targets_to_pos_mat(targets: jax.Array) -> tuple[jax.Array, jax.Array | None]:
    """Split targets ``[..., D]`` into position [..., 3] and rotation matrix [..., 3, 3].

    ``D`` = 3 (no rotation: returns None), 7 (quaternion), 9 (6D), 12 (matrix row-major).
    """
    d = targets.shape[-1]
    pos = targets[..., :3]
    if d == 3:
        return pos, None
    if d == 7:
        return pos, quat_to_mat(targets[..., 3:7])
    if d == 9:
        return pos, rot6d_to_mat(targets[..., 3:9])
    if d == 12:
        return pos, targets[..., 3:12].reshape(targets.shape[:-1] + (3, 3))
    raise ValueError(f"targets must have last dim 3, 7, 9 or 12; got shape {targets.shape}")


# ------------------------------------------------------------------ chain extraction
@dataclasses.dataclass(frozen=True, eq=False)
class ArmChains:
    """Constants of the two arm chains (stacked over side), as numpy arrays.

    Attributes:
      qadr: int [2, n] qpos addresses of the arm joints, base to tip.
      jtype: int [n] joint types (same for both sides).
      body_pos, body_quat: [2, n, 3] / [2, n, 4] local frames of the body holding each joint
        (every chain body holds exactly one arm joint).
      jnt_pos, jnt_axis: [2, n, 3] joint anchor/axis in the body frame.
      qpos0: [2, n] reference positions.
      root_pos, root_mat: [2, 3] / [2, 3, 3] world frame of the first joint body's parent.
      site_pos, site_quat: [2, 3] / [2, 4] ee site in the last body's frame.
      lo, hi: [2, n] joint limits (+-inf for unlimited joints).
      site_ids, body_ids: [2] / [2, n] model ids (for the mjx backend).
    """

    qadr: np.ndarray
    jtype: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray
    jnt_pos: np.ndarray
    jnt_axis: np.ndarray
    qpos0: np.ndarray
    root_pos: np.ndarray
    root_mat: np.ndarray
    site_pos: np.ndarray
    site_quat: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    site_ids: np.ndarray
    body_ids: np.ndarray
    jnt_ids: np.ndarray

    @property
    def n(self) -> int:
        return int(self.qadr.shape[1])


def _host_model(model) -> mujoco.MjModel:
    if isinstance(model, mujoco.MjModel):
        return model
    raise TypeError(
        "make_arm_chains needs the host mujoco.MjModel (names and constants); "
        f"got {type(model).__name__}. Pass the MjModel (make_ik also accepts an mjx.Model "
        "together with host_model=...)."
    )


def make_arm_chains(model: mujoco.MjModel, info: RobotInfo) -> ArmChains:
    """Extract the two arm chains (base to ee site) of ``info`` from ``model``."""
    model = _host_model(model)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)  # at qpos0, for the fixed root frames

    fields = {k: [] for k in ArmChains.__dataclass_fields__}
    jtypes = None
    for side in range(2):
        site = model.site(info.ee_sites[side])
        jids = [model.joint(n).id for n in info.arm_joints[side]]
        bodies = [int(model.jnt_bodyid[j]) for j in jids]
        if len(set(bodies)) != len(bodies):
            raise ValueError(f"{info.name}: two arm joints share a body; chain IK needs one per body")
        # the chain must be contiguous: each joint body is the parent of the next, and the
        # ee site hangs on the last one
        for a, b in zip(bodies[:-1], bodies[1:]):
            if int(model.body_parentid[b]) != a:
                raise ValueError(
                    f"{info.name}: body {model.body(b).name} is not a child of {model.body(a).name}"
                )
        if int(model.site_bodyid[site.id]) != bodies[-1]:
            raise ValueError(f"{info.name}: ee site {site.name} is not on the last arm body")
        root = int(model.body_parentid[bodies[0]])
        # nothing above the chain may move
        b = root
        while b != 0:
            if model.body_jntnum[b] != 0 or model.body_mocapid[b] >= 0:
                raise ValueError(f"{info.name}: body {model.body(b).name} above the arm moves")
            b = int(model.body_parentid[b])
        for j in jids:
            if int(model.jnt_type[j]) not in (_HINGE, _SLIDE):
                raise ValueError(f"{info.name}: arm joint {model.joint(j).name} is not hinge/slide")
        types = np.asarray([int(model.jnt_type[j]) for j in jids])
        if jtypes is None:
            jtypes = types
        elif not np.array_equal(jtypes, types):
            raise ValueError(f"{info.name}: left and right arm chains differ in joint types")
        lim = model.jnt_limited[jids].astype(bool)
        rng = model.jnt_range[jids]
        fields["qadr"].append(model.jnt_qposadr[jids])
        fields["body_pos"].append(model.body_pos[bodies])
        fields["body_quat"].append(model.body_quat[bodies])
        fields["jnt_pos"].append(model.jnt_pos[jids])
        fields["jnt_axis"].append(model.jnt_axis[jids])
        fields["qpos0"].append(model.qpos0[model.jnt_qposadr[jids]])
        fields["root_pos"].append(data.xpos[root])
        fields["root_mat"].append(data.xmat[root].reshape(3, 3))
        fields["site_pos"].append(model.site_pos[site.id])
        fields["site_quat"].append(model.site_quat[site.id])
        fields["lo"].append(np.where(lim, rng[:, 0], -np.inf))
        fields["hi"].append(np.where(lim, rng[:, 1], np.inf))
        fields["site_ids"].append(site.id)
        fields["body_ids"].append(bodies)
        fields["jnt_ids"].append(jids)
    out = {k: np.asarray(v) for k, v in fields.items() if k != "jtype"}
    out["qadr"] = out["qadr"].astype(np.int32)
    return ArmChains(jtype=jtypes, **out)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _quat2mat_np(q: np.ndarray) -> np.ndarray:
    r = np.zeros(9)
    mujoco.mju_quat2Mat(r, np.asarray(q, dtype=np.float64))
    return r.reshape(3, 3)


def _chain_tables(ch: ArmChains) -> dict[str, np.ndarray]:
    """Constant tables for the chain FK, per side and joint.

    Body ``i`` relative to its parent, with joint value ``t = q - qpos0``:
    rotation ``C0 + sin(t) C1 + (1 - cos(t)) C2`` and translation
    ``T0 + sin(t) T1 + (1 - cos(t)) T2 + t T3`` (Rodrigues for hinges, T3 for slides).
    """
    n = ch.n
    c0, c1, c2 = (np.zeros((2, n, 3, 3)) for _ in range(3))
    t0, t1, t2, t3 = (np.zeros((2, n, 3)) for _ in range(4))
    ax_local = np.zeros((2, n, 3))  # joint axis in the parent frame
    an_local = np.zeros((2, n, 3))  # joint anchor in the parent frame
    for s in range(2):
        for i in range(n):
            rb = _quat2mat_np(ch.body_quat[s, i])
            a = ch.jnt_axis[s, i] / np.linalg.norm(ch.jnt_axis[s, i])
            jp = ch.jnt_pos[s, i]
            ax_local[s, i] = rb @ a
            an_local[s, i] = ch.body_pos[s, i] + rb @ jp
            if ch.jtype[i] == _HINGE:
                k = _skew(a)
                c0[s, i], c1[s, i], c2[s, i] = rb, rb @ k, rb @ k @ k
                # pos = anchor - R jp, R = rb (I + s K + (1 - c) K^2)
                t0[s, i] = ch.body_pos[s, i]
                t1[s, i] = -(rb @ k @ jp)
                t2[s, i] = -(rb @ k @ k @ jp)
            else:
                c0[s, i] = rb
                t0[s, i] = ch.body_pos[s, i]
                t3[s, i] = rb @ a
    site_r = np.stack([_quat2mat_np(ch.site_quat[s]) for s in range(2)])
    return dict(c0=c0, c1=c1, c2=c2, t0=t0, t1=t1, t2=t2, t3=t3, ax_local=ax_local,
                an_local=an_local, root_pos=ch.root_pos, root_mat=ch.root_mat,
                site_pos=ch.site_pos, site_mat=site_r, qpos0=ch.qpos0,
                slide=np.asarray(ch.jtype == _SLIDE, np.float64))


def _mm(a, b):
    return jnp.matmul(a, b)


def _mv(a, v):
    return jnp.matmul(a, v[..., None])[..., 0]


def _chain_fk(tab: dict, q: jax.Array):
    """FK of both chains at once. ``q``: [2, n] arm joint positions.

    Returns site pos [2, 3], site mat [2, 3, 3], joint anchors [2, n, 3] and world joint
    axes [2, n, 3].
    """
    t = q - tab["qpos0"]
    sn, cs = jnp.sin(t)[..., None], (1.0 - jnp.cos(t))[..., None]
    hinge = 1.0 - tab["slide"]
    sn_h, cs_h = sn * hinge[:, None], cs * hinge[:, None]
    rot = tab["c0"] + sn_h[..., None] * tab["c1"] + cs_h[..., None] * tab["c2"]  # [2,n,3,3]
    tr = tab["t0"] + sn_h * tab["t1"] + cs_h * tab["t2"] + (t * tab["slide"])[..., None] * tab["t3"]
    pos, mat = tab["root_pos"], tab["root_mat"]
    ppos, pmat = [], []
    n = q.shape[-1]
    for i in range(n):
        ppos.append(pos)
        pmat.append(mat)
        pos = pos + _mv(mat, tr[:, i])
        mat = _mm(mat, rot[:, i])
    ppos, pmat = jnp.stack(ppos, 1), jnp.stack(pmat, 1)  # parent frames [2, n, ...]
    anchors = ppos + _mv(pmat, tab["an_local"])
    axes = _mv(pmat, tab["ax_local"])
    site_pos = pos + _mv(mat, tab["site_pos"])
    site_mat = _mm(mat, tab["site_mat"])
    return site_pos, site_mat, anchors, axes


def _make_side_fk(model, info: RobotInfo, backend: str, mjx_model=None):
    """Returns (chains, fk_sides) with fk_sides(qpos [nq]) -> (pos [2,3], mat [2,3,3],
    anchors [2,n,3], axes [2,n,3])."""
    ch = make_arm_chains(model, info)
    qadr = jnp.asarray(ch.qadr)

    if backend == "chain":
        tables = _chain_tables(ch)

        def fk_sides(qpos):
            tab = {k: jnp.asarray(v, qpos.dtype) for k, v in tables.items()}
            return _chain_fk(tab, qpos[qadr])

    elif backend == "mjx":
        mm = mjx_model if mjx_model is not None else mjx.put_model(model, impl="jax",
                                                                    device=jax.local_devices()[0])
        site_ids = jnp.asarray(ch.site_ids)
        jnt_ids = jnp.asarray(ch.jnt_ids)

        def fk_sides(qpos):
            d = mjx.make_data(mm, impl="jax")
            d = d.replace(qpos=qpos.astype(d.qpos.dtype))
            d = mjx.kinematics(mm, d)
            pos = d.site_xpos[site_ids]
            mat = d.site_xmat[site_ids]
            return pos, mat, d.xanchor[jnt_ids], d.xaxis[jnt_ids]

    else:
        raise ValueError(f"backend must be 'chain' or 'mjx', got {backend!r}")
    return ch, fk_sides


def make_ee_fk(model, info: RobotInfo, backend: str = "chain", mjx_model=None):
    """End-effector forward kinematics ``fk(qpos [nq]) -> (pos [2, 3], mat [2, 3, 3])``.

    Row 0 is the left arm's ee site, row 1 the right arm's. Pure; jit/vmap-able.
    ``model`` is the host ``mujoco.MjModel``.
    """
    _, fk_sides = _make_side_fk(model, info, backend, mjx_model)

    def fk(qpos):
        qpos = jnp.asarray(qpos)
        if not jnp.issubdtype(qpos.dtype, jnp.floating):
            qpos = qpos.astype(jnp.float32)
        pos, mat, _, _ = fk_sides(qpos)
        return pos, mat

    return fk


def pose_errors(pos, mat, targets) -> tuple[jax.Array, jax.Array]:
    """Position error (m) and rotation error (rad) of ee poses against ``targets``.

    ``pos`` [..., 3], ``mat`` [..., 3, 3], ``targets`` [..., D] (see module doc).
    Returns ([...], [...]); the rotation error is 0 for position-only targets.
    """
    tpos, tmat = targets_to_pos_mat(jnp.asarray(targets))
    perr = jnp.linalg.norm(tpos - pos, axis=-1)
    if tmat is None:
        return perr, jnp.zeros_like(perr)
    rerr = jnp.linalg.norm(_rot_log(tmat @ jnp.swapaxes(mat, -1, -2)), axis=-1)
    return perr, rerr


def make_ik(
    model,
    info: RobotInfo,
    iterations: int = 25,
    damping: float = 0.02,
    rot_weight: float = 0.3,
    max_step: float = 1.0,
    backend: str = "chain",
    host_model: mujoco.MjModel | None = None,
) -> Callable[..., jax.Array]:
    """Damped-least-squares IK for both arms at once.

    Args:
      model: the host ``mujoco.MjModel`` (robot plus any task objects), or an ``mjx.Model``
        together with ``host_model`` (the names and chain constants are read on the host).
      info: the robot's :class:`~equibim_jax.sim.robots.RobotInfo`.
      iterations: fixed number of DLS iterations (``lax.scan``).
      damping: ``lambda`` in ``dq = J^T (J J^T + lambda^2 I)^-1 e`` (per arm, 6x6 solve).
      rot_weight: metres per radian: orientation error rows are scaled by this, so
        ``rot_weight = 0.3`` weighs 1 rad like 0.3 m. Equal for both arms (equivariant).
      max_step: the joint update per iteration is scaled down to at most this norm (rad).
      backend: ``"chain"`` (fast, default) or ``"mjx"`` (``mjx.kinematics``).

    Returns:
      ``ik(q_init, targets, active=None) -> qpos``: ``q_init`` [nq] full qpos (only the arm
      joints change; grippers and objects are copied through), ``targets`` [2, D] per-arm
      ee target (row 0 left, row 1 right; D in {3, 7, 9, 12}), ``active`` optional bool [2]
      (an inactive arm keeps its ``q_init``). Output [nq], joint limits respected.
      Pure; ``jit`` and ``vmap`` it freely.
    """
    mjx_model = None
    if not isinstance(model, mujoco.MjModel):
        if host_model is None:
            raise TypeError("make_ik with an mjx.Model needs host_model=<mujoco.MjModel>")
        mjx_model, model = model, host_model
    ch, fk_sides = _make_side_fk(model, info, backend, mjx_model)
    qadr = jnp.asarray(ch.qadr)
    jtype = jnp.asarray(ch.jtype)
    is_hinge = (jtype == _HINGE)[:, None]  # [n, 1]
    n = ch.n
    lam2 = float(damping) ** 2
    w_rot = float(rot_weight)

    def jac_and_err(q_full, tpos, tmat):
        pos, mat, anchors, axes = fk_sides(q_full)  # [2,3], [2,3,3], [2,n,3], [2,n,3]
        lin = jnp.where(is_hinge[None], jnp.cross(axes, pos[:, None, :] - anchors), axes)
        ang = jnp.where(is_hinge[None], axes, 0.0)
        e_p = tpos - pos  # [2, 3]
        if tmat is None:
            jac = jnp.swapaxes(lin, -1, -2)  # [2, 3, n]
            err = e_p
        else:
            e_r = _rot_log(tmat @ jnp.swapaxes(mat, -1, -2))  # [2, 3]
            jac = jnp.concatenate([jnp.swapaxes(lin, -1, -2), w_rot * jnp.swapaxes(ang, -1, -2)], -2)
            err = jnp.concatenate([e_p, w_rot * e_r], -1)  # [2, 6]
        return jac, err

    def ik(q_init, targets, active=None):
        q_init = jnp.asarray(q_init)
        if not jnp.issubdtype(q_init.dtype, jnp.floating):
            q_init = q_init.astype(jnp.float32)
        dtype = q_init.dtype
        targets = jnp.asarray(targets, dtype)
        if targets.ndim != 2 or targets.shape[0] != 2:
            raise ValueError(f"targets must be [2, D] (left, right); got {targets.shape}")
        tpos, tmat = targets_to_pos_mat(targets)
        lo = jnp.asarray(ch.lo, dtype)
        hi = jnp.asarray(ch.hi, dtype)
        mask = jnp.ones((2,), bool) if active is None else jnp.asarray(active, bool)

        def body(q_full, _):
            jac, err = jac_and_err(q_full, tpos, tmat)  # [2, m, n], [2, m]
            m = jac.shape[-2]
            jjt = jac @ jnp.swapaxes(jac, -1, -2) + lam2 * jnp.eye(m, dtype=dtype)
            # per arm, in plain JAX (no batched LAPACK call under vmap; sim/_linalg.py)
            y = jax.vmap(lambda a, e: cho_solve(cho_factor(a, lower=True), e))(jjt, err)
            dq = jnp.einsum("smn,sm->sn", jac, y)
            norm = jnp.linalg.norm(dq, axis=-1, keepdims=True)
            dq = dq * jnp.minimum(1.0, max_step / jnp.maximum(norm, 1e-12))
            dq = jnp.where(mask[:, None], dq, 0.0)
            q_arm = jnp.clip(q_full[qadr] + dq, lo, hi)
            return q_full.at[qadr].set(q_arm), None

        q, _ = jax.lax.scan(body, q_init, None, length=iterations)
        return q

    ik.chains = ch  # type: ignore[attr-defined]
    ik.n_arm = n  # type: ignore[attr-defined]
    return ik
