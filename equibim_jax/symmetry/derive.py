"""Derive the mirror symmetry of a MuJoCo model, and verify it on forward kinematics.

``derive_symmetry(model, mirror)`` matches every body to its mirror image, every joint to
its mirror joint (hinge signs as axial vectors, slide signs as polar vectors), every geom,
site and camera, and builds the maps for ``qpos``, ``qvel`` and ``ctrl``. Free and ball
joints of objects map their position as a point and their orientation by ``M R L``, with
``L`` the body's own local reflection found from its geoms. Nothing is typed in by hand,
and a model that is not mirror-symmetric within ``tol`` raises :class:`SymmetryError`
naming what does not match.

Matching runs in body-tree order at the model's reference posture ``qpos0`` (which must be
mirror-symmetric), and ambiguous candidates (e.g. two fingers that coincide at q = 0) are
resolved by comparing them at random postures. The whole map is then checked by
:func:`verify_symmetry` at random configurations inside the joint ranges.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from equibim_jax.symmetry.mirror import Mirror, axis_reflection
from equibim_jax.symmetry.structure import JointMap

_FREE, _BALL, _SLIDE, _HINGE = (
    int(mujoco.mjtJoint.mjJNT_FREE),
    int(mujoco.mjtJoint.mjJNT_BALL),
    int(mujoco.mjtJoint.mjJNT_SLIDE),
    int(mujoco.mjtJoint.mjJNT_HINGE),
)
_JNT_NAMES = {_FREE: "free", _BALL: "ball", _SLIDE: "slide", _HINGE: "hinge"}
_GEOM = mujoco.mjtGeom
# Geom types whose shape is invariant under any rotation about the local z axis.
_AXISYM = {int(_GEOM.mjGEOM_CAPSULE), int(_GEOM.mjGEOM_CYLINDER)}
_SPHERE = int(_GEOM.mjGEOM_SPHERE)

DEFAULT_TOL = 5e-4
"""Default tolerance: 0.5 mm of forward-kinematics residual (orientations count as the
displacement of a point 1 m from the body origin). It accepts rounded constants such as
pi written as 3.1416 (~1e-5 m at arm scale) and refuses a link 1 mm off."""


class SymmetryError(ValueError):
    """The model is not mirror-symmetric about the given plane within the tolerance."""


def _name(model, obj, i) -> str:
    n = mujoco.mj_id2name(model, obj, i)
    return n if n else f"#{i}"


def _body_name(model, b):
    return "world" if b == 0 else _name(model, mujoco.mjtObj.mjOBJ_BODY, b)


def _joint_name(model, j):
    return _name(model, mujoco.mjtObj.mjOBJ_JOINT, j)


def _mat2quat(r: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(r, dtype=np.float64).reshape(9))
    return q


def _quat_lr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Matrix of ``q -> a * q * b`` (Hamilton, w-first), [4, 4]."""
    w, x, y, z = a
    la = np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])
    w, x, y, z = b
    rb = np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])
    return la @ rb


def _signed_perm(a: np.ndarray, what: str, atol=1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Decompose a matrix that must be a signed permutation into (perm, signs)."""
    n = a.shape[0]
    perm = np.argmax(np.abs(a), axis=1)
    signs = np.sign(a[np.arange(n), perm])
    rebuilt = np.zeros_like(a)
    rebuilt[np.arange(n), perm] = signs
    if not np.allclose(rebuilt, a, atol=atol) or sorted(perm.tolist()) != list(range(n)):
        raise SymmetryError(
            f"{what}: its mirror map is not a signed permutation (an oblique mirror plane or "
            "local reflection); JointMap needs an axis-aligned one.\n" + np.array2string(a, precision=3)
        )
    return perm, signs


def _is_primitive_symmetry(q: np.ndarray, gtype: int, tol: float) -> bool:
    """Whether the orthogonal map ``q`` (geom frame -> mirror geom frame) preserves the shape."""
    if gtype == _SPHERE:
        return True
    if gtype in _AXISYM:
        return abs(abs(q[2, 2]) - 1.0) < tol
    return bool(np.all(np.abs(np.abs(q) - np.round(np.abs(q))) < tol))


@dataclasses.dataclass(frozen=True, eq=False)
class ModelSymmetry:
    """The mirror symmetry of one model.

    Attributes:
      mirror: the plane.
      qpos: JointMap [nq]; qvel: JointMap [nv] (a linear map, no offsets);
      ctrl: JointMap [nu].
      bodies: int [nbody], the mirror body of each body. joints: int [njnt].
      joint_signs: float [njnt], +1/-1 for hinge and slide joints, 0 for free and ball.
      geoms: int [ngeom]; sites: int [nsite]; cameras: int [ncam] (-1: no mirror camera).
      body_local: float [nbody, 3, 3], each body's local reflection ``L`` with
        ``R_{bodies[b]} = M R_b L_b``.
      site_local: float [nsite, 3, 3], the same for sites.
      residual: the forward-kinematics residual found by :func:`verify_symmetry` (m).
    """

    mirror: Mirror
    qpos: JointMap
    qvel: JointMap
    ctrl: JointMap
    bodies: np.ndarray
    joints: np.ndarray
    joint_signs: np.ndarray
    geoms: np.ndarray
    sites: np.ndarray
    cameras: np.ndarray
    body_local: np.ndarray
    site_local: np.ndarray
    residual: float
    body_names: tuple[str, ...]
    joint_names: tuple[str, ...]

    def describe(self) -> str:
        """A table of joint pairs with their signs and offsets."""
        lines = [f"{'joint':>20s}   {'mirror joint':<20s}  sign   offset"]
        for j, jm in enumerate(self.joints):
            s = float(self.joint_signs[j])
            sign = {1.0: "+1", -1.0: "-1"}.get(s, "MRL")
            adr = None
            off = ""
            if s != 0.0 and self.qpos.names is not None:
                adr = self.qpos.names.index(self.joint_names[jm]) if self.joint_names[jm] in self.qpos.names else None
                off = f"{self.qpos.offsets[adr]:+.4f}" if adr is not None else ""
            lines.append(f"{self.joint_names[j]:>20s} ↔ {self.joint_names[jm]:<20s} {sign:>5s}  {off}")
        return "\n".join(lines)


@dataclasses.dataclass
class _Kin:
    xpos: np.ndarray
    xmat: np.ndarray
    xipos: np.ndarray
    xaxis: np.ndarray
    xanchor: np.ndarray
    geom_xpos: np.ndarray
    geom_xmat: np.ndarray
    site_xpos: np.ndarray
    site_xmat: np.ndarray
    cam_xpos: np.ndarray
    cam_xmat: np.ndarray


def _fk(model, data, q) -> _Kin:
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_camlight(model, data)  # camera poses are not part of mj_kinematics
    return _Kin(
        data.xpos.copy(),
        data.xmat.reshape(-1, 3, 3).copy(),
        data.xipos.copy(),
        data.xaxis.copy(),
        data.xanchor.copy(),
        data.geom_xpos.copy(),
        data.geom_xmat.reshape(-1, 3, 3).copy(),
        data.site_xpos.copy(),
        data.site_xmat.reshape(-1, 3, 3).copy(),
        data.cam_xpos.copy(),
        data.cam_xmat.reshape(-1, 3, 3).copy(),
    )


class _Deriver:
    def __init__(self, model: mujoco.MjModel, mirror: Mirror, tol: float, seed: int):
        self.m = model
        self.mirror = mirror
        self.M = mirror.matrix
        self.tol = tol
        self.rng = np.random.default_rng(seed)
        self.data = mujoco.MjData(model)
        self.errors: list[str] = []
        m = model
        self.body_jnts = [
            list(range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])) if m.body_jntnum[b] else []
            for b in range(m.nbody)
        ]
        self.body_geoms = [[g for g in range(m.ngeom) if m.geom_bodyid[g] == b] for b in range(m.nbody)]

    # -- helpers -----------------------------------------------------------------------
    def mp(self, p):
        p0 = np.asarray(self.mirror.point)
        return p0 + (np.asarray(p) - p0) @ self.M.T

    def is_free_root(self, b) -> bool:
        js = self.body_jnts[b]
        return len(js) > 0 and self.m.jnt_type[js[0]] == _FREE

    def random_joint_value(self, j) -> np.ndarray:
        m = self.m
        t = m.jnt_type[j]
        if t in (_HINGE, _SLIDE):
            if m.jnt_limited[j]:
                lo, hi = m.jnt_range[j]
            else:
                lo, hi = (-np.pi, np.pi) if t == _HINGE else (-0.1, 0.1)
            return np.array([self.rng.uniform(lo, hi)])
        q = self.rng.normal(size=4)
        q /= np.linalg.norm(q)
        if t == _BALL:
            return q
        adr = m.jnt_qposadr[j]
        pos = m.qpos0[adr : adr + 3] + self.rng.uniform(-0.2, 0.2, size=3)
        return np.concatenate([pos, q])

    # -- local reflection of a free body from its own geoms ------------------------------
    def free_body_local(self, b, kin0) -> np.ndarray | None:
        """The local reflection L under which the body's geoms map onto themselves."""
        r = kin0.xmat[b]
        cands = [r.T @ self.M @ r] + [axis_reflection(i) for i in range(3)]
        m = self.m
        for loc in cands:
            loc = np.where(np.abs(loc) < 1e-9, 0.0, loc)
            if not np.allclose(loc, loc.T, atol=1e-9):
                continue
            ok = True
            for g in self.body_geoms[b]:
                pg = loc @ m.geom_pos[g]
                rg = np.zeros(9)
                mujoco.mju_quat2Mat(rg, m.geom_quat[g])
                rg = rg.reshape(3, 3)
                found = False
                for g2 in self.body_geoms[b]:
                    if m.geom_type[g2] != m.geom_type[g] or not np.allclose(
                        m.geom_size[g2], m.geom_size[g], atol=self.tol
                    ):
                        continue
                    if np.linalg.norm(m.geom_pos[g2] - pg) > self.tol:
                        continue
                    rg2 = np.zeros(9)
                    mujoco.mju_quat2Mat(rg2, m.geom_quat[g2])
                    if _is_primitive_symmetry(rg2.reshape(3, 3).T @ loc @ rg, m.geom_type[g], self.tol):
                        found = True
                        break
                if not found:
                    ok = False
                    break
            if ok and np.linalg.norm(loc @ m.body_ipos[b] - m.body_ipos[b]) <= self.tol:
                return loc
        return None

    def rot_map(self, k_left: np.ndarray, l_right: np.ndarray, what: str):
        """(perm, signs) of the quaternion map matching ``R -> K R L`` (both improper)."""
        kq = _mat2quat(-k_left)
        lq = _mat2quat(-l_right)
        a = _quat_lr(kq, lq)
        if not np.allclose(a @ a, np.eye(4), atol=1e-6):
            a = -a
        return _signed_perm(a, what)

    # -- main ----------------------------------------------------------------------------
    def run(self) -> ModelSymmetry:
        m = self.m
        nb = m.nbody
        kin0 = _fk(m, self.data, m.qpos0)
        bodies = -np.ones(nb, dtype=np.int64)
        bodies[0] = 0
        body_local = np.zeros((nb, 3, 3))
        body_local[0] = self.M
        joints = -np.ones(m.njnt, dtype=np.int64)
        jsigns = np.zeros(m.njnt)
        joffs = np.zeros(m.njnt)

        # Free bodies map to themselves; their pose is mirrored with their own L.
        q_b = m.qpos0.copy()
        for b in range(1, nb):
            if not self.is_free_root(b):
                continue
            loc = self.free_body_local(b, kin0)
            if loc is None:
                self.errors.append(
                    f"free body '{_body_name(m, b)}': its geoms are not symmetric under any "
                    "local reflection, so its mirror image is not the same object"
                )
                continue
            bodies[b], body_local[b] = b, loc
            j = self.body_jnts[b][0]
            joints[j] = j
            adr = m.jnt_qposadr[j]
            q_b[adr : adr + 3] = self.mp(m.qpos0[adr : adr + 3])
            q_b[adr + 3 : adr + 7] = _mat2quat(self.M @ kin0.xmat[b] @ loc)
        kin_b = _fk(m, self.data, q_b)
        self.kin0, self.kin_b = kin0, kin_b

        for b in range(1, nb):
            if bodies[b] >= 0:
                continue
            pb = bodies[m.body_parentid[b]]
            if pb < 0:
                self.errors.append(f"body '{_body_name(m, b)}': its parent has no mirror")
                continue
            best = None
            cands = []
            for c in range(1, nb):
                if m.body_parentid[c] != pb or self.is_free_root(c):
                    continue
                if [m.jnt_type[j] for j in self.body_jnts[c]] != [m.jnt_type[j] for j in self.body_jnts[b]]:
                    continue
                res, info = self.candidate(b, c, kin0, kin_b, q_b)
                cands.append((res, c, info))
            if not cands:
                self.errors.append(
                    f"body '{_body_name(m, b)}' (joints {self._jn(b)}): no body under the mirror "
                    f"of its parent has the same joint types"
                )
                continue
            cands.sort(key=lambda t: t[0])
            close = [t for t in cands if t[0] <= self.tol]
            if len(close) > 1:
                # Ambiguous at the reference posture: compare at random postures.
                close = sorted(
                    ((self.random_residual(b, c, info, q_b), c, info) for _, c, info in close),
                    key=lambda t: t[0],
                )
            best = close[0] if close else cands[0]
            res, c, info = best
            if res > self.tol:
                self.errors.append(
                    f"body '{_body_name(m, b)}' (joints {self._jn(b)}): nearest mirror candidate "
                    f"'{_body_name(m, c)}' has residual {res:.3g} ({info['why']})"
                )
                continue
            bodies[b] = c
            body_local[b] = kin0.xmat[b].T @ self.M @ kin_b.xmat[c]
            for (j, j2, s, off) in info["pairs"]:
                joints[j], jsigns[j], joffs[j] = j2, s, off

        for b in range(nb):
            if bodies[b] >= 0 and bodies[bodies[b]] != b:
                self.errors.append(
                    f"body '{_body_name(m, b)}' maps to '{_body_name(m, bodies[b])}', which maps to "
                    f"'{_body_name(m, bodies[bodies[b]])}': the map is not an involution"
                )
        if self.errors:
            raise SymmetryError(self._msg())

        geoms = self.match_elements(
            "geom", m.ngeom, m.geom_bodyid, kin0.geom_xpos, kin_b.geom_xpos,
            kin0.geom_xmat, kin_b.geom_xmat, bodies,
            same=lambda g, g2: m.geom_type[g] == m.geom_type[g2]
            and np.allclose(m.geom_size[g], m.geom_size[g2], atol=self.tol)
            and np.allclose(self.geom_color(g), self.geom_color(g2), atol=1e-6),
            shape_ok=lambda g, q: _is_primitive_symmetry(q, m.geom_type[g], self.tol),
        )
        sites = self.match_elements(
            "site", m.nsite, m.site_bodyid, kin0.site_xpos, kin_b.site_xpos,
            kin0.site_xmat, kin_b.site_xmat, bodies,
            same=lambda a, b2: True, shape_ok=lambda a, q: True,
        )
        # Cameras do not touch physics: one without a mirror maps to -1 instead of failing;
        # code that needs image symmetry checks its camera (see Env).
        n_err = len(self.errors)
        cams = self.match_elements(
            "camera", m.ncam, m.cam_bodyid, kin0.cam_xpos, kin_b.cam_xpos,
            kin0.cam_xmat, kin_b.cam_xmat, bodies,
            same=lambda a, b2: abs(m.cam_fovy[a] - m.cam_fovy[b2]) < 1e-6, shape_ok=lambda a, q: True,
        )
        del self.errors[n_err:]
        if self.errors:
            raise SymmetryError(self._msg())
        site_local = np.stack(
            [kin0.site_xmat[s].T @ self.M @ kin_b.site_xmat[sites[s]] for s in range(m.nsite)]
        ) if m.nsite else np.zeros((0, 3, 3))

        qpos_map, qvel_map = self.build_joint_maps(joints, jsigns, joffs, bodies, body_local, kin0)
        ctrl_map = self.build_ctrl_map(joints, jsigns, joffs, qpos_map)
        if self.errors:
            raise SymmetryError(self._msg())

        sym = ModelSymmetry(
            mirror=self.mirror, qpos=qpos_map, qvel=qvel_map, ctrl=ctrl_map,
            bodies=bodies, joints=joints, joint_signs=jsigns, geoms=geoms, sites=sites,
            cameras=cams, body_local=body_local, site_local=site_local, residual=float("nan"),
            body_names=tuple(_body_name(m, b) for b in range(nb)),
            joint_names=tuple(_joint_name(m, j) for j in range(m.njnt)),
        )
        for name, jm in (("qpos", qpos_map), ("qvel", qvel_map), ("ctrl", ctrl_map)):
            if not jm.is_involution(atol=1e-6):
                raise SymmetryError(f"the derived {name} map is not an involution")
        return sym

    def geom_color(self, g) -> np.ndarray:
        """The RGBA a renderer shows: the material's when the geom has one."""
        mat = self.m.geom_matid[g]
        return self.m.mat_rgba[mat] if mat >= 0 else self.m.geom_rgba[g]

    def _jn(self, b):
        return [_joint_name(self.m, j) for j in self.body_jnts[b]] or "none"

    def _msg(self):
        return (
            f"model is not mirror-symmetric about the plane n={self.mirror.normal}, "
            f"p0={self.mirror.point} within tol={self.tol:g} m:\n  - " + "\n  - ".join(self.errors)
        )

    def candidate(self, b, c, kin0, kin_b, q_b):
        """Residual of matching body b to c at the reference posture, and the joint pairs."""
        m = self.m
        res = [
            np.linalg.norm(kin_b.xpos[c] - self.mp(kin0.xpos[b])),
            np.linalg.norm(kin_b.xipos[c] - self.mp(kin0.xipos[b])),
            abs(m.body_mass[c] - m.body_mass[b]) / max(m.body_mass[b], 1e-9) * 0.01,
        ]
        why = "position"
        pairs = []
        for j, j2 in zip(self.body_jnts[b], self.body_jnts[c]):
            t = m.jnt_type[j]
            if t in (_HINGE, _SLIDE):
                img = -self.M @ kin0.xaxis[j] if t == _HINGE else self.M @ kin0.xaxis[j]
                ax2 = kin_b.xaxis[j2]
                e_plus, e_minus = np.linalg.norm(ax2 - img), np.linalg.norm(ax2 + img)
                s = 1.0 if e_plus <= e_minus else -1.0
                e_axis = min(e_plus, e_minus)
                e_anchor = np.linalg.norm(kin_b.xanchor[j2] - self.mp(kin0.xanchor[j]))
                off = m.qpos0[m.jnt_qposadr[j2]] - s * m.qpos0[m.jnt_qposadr[j]]
                e_range = 0.0
                if m.jnt_limited[j] != m.jnt_limited[j2]:
                    e_range = np.inf
                elif m.jnt_limited[j]:
                    mapped = np.sort(s * m.jnt_range[j] + off)
                    e_range = float(np.max(np.abs(mapped - m.jnt_range[j2])))
                if e_axis > self.tol:
                    why = (
                        f"joint '{_joint_name(m, j)}' axis {np.round(kin0.xaxis[j], 4)} has no mirror "
                        f"in '{_joint_name(m, j2)}' axis {np.round(ax2, 4)}"
                    )
                elif e_range > self.tol:
                    why = (
                        f"joint '{_joint_name(m, j)}' range {m.jnt_range[j]} mirrored with sign {s:+.0f} "
                        f"is not the range {m.jnt_range[j2]} of '{_joint_name(m, j2)}'"
                    )
                elif e_anchor > self.tol:
                    why = f"joint '{_joint_name(m, j)}' anchor is off its mirror by {e_anchor:.3g} m"
                res += [e_axis, e_anchor, e_range]
                pairs.append((j, j2, s, off))
            else:  # ball joint inside an articulated chain
                pairs.append((j, j2, 0.0, 0.0))
        return float(max(res)), {"pairs": pairs, "why": why}

    def random_residual(self, b, c, info, q_b, n=4):
        """Residual of the pairing b->c with b's joints at random values."""
        m = self.m
        loc0 = self.kin0.xmat[b].T @ self.M @ self.kin_b.xmat[c]
        worst = 0.0
        for _ in range(n):
            qa, qm = self.m.qpos0.copy(), q_b.copy()
            for (j, j2, s, off) in info["pairs"]:
                if s == 0.0:
                    continue
                v = self.random_joint_value(j)[0]
                qa[m.jnt_qposadr[j]] = v
                qm[m.jnt_qposadr[j2]] = s * v + off
            ka, km = _fk(m, self.data, qa), _fk(m, self.data, qm)
            worst = max(
                worst,
                np.linalg.norm(km.xipos[c] - self.mp(ka.xipos[b])),
                np.abs(km.xmat[c] - self.M @ ka.xmat[b] @ loc0).max(),
            )
            ga, gc = self.body_geoms[b], self.body_geoms[c]
            if ga and gc:
                d = np.linalg.norm(km.geom_xpos[gc][None] - self.mp(ka.geom_xpos[ga])[:, None], axis=-1)
                worst = max(worst, float(d.min(axis=1).max()))
            for ch in range(1, m.nbody):
                if m.body_parentid[ch] == b:
                    d = np.linalg.norm(km.xpos[None] - self.mp(ka.xpos[ch])[None], axis=-1)
                    kids = [k for k in range(1, m.nbody) if m.body_parentid[k] == c]
                    worst = max(worst, float(min(d[0][k] for k in kids)) if kids else np.inf)
        return float(worst)

    def match_elements(self, kind, n, body_of, xa, xb, ra, rb, bodies, same, shape_ok):
        out = -np.ones(n, dtype=np.int64)
        used = set()
        for e in range(n):
            target_body = bodies[body_of[e]]
            best, best_res = -1, np.inf
            for e2 in range(n):
                if body_of[e2] != target_body or e2 in used or not same(e, e2):
                    continue
                res = np.linalg.norm(xb[e2] - self.mp(xa[e]))
                q = rb[e2].T @ self.M @ ra[e]
                if not shape_ok(e, q):
                    res = max(res, 1.0)
                if res < best_res:
                    best, best_res = e2, res
            if best < 0 or best_res > self.tol:
                name = _name(self.m, getattr(mujoco.mjtObj, f"mjOBJ_{kind.upper()}"), e)
                hint = " with the same type, size and colour" if kind == "geom" else ""
                self.errors.append(
                    f"{kind} '{name}' on body '{_body_name(self.m, body_of[e])}' has no mirror{hint} "
                    f"(best residual {best_res:.3g} m)"
                )
            else:
                out[e] = best
                used.add(best)
        return out

    def build_joint_maps(self, joints, jsigns, joffs, bodies, body_local, kin0):
        m = self.m
        qperm, qsign, qoff = np.arange(m.nq), np.ones(m.nq), np.zeros(m.nq)
        vperm, vsign = np.arange(m.nv), np.ones(m.nv)
        qnames, vnames = [""] * m.nq, [""] * m.nv
        for j in range(m.njnt):
            j2 = joints[j]
            t = m.jnt_type[j]
            qa, qa2 = m.jnt_qposadr[j], m.jnt_qposadr[j2]
            va, va2 = m.jnt_dofadr[j], m.jnt_dofadr[j2]
            name = _joint_name(m, j)
            if t in (_HINGE, _SLIDE):
                qperm[qa2], qsign[qa2], qoff[qa2] = qa, jsigns[j], joffs[j]
                vperm[va2], vsign[va2] = va, jsigns[j]
                qnames[qa], vnames[va] = name, name
                continue
            b = m.jnt_bodyid[j]
            loc = body_local[b]
            if t == _FREE:
                ax = self.mirror.axis_index()
                if ax is None:
                    self.errors.append(f"free joint '{name}': oblique mirror planes are not supported")
                    continue
                ppos, spos = _signed_perm(self.M, f"free joint '{name}' position")
                p0 = np.asarray(self.mirror.point)
                qperm[qa2 : qa2 + 3] = qa + ppos
                qsign[qa2 : qa2 + 3] = spos
                qoff[qa2 : qa2 + 3] = p0 - self.M @ p0
                k = self.M
                qs, vs = 3, 3
                vperm[va2 : va2 + 3], vsign[va2 : va2 + 3] = va + ppos, spos
                for i in range(3):
                    qnames[qa + i] = f"{name}[{'xyz'[i]}]"
                    vnames[va + i] = f"{name}[v{'xyz'[i]}]"
            else:  # ball: R_b = R_parent R_offset R(q); R' = K R(q) L with K below.
                p = m.body_parentid[b]
                r_off = np.zeros(9)
                mujoco.mju_quat2Mat(r_off, m.body_quat[b])
                r_off2 = np.zeros(9)
                mujoco.mju_quat2Mat(r_off2, m.body_quat[bodies[b]])
                k = r_off2.reshape(3, 3).T @ body_local[p].T @ r_off.reshape(3, 3)
                qs, vs = 0, 0
            try:
                qp, qsg = self.rot_map(k, loc, f"joint '{name}' orientation")
                # Angular velocity in the body frame: w' = -L^T w.
                wp, wsg = _signed_perm(-loc.T, f"joint '{name}' angular velocity")
            except SymmetryError as e:
                self.errors.append(str(e))
                continue
            qperm[qa2 + qs : qa2 + qs + 4] = qa + qs + qp
            qsign[qa2 + qs : qa2 + qs + 4] = qsg
            vperm[va2 + vs : va2 + vs + 3] = va + vs + wp
            vsign[va2 + vs : va2 + vs + 3] = wsg
            for i in range(4):
                qnames[qa + qs + i] = f"{name}[q{'wxyz'[i]}]"
            for i in range(3):
                vnames[va + vs + i] = f"{name}[w{'xyz'[i]}]"
        return (
            JointMap(qperm, qsign, qoff, tuple(qnames)),
            JointMap(vperm, vsign, np.zeros(m.nv), tuple(vnames)),
        )

    def build_ctrl_map(self, joints, jsigns, joffs, qpos_map):
        m = self.m
        perm, sign, off = np.arange(m.nu), np.ones(m.nu), np.zeros(m.nu)
        names = tuple(_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in range(m.nu))
        trn_joint = int(mujoco.mjtTrn.mjTRN_JOINT)
        trn_tendon = int(mujoco.mjtTrn.mjTRN_TENDON)

        def tendon_terms(t):
            adr, num = m.tendon_adr[t], m.tendon_num[t]
            if np.any(m.wrap_type[adr : adr + num] != int(mujoco.mjtWrap.mjWRAP_JOINT)):
                return None
            return {int(m.wrap_objid[adr + i]): float(m.wrap_prm[adr + i]) for i in range(num)}

        def image(a):
            """(kind, target, sign, const) of the mirror of actuator a's transmission."""
            tid = m.actuator_trnid[a, 0]
            if m.actuator_trntype[a] == trn_joint:
                j = tid
                if m.jnt_type[j] not in (_HINGE, _SLIDE):
                    return None
                return ("joint", joints[j], jsigns[j], joffs[j])
            if m.actuator_trntype[a] == trn_tendon:
                terms = tendon_terms(tid)
                if terms is None:
                    return None
                mapped = {int(joints[j]): c * jsigns[j] for j, c in terms.items()}
                const_src = {int(joints[j]): joffs[j] for j in terms}
                for t2 in range(m.ntendon):
                    terms2 = tendon_terms(t2)
                    if terms2 is None or set(terms2) != set(mapped):
                        continue
                    for sigma in (1.0, -1.0):
                        if all(abs(terms2[k] - sigma * v) < 1e-9 for k, v in mapped.items()):
                            const = sum(terms2[k] * const_src[k] for k in mapped)
                            return ("tendon", t2, sigma, const)
                return ("tendon", -1, 0.0, 0.0)
            return None

        for a in range(m.nu):
            im = image(a)
            if im is None:
                self.errors.append(
                    f"actuator '{names[a]}': only joint and fixed-tendon transmissions are supported"
                )
                continue
            kind, target, s, const = im
            a2s = [
                a2 for a2 in range(m.nu)
                if m.actuator_trntype[a2] == m.actuator_trntype[a] and m.actuator_trnid[a2, 0] == target
            ]
            if not a2s:
                self.errors.append(f"actuator '{names[a]}': no actuator drives the mirror {kind}")
                continue
            a2 = a2s[0]
            g, g2 = m.actuator_gear[a, 0], m.actuator_gear[a2, 0]
            gain_ok = np.allclose(m.actuator_gainprm[a], m.actuator_gainprm[a2], atol=1e-9) and np.allclose(
                m.actuator_biasprm[a], m.actuator_biasprm[a2], atol=1e-9
            )
            if abs(abs(g) - abs(g2)) > 1e-9 or not gain_ok:
                self.errors.append(
                    f"actuator '{names[a]}' and its mirror '{names[a2]}' differ in gear or gains"
                )
                continue
            sa = s * np.sign(g * g2)
            # Position-like actuators (bias on length) take a target: add the joint offset.
            oa = g2 * const if abs(m.actuator_biasprm[a, 1]) > 0 else 0.0
            perm[a2], sign[a2], off[a2] = a, sa, oa
            if m.actuator_ctrllimited[a]:
                mapped = np.sort(sa * m.actuator_ctrlrange[a] + oa)
                if np.max(np.abs(mapped - m.actuator_ctrlrange[a2])) > self.tol:
                    self.errors.append(
                        f"actuator '{names[a]}' ctrlrange {m.actuator_ctrlrange[a]} mirrors to "
                        f"{mapped}, not the range {m.actuator_ctrlrange[a2]} of '{names[a2]}'"
                    )
        return JointMap(perm, sign, off, names)


def derive_symmetry(
    model: mujoco.MjModel, mirror: Mirror, tol: float = DEFAULT_TOL, n_verify: int = 64, seed: int = 0
) -> ModelSymmetry:
    """Derive ``S`` for a model: body, joint, geom, site, camera matches and joint maps.

    Args:
      model: a compiled MuJoCo model whose reference posture ``qpos0`` is mirror-symmetric.
      mirror: the mirror plane (e.g. ``Mirror.from_axis("y")``).
      tol: accepted forward-kinematics residual in metres (see :data:`DEFAULT_TOL`).
      n_verify: random configurations used to verify the result.
      seed: seed of those configurations (and of ambiguity resolution).
    Returns:
      A :class:`ModelSymmetry`; ``residual`` holds the verified FK residual.
    Raises:
      SymmetryError: listing every unmatched body, joint, geom, site or actuator with its
        residual, or if the verified residual exceeds ``tol``.
    """
    if not isinstance(model, mujoco.MjModel):
        raise TypeError(f"derive_symmetry expects a mujoco.MjModel, got {type(model).__name__}")
    if not isinstance(mirror, Mirror):
        raise TypeError(f"derive_symmetry expects a Mirror, got {type(mirror).__name__}")
    sym = _Deriver(model, mirror, tol, seed).run()
    res, per_body = _verify(model, sym, n_verify, seed)
    if res > tol:
        worst = np.argsort(per_body)[::-1][:8]
        lines = [
            f"body '{sym.body_names[b]}' residual {per_body[b]:.3g} m" for b in worst if per_body[b] > tol
        ]
        raise SymmetryError(
            f"the derived map fails forward kinematics at random postures (max residual "
            f"{res:.3g} m > tol {tol:g} m):\n  - " + "\n  - ".join(lines)
        )
    return dataclasses.replace(sym, residual=res)


def _verify(model, sym: ModelSymmetry, n: int, seed: int):
    d = _Deriver(model, sym.mirror, DEFAULT_TOL, seed)
    mj = mujoco.MjData(model)
    a, b = sym.qpos.as_matrix()
    per_body = np.zeros(model.nbody)
    worst = 0.0
    for _ in range(n):
        q = model.qpos0.copy()
        for j in range(model.njnt):
            adr = model.jnt_qposadr[j]
            v = d.random_joint_value(j)
            q[adr : adr + len(v)] = v
        qm = a @ q + b
        ka, km = _fk(model, mj, q), _fk(model, mj, qm)
        pos_err = np.linalg.norm(km.xpos[sym.bodies] - d.mp(ka.xpos), axis=-1)
        rot_err = np.abs(km.xmat[sym.bodies] - sym.mirror.matrix @ ka.xmat @ sym.body_local).max(axis=(1, 2))
        per_body = np.maximum(per_body, np.maximum(pos_err, rot_err))
        if model.ngeom:
            worst = max(worst, float(np.linalg.norm(km.geom_xpos[sym.geoms] - d.mp(ka.geom_xpos), axis=-1).max()))
        if model.nsite:
            worst = max(worst, float(np.linalg.norm(km.site_xpos[sym.sites] - d.mp(ka.site_xpos), axis=-1).max()))
    return max(worst, float(per_body.max())), per_body


def verify_symmetry(model: mujoco.MjModel, sym: ModelSymmetry, n: int = 256, seed: int = 0) -> float:
    """Largest forward-kinematics residual of ``sym`` over ``n`` random configurations.

    For each random ``q`` inside the joint ranges (free joints: random orientation, position
    near ``qpos0``), compares ``FK(S q)`` with the mirrored ``FK(q)`` for every body
    (position, and orientation ``M R L`` as the displacement of a point 1 m away), every geom
    and every site.

    Returns:
      The maximum residual in metres.
    """
    return _verify(model, sym, n, seed)[0]
