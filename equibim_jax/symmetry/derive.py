"""Derive the mirror symmetry of a MuJoCo model, and verify it on forward kinematics.

``derive_symmetry(model, mirror)`` matches every body to its mirror image, every joint to
its mirror joint (hinge signs as axial vectors, slide signs as polar vectors), every geom,
site and camera, and builds the maps for ``qpos``, ``qvel`` and ``ctrl``. Free and ball
joints of objects map their position as a point and their orientation by ``M R L``, with
``L`` the body's own local reflection found from its geoms. Nothing is typed in by hand.

The check has two parts:

* **Kinematics** (body frames, joint axes, anchors and ranges, sites, actuator
  transmissions): what ``S`` needs. Strict by default: a model whose kinematics are not
  mirror-symmetric within ``tol`` raises :class:`SymmetryError` naming what does not match.
  With ``approximate=True`` the best joint map is derived for a model that is only nearly
  symmetric, asymmetric joint and control ranges are intersected (with a warning), and the
  forward-kinematics residual of every body is reported.
* **Dynamics and geometry** (masses, centres of mass, inertias, actuator gains, collision
  and visual geoms): measured and reported in :class:`DynamicsReport`, with sizes.
  Massless bodies are never compared by their inertial frame. With ``dynamics="strict"``
  any such asymmetry is an error instead.

Matching runs in body-tree order at the model's reference posture ``qpos0`` (which must be
mirror-symmetric), and ambiguous candidates (e.g. two fingers that coincide at q = 0) are
resolved by comparing them at random postures. The whole map is then checked by
:func:`verify_symmetry` at random configurations inside the (mirror-consistent) joint ranges.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

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
_MESH = int(_GEOM.mjGEOM_MESH)
_BOXLIKE = {int(_GEOM.mjGEOM_BOX), int(_GEOM.mjGEOM_ELLIPSOID)}

DEFAULT_TOL = 5e-4
"""Default tolerance: 0.5 mm of forward-kinematics residual (orientations count as the
displacement of a point 1 m from the body origin). It accepts rounded constants such as
pi written as 3.1416 (~1e-5 m at arm scale) and refuses a link 1 mm off."""

APPROX_TOL = 0.05
"""Default largest forward-kinematics residual (m) accepted with ``approximate=True``."""

DYN_RTOL = 1e-3
"""Relative difference of masses, inertias and actuator gains above which a mirror pair is
reported as dynamically asymmetric."""

_MIN_MASS = 1e-12


class SymmetryError(ValueError):
    """The model is not mirror-symmetric about the given plane within the tolerance."""


class SymmetryWarning(UserWarning):
    """``S`` was derived with a concession, e.g. an asymmetric joint range was intersected."""


def _name(model, obj, i) -> str:
    n = mujoco.mj_id2name(model, obj, i)
    return n if n else f"#{i}"


def _body_name(model, b):
    return "world" if b == 0 else _name(model, mujoco.mjtObj.mjOBJ_BODY, b)


def _joint_name(model, j):
    return _name(model, mujoco.mjtObj.mjOBJ_JOINT, j)


def _geom_name(model, g):
    return _name(model, mujoco.mjtObj.mjOBJ_GEOM, g)


def _mat2quat(r: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(r, dtype=np.float64).reshape(9))
    return q


def _quat2mat(q: np.ndarray) -> np.ndarray:
    r = np.zeros(9)
    mujoco.mju_quat2Mat(r, np.asarray(q, dtype=np.float64))
    return r.reshape(3, 3)


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


def _point_set_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Hausdorff distance between point sets a [n, 3] and b [k, 3] (m)."""
    try:  # a k-d tree keeps large meshes fast; scipy comes with jax
        from scipy.spatial import cKDTree
    except ImportError:  # pragma: no cover
        cKDTree = None

    def one_sided(p, q):
        if cKDTree is not None and len(p) * len(q) > 1_000_000:
            return float(cKDTree(q).query(p)[0].max())
        worst = 0.0
        rows = max(1, int(1_000_000 // max(len(q), 1)))
        for i in range(0, len(p), rows):
            d = np.linalg.norm(p[i : i + rows, None, :] - q[None, :, :], axis=-1)
            worst = max(worst, float(d.min(axis=1).max()))
        return worst

    if len(a) == 0 or len(b) == 0:
        return 0.0 if len(a) == len(b) else math.inf
    return max(one_sided(a, b), one_sided(b, a))


def _finite_or_none(x):
    x = float(x)
    return x if math.isfinite(x) else None


@dataclasses.dataclass(frozen=True)
class Asymmetry:
    """One measured dynamic or geometric asymmetry of a mirror pair.

    Attributes:
      kind: ``"mass"``, ``"com"``, ``"inertia"``, ``"actuator"`` or ``"geom"``.
      element: the body, actuator or geom it concerns.
      mirror: its mirror partner (``None`` for a geom without one).
      value: its size: metres for ``"com"`` (centre-of-mass offset from the mirror image)
        and ``"geom"`` (best residual of a geom without a mirror geom, ``inf`` when no geom
        of the mirror body has its type); relative difference for ``"mass"``,
        ``"inertia"`` and ``"actuator"``.
      detail: a readable sentence.
    """

    kind: str
    element: str
    mirror: str | None
    value: float
    detail: str

    def to_dict(self) -> dict:
        return {"kind": self.kind, "element": self.element, "mirror": self.mirror,
                "value": _finite_or_none(self.value), "detail": self.detail}

    @classmethod
    def from_dict(cls, d: dict) -> "Asymmetry":
        v = d.get("value")
        return cls(str(d["kind"]), str(d["element"]), d.get("mirror"), math.inf if v is None else float(v),
                   str(d.get("detail", "")))


@dataclasses.dataclass(frozen=True)
class DynamicsReport:
    """Dynamic and geometric asymmetries of a model whose kinematics are mirror-symmetric.

    Physics (contacts, inertia, actuator response) is exactly mirror-equivariant only when
    ``exact`` is true; otherwise each entry of ``items`` says by how much it is not.

    Attributes:
      items: the asymmetries above the thresholds (COM offset above the tolerance, masses,
        inertias and gains differing by more than :data:`DYN_RTOL`, geoms without a mirror).
      max_com_offset_m: largest centre-of-mass offset over all massive mirror pairs (m).
      max_mass_rel: largest relative mass difference.
      max_inertia_rel: largest relative inertia difference (Frobenius norm, in the
        mirrored body frame).
    """

    items: tuple[Asymmetry, ...] = ()
    max_com_offset_m: float = 0.0
    max_mass_rel: float = 0.0
    max_inertia_rel: float = 0.0

    @property
    def exact(self) -> bool:
        """Whether no dynamic or geometric asymmetry was found."""
        return not self.items

    @property
    def unmatched_geoms(self) -> tuple[str, ...]:
        return tuple(a.element for a in self.items if a.kind == "geom")

    def of_kind(self, kind: str) -> tuple[Asymmetry, ...]:
        return tuple(a for a in self.items if a.kind == kind)

    def describe(self) -> str:
        head = (f"dynamics: {'exact' if self.exact else f'{len(self.items)} asymmetries'} "
                f"(max COM offset {self.max_com_offset_m:.3g} m, max mass difference "
                f"{self.max_mass_rel:.3g}, max inertia difference {self.max_inertia_rel:.3g})")
        return "\n".join([head] + [f"  - {a.kind}: {a.detail}" for a in self.items])

    def to_dict(self) -> dict:
        return {
            "exact": self.exact,
            "max_com_offset_m": self.max_com_offset_m,
            "max_mass_rel": self.max_mass_rel,
            "max_inertia_rel": self.max_inertia_rel,
            "unmatched_geoms": list(self.unmatched_geoms),
            "items": [a.to_dict() for a in self.items],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "DynamicsReport":
        return cls(
            tuple(Asymmetry.from_dict(a) for a in d.get("items", ())),
            float(d.get("max_com_offset_m", 0.0)),
            float(d.get("max_mass_rel", 0.0)),
            float(d.get("max_inertia_rel", 0.0)),
        )


def _camera_flip(loc: np.ndarray, atol: float) -> str | None:
    """How a camera's image maps, from its local reflection ``L`` [3, 3] (camera frame:
    x right, y up, looking along -z)."""
    if np.allclose(loc, np.diag([-1.0, 1.0, 1.0]), atol=atol):
        return "horizontal"
    if np.allclose(loc, np.diag([1.0, -1.0, 1.0]), atol=atol):
        return "vertical"
    return None


@dataclasses.dataclass(frozen=True, eq=False)
class ModelSymmetry:
    """The mirror symmetry of one model.

    Attributes:
      mirror: the plane.
      qpos: JointMap [nq]; qvel: JointMap [nv] (a linear map, no offsets);
      ctrl: JointMap [nu].
      bodies: int [nbody], the mirror body of each body. joints: int [njnt].
      joint_signs: float [njnt], +1/-1 for hinge and slide joints, 0 for free and ball.
      geoms: int [ngeom] (-1: no mirror geom, see ``dynamics``); sites: int [nsite];
        cameras: int [ncam] (-1: no mirror camera).
      body_local: float [nbody, 3, 3], each body's local reflection ``L`` with
        ``R_{bodies[b]} = M R_b L_b``.
      site_local: float [nsite, 3, 3], the same for sites.
      residual: the largest forward-kinematics residual found by :func:`verify_symmetry`
        over bodies, sites and matched geoms (m).
      body_names, joint_names: names [nbody], [njnt].
      dynamics: the measured dynamic and geometric asymmetries.
      body_residual: float [nbody], each body's forward-kinematics residual (m), or None.
      site_residual: float [nsite], the same for sites, or None.
      joint_ranges: float [njnt, 2], the range of each hinge and slide joint inside which
        ``S`` maps to valid postures (the joint range intersected with the mirror of its
        partner's); NaN for unlimited, free and ball joints. None: the model's ranges.
      ctrl_ranges: float [nu, 2], the same for control ranges (NaN: unlimited).
      camera_local: float [ncam, 3, 3], each camera's local reflection (identity where
        ``cameras`` is -1).
      approximate: whether ``approximate=True`` derived it. tol: the residual it was
        accepted with (m). dynamics_mode: ``"report"`` or ``"strict"``.
      warnings: the concessions made (intersected ranges).
      geom_names, site_names, camera_names: names [ngeom], [nsite], [ncam].
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
    dynamics: DynamicsReport = DynamicsReport()
    body_residual: np.ndarray | None = None
    site_residual: np.ndarray | None = None
    joint_ranges: np.ndarray | None = None
    ctrl_ranges: np.ndarray | None = None
    camera_local: np.ndarray | None = None
    approximate: bool = False
    tol: float = DEFAULT_TOL
    dynamics_mode: str = "report"
    warnings: tuple[str, ...] = ()
    geom_names: tuple[str, ...] = ()
    site_names: tuple[str, ...] = ()
    camera_names: tuple[str, ...] = ()

    @property
    def dynamics_exact(self) -> bool:
        """Whether masses, COMs, inertias, gains and geoms are mirror-symmetric too, so that
        physics (not only kinematics) is mirror-equivariant."""
        return self.dynamics.exact

    @property
    def camera_flip(self) -> tuple[str | None, ...]:
        """Per camera: ``"horizontal"`` when the mirrored scene seen by its mirror camera is
        its own image flipped left-right, ``"vertical"`` for an up-down flip, ``None`` when
        it has no mirror camera or the image map is not a flip."""
        if self.camera_local is None:
            return tuple(None for _ in range(len(self.cameras)))
        atol = max(1e-6, min(self.tol, DEFAULT_TOL))
        return tuple(
            _camera_flip(self.camera_local[c], atol) if self.cameras[c] >= 0 else None
            for c in range(len(self.cameras))
        )

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

    def report(self, min_residual: float = 0.0) -> str:
        """Residuals per body and site (those above ``min_residual`` m), intersected ranges
        and the dynamic report, as text."""
        lines = [f"forward-kinematics residual {self.residual:.3g} m "
                 f"({'approximate' if self.approximate else 'strict'} kinematics, tol {self.tol:g} m)"]
        if self.body_residual is not None:
            order = np.argsort(-self.body_residual, kind="stable")
            rows = [b for b in order if self.body_residual[b] > min_residual]
            for b in rows:
                lines.append(f"  body '{self.body_names[b]}' ↔ '{self.body_names[self.bodies[b]]}': "
                             f"{self.body_residual[b]:.3g} m")
        if self.site_residual is not None and self.site_names:
            for s in np.argsort(-self.site_residual, kind="stable"):
                if self.site_residual[s] > min_residual:
                    lines.append(f"  site '{self.site_names[s]}' ↔ '{self.site_names[self.sites[s]]}': "
                                 f"{self.site_residual[s]:.3g} m")
        lines += [f"warning: {w}" for w in self.warnings]
        lines.append(self.dynamics.describe())
        return "\n".join(lines)

    def save(self, path, ee_sites=None) -> None:
        """Write this map as portable JSON (see :func:`save_mirror_map`)."""
        from equibim_jax.symmetry.mirror_map import save_mirror_map

        save_mirror_map(self, path, ee_sites=ee_sites)

    @classmethod
    def load(cls, path, model: mujoco.MjModel | None = None) -> "ModelSymmetry":
        """Read a map written by :meth:`save` (see :func:`load_mirror_map`)."""
        from equibim_jax.symmetry.mirror_map import load_mirror_map

        return load_mirror_map(path, model)


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


def _rel(a, b) -> float:
    """Relative difference of two arrays: ||a - b|| / max(||a||, ||b||) (0 when both are 0)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(float(np.linalg.norm(a)), float(np.linalg.norm(b)))
    return float(np.linalg.norm(a - b) / scale) if scale > 0 else 0.0


def _fmt_range(r) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in r) + "]"


class _Deriver:
    def __init__(self, model: mujoco.MjModel, mirror: Mirror, tol: float, seed: int, *,
                 approximate: bool = False, geo_tol: float | None = None, dynamics: str = "report"):
        self.m = model
        self.mirror = mirror
        self.M = mirror.matrix
        self.tol = tol  # kinematic tolerance (body frames, joints, sites, cameras)
        self.geo_tol = tol if geo_tol is None else geo_tol  # geoms, COMs, range equality
        self.approximate = approximate
        self.dynamics = dynamics
        self.rng = np.random.default_rng(seed)
        self.data = mujoco.MjData(model)
        self.errors: list[str] = []
        self.warnings: list[str] = []
        m = model
        self.body_jnts = [
            list(range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])) if m.body_jntnum[b] else []
            for b in range(m.nbody)
        ]
        self.body_geoms = [[] for _ in range(m.nbody)]
        for g in range(m.ngeom):
            self.body_geoms[m.geom_bodyid[g]].append(g)

    # -- helpers -----------------------------------------------------------------------
    def mp(self, p):
        p0 = np.asarray(self.mirror.point)
        return p0 + (np.asarray(p) - p0) @ self.M.T

    def is_free_root(self, b) -> bool:
        js = self.body_jnts[b]
        return len(js) > 0 and self.m.jnt_type[js[0]] == _FREE

    def random_joint_value(self, j, ranges: np.ndarray | None = None) -> np.ndarray:
        """A random value of joint j inside its range ([1] or [4] or [7]); ``ranges``
        [njnt, 2] overrides the model's ranges where finite."""
        m = self.m
        t = m.jnt_type[j]
        if t in (_HINGE, _SLIDE):
            if ranges is not None and np.all(np.isfinite(ranges[j])):
                lo, hi = ranges[j]
            elif m.jnt_limited[j]:
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

    def geom_color(self, g) -> np.ndarray:
        """The RGBA a renderer shows: the material's when the geom has one."""
        mat = self.m.geom_matid[g]
        return self.m.mat_rgba[mat] if mat >= 0 else self.m.geom_rgba[g]

    def mesh_verts(self, g) -> np.ndarray:
        m = self.m
        mid = m.geom_dataid[g]
        adr, num = m.mesh_vertadr[mid], m.mesh_vertnum[mid]
        return np.asarray(m.mesh_vert[adr : adr + num], dtype=np.float64)

    def shape_residual(self, g, g2, q) -> tuple[float, str]:
        """How far geom g2 is from the mirror image of geom g's shape (m), and why.

        ``q`` [3, 3] maps g's frame onto g2's (improper). Meshes compare their vertex sets;
        primitives their sizes along the axes that ``q`` permutes. ``inf`` when the
        orientation cannot match."""
        m = self.m
        t = int(m.geom_type[g])
        if t != int(m.geom_type[g2]):
            return math.inf, "different geom type"
        s1, s2 = m.geom_size[g], m.geom_size[g2]
        if t == _MESH:
            r = _point_set_distance(self.mesh_verts(g) @ q.T, self.mesh_verts(g2))
            n1 = _name(m, mujoco.mjtObj.mjOBJ_MESH, m.geom_dataid[g])
            n2 = _name(m, mujoco.mjtObj.mjOBJ_MESH, m.geom_dataid[g2])
            if n1 == n2:
                return r, f"mesh '{n1}' is chiral: its mirror image is {r:.3g} m from itself"
            return r, f"mesh '{n2}' is {r:.3g} m from the mirror image of mesh '{n1}'"
        if t == _SPHERE:
            return float(abs(s1[0] - s2[0])), "size differs"
        if t in _AXISYM:
            if abs(abs(q[2, 2]) - 1.0) > self.geo_tol:
                return math.inf, "its axis does not mirror onto the other geom's axis"
            return float(np.max(np.abs(s1[:2] - s2[:2]))), "size differs"
        aq = np.abs(q)
        p = np.round(aq)
        if np.max(np.abs(aq - p)) > self.geo_tol or not np.allclose(p.sum(0), 1) or not np.allclose(p.sum(1), 1):
            return math.inf, "its orientation does not mirror onto the other geom's"
        if t in _BOXLIKE:
            return float(np.max(np.abs(p @ s1 - s2))), "size differs"
        return float(np.max(np.abs(s1 - s2))), "size differs"

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
                rg = _quat2mat(m.geom_quat[g])
                found = False
                for g2 in self.body_geoms[b]:
                    if np.linalg.norm(m.geom_pos[g2] - pg) > self.geo_tol:
                        continue
                    q = _quat2mat(m.geom_quat[g2]).T @ loc @ rg
                    if self.shape_residual(g, g2, q)[0] <= self.geo_tol:
                        found = True
                        break
                if not found:
                    ok = False
                    break
            if ok and np.linalg.norm(loc @ m.body_ipos[b] - m.body_ipos[b]) <= self.geo_tol:
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
        self.kin0, self.kin_b, self.kin_b_q = kin0, kin_b, q_b

        for b in range(1, nb):
            if bodies[b] >= 0:
                continue
            pb = bodies[m.body_parentid[b]]
            if pb < 0:
                self.errors.append(f"body '{_body_name(m, b)}': its parent has no mirror")
                continue
            cands = []
            for c in range(1, nb):
                if m.body_parentid[c] != pb or self.is_free_root(c):
                    continue
                if [m.jnt_type[j] for j in self.body_jnts[c]] != [m.jnt_type[j] for j in self.body_jnts[b]]:
                    continue
                cands.append(self.candidate(b, c, kin0, kin_b))
            if not cands:
                self.errors.append(
                    f"body '{_body_name(m, b)}' (joints {self._jn(b)}): no body under the mirror "
                    f"of its parent has the same joint types"
                )
                continue
            ok = [x for x in cands if x["ok"]]
            if not ok:
                x = min(cands, key=lambda x: x["res"])
                self.errors.append(
                    f"body '{_body_name(m, b)}' (joints {self._jn(b)}): nearest mirror candidate "
                    f"'{_body_name(m, x['c'])}' has residual {x['res']:.3g} ({x['why']})"
                )
                continue
            if len(ok) > 1:
                # Ambiguous at the reference posture: compare at random postures; kinematic
                # ties are broken by the ranges, then by mass and centre of mass.
                for x in ok:
                    x["rand"] = self.random_residual(b, x["c"], x)
                ok.sort(key=lambda x: (max(x["rand"], self.geo_tol), x["rng"], x["dyn"]))
            best = ok[0]
            c = best["c"]
            bodies[b] = c
            body_local[b] = kin0.xmat[b].T @ self.M @ kin_b.xmat[c]
            for (j, j2, s, off) in best["pairs"]:
                joints[j], jsigns[j], joffs[j] = j2, s, off

        for b in range(nb):
            if bodies[b] >= 0 and bodies[bodies[b]] != b:
                self.errors.append(
                    f"body '{_body_name(m, b)}' maps to '{_body_name(m, bodies[b])}', which maps to "
                    f"'{_body_name(m, bodies[bodies[b]])}': the map is not an involution"
                )
        if self.errors:
            raise SymmetryError(self._msg())

        geoms, geom_items = self.match_geoms(bodies, body_local)
        sites = self.match_elements(
            "site", m.nsite, m.site_bodyid, kin0.site_xpos, kin_b.site_xpos, bodies,
        )
        # Cameras do not touch physics: one without a mirror maps to -1 instead of failing;
        # code that needs image symmetry checks its camera (see Env).
        n_err = len(self.errors)
        cams = self.match_elements(
            "camera", m.ncam, m.cam_bodyid, kin0.cam_xpos, kin_b.cam_xpos, bodies,
            same=lambda a, b2: abs(m.cam_fovy[a] - m.cam_fovy[b2]) < 1e-6,
        )
        del self.errors[n_err:]
        if self.errors:
            raise SymmetryError(self._msg())
        site_local = np.stack(
            [kin0.site_xmat[s].T @ self.M @ kin_b.site_xmat[sites[s]] for s in range(m.nsite)]
        ) if m.nsite else np.zeros((0, 3, 3))
        cam_local = np.stack(
            [kin0.cam_xmat[c].T @ self.M @ kin_b.cam_xmat[cams[c]] if cams[c] >= 0 else np.eye(3)
             for c in range(m.ncam)]
        ) if m.ncam else np.zeros((0, 3, 3))

        joint_ranges = self.mirror_joint_ranges(joints, jsigns, joffs)
        qpos_map, qvel_map = self.build_joint_maps(joints, jsigns, joffs, bodies, body_local, kin0)
        ctrl_map, ctrl_ranges, act_items = self.build_ctrl_map(joints, jsigns, joffs)
        if self.errors:
            raise SymmetryError(self._msg())

        dyn = self.measure_dynamics(bodies, body_local, joints, geom_items + act_items)
        if self.dynamics == "strict" and not dyn.exact:
            self.errors += [a.detail for a in dyn.items]
            raise SymmetryError(self._msg() + "\n(dynamics='strict'; the default dynamics='report' "
                                              "reports these instead of refusing the model)")

        sym = ModelSymmetry(
            mirror=self.mirror, qpos=qpos_map, qvel=qvel_map, ctrl=ctrl_map,
            bodies=bodies, joints=joints, joint_signs=jsigns, geoms=geoms, sites=sites,
            cameras=cams, body_local=body_local, site_local=site_local, residual=float("nan"),
            body_names=tuple(_body_name(m, b) for b in range(nb)),
            joint_names=tuple(_joint_name(m, j) for j in range(m.njnt)),
            dynamics=dyn, joint_ranges=joint_ranges, ctrl_ranges=ctrl_ranges, camera_local=cam_local,
            approximate=self.approximate, tol=self.tol, dynamics_mode=self.dynamics,
            warnings=tuple(self.warnings),
            geom_names=tuple(_geom_name(m, g) for g in range(m.ngeom)),
            site_names=tuple(_name(m, mujoco.mjtObj.mjOBJ_SITE, s) for s in range(m.nsite)),
            camera_names=tuple(_name(m, mujoco.mjtObj.mjOBJ_CAMERA, c) for c in range(m.ncam)),
        )
        for name, jm in (("qpos", qpos_map), ("qvel", qvel_map), ("ctrl", ctrl_map)):
            if not jm.is_involution(atol=1e-6):
                raise SymmetryError(f"the derived {name} map is not an involution")
        return sym

    def _jn(self, b):
        return [_joint_name(self.m, j) for j in self.body_jnts[b]] or "none"

    def _msg(self):
        kind = "approximately " if self.approximate else ""
        return (
            f"model is not {kind}mirror-symmetric about the plane n={self.mirror.normal}, "
            f"p0={self.mirror.point} within tol={self.tol:g} m:\n  - " + "\n  - ".join(self.errors)
        )

    def candidate(self, b, c, kin0, kin_b) -> dict:
        """How well body c matches the mirror of body b at the reference posture.

        Returns a dict: ``c``; ``kin`` the kinematic residual (body origin, joint axes and
        anchors; m); ``rng`` the joint-range mismatch; ``dyn`` a mass and centre-of-mass
        difference used only to break ties; ``res`` the residual compared with the
        tolerance; ``ok`` whether c is admissible; ``why`` the first reason it is not;
        ``pairs`` [(j, j2, sign, offset)]."""
        m = self.m
        e_pos = float(np.linalg.norm(kin_b.xpos[c] - self.mp(kin0.xpos[b])))
        kin, rng = [e_pos], [0.0]
        reasons = {}
        pairs = []
        for j, j2 in zip(self.body_jnts[b], self.body_jnts[c]):
            t = m.jnt_type[j]
            if t not in (_HINGE, _SLIDE):  # ball joint inside an articulated chain
                pairs.append((j, j2, 0.0, 0.0))
                continue
            img = -self.M @ kin0.xaxis[j] if t == _HINGE else self.M @ kin0.xaxis[j]
            ax2 = kin_b.xaxis[j2]
            e_plus, e_minus = np.linalg.norm(ax2 - img), np.linalg.norm(ax2 + img)
            s = 1.0 if e_plus <= e_minus else -1.0
            e_axis = float(min(e_plus, e_minus))
            e_anchor = float(np.linalg.norm(kin_b.xanchor[j2] - self.mp(kin0.xanchor[j])))
            off = m.qpos0[m.jnt_qposadr[j2]] - s * m.qpos0[m.jnt_qposadr[j]]
            e_range = 0.0
            if m.jnt_limited[j] != m.jnt_limited[j2]:
                e_range = 1.0 if self.approximate else math.inf
            elif m.jnt_limited[j]:
                mapped = np.sort(s * m.jnt_range[j] + off)
                e_range = float(np.max(np.abs(mapped - m.jnt_range[j2])))
                overlap = min(mapped[1], m.jnt_range[j2][1]) - max(mapped[0], m.jnt_range[j2][0])
                if self.approximate and overlap <= 0:
                    e_range = math.inf
            jn, jn2 = _joint_name(m, j), _joint_name(m, j2)
            if e_axis > self.tol:
                reasons.setdefault("axis", f"joint '{jn}' axis {np.round(kin0.xaxis[j], 4)} has no mirror in "
                                           f"'{jn2}' axis {np.round(ax2, 4)}")
            if e_range > (math.inf if self.approximate else self.tol) or e_range == math.inf:
                what = "does not overlap" if self.approximate else "is not"
                reasons.setdefault("range", f"joint '{jn}' range {m.jnt_range[j]} mirrored with sign {s:+.0f} "
                                            f"{what} the range {m.jnt_range[j2]} of '{jn2}'")
            if e_anchor > self.tol:
                reasons.setdefault("anchor", f"joint '{jn}' anchor is off its mirror by {e_anchor:.3g} m")
            kin += [e_axis, e_anchor]
            rng.append(e_range)
            pairs.append((j, j2, s, off))
        if e_pos > self.tol:
            reasons.setdefault("position", f"body origin is off its mirror by {e_pos:.3g} m")
        kin_res, rng_res = max(kin), max(rng)
        if self.approximate:
            res = kin_res if rng_res < math.inf else math.inf
        else:
            res = max(kin_res, rng_res)
        why = next((reasons[k] for k in ("axis", "range", "anchor", "position") if k in reasons), "")
        mb, mc = m.body_mass[b], m.body_mass[c]
        dyn = abs(mc - mb) / max(mb, mc, _MIN_MASS)
        if min(mb, mc) > _MIN_MASS:  # a massless body has no meaningful inertial frame
            dyn += float(np.linalg.norm(kin_b.xipos[c] - self.mp(kin0.xipos[b])))
        # Approximate mode takes the nearest candidate whose ranges overlap; the verification
        # then reports (and judges) the residual of every body.
        ok = res < math.inf if self.approximate else res <= self.tol
        return {"c": c, "kin": kin_res, "rng": rng_res, "dyn": dyn, "res": res,
                "ok": ok, "why": why, "pairs": pairs}

    def random_residual(self, b, c, cand, n=4):
        """Kinematic residual of the pairing b->c with b's joints at random values: body
        frame, orientation, and the nearest mirror child of each child."""
        m = self.m
        loc0 = self.kin0.xmat[b].T @ self.M @ self.kin_b.xmat[c]
        kids_c = [k for k in range(1, m.nbody) if m.body_parentid[k] == c]
        kids_b = [k for k in range(1, m.nbody) if m.body_parentid[k] == b]
        worst = 0.0
        q_b = self.kin_b_q
        if not any(s != 0.0 for (_, _, s, _) in cand["pairs"]):
            n = 1  # nothing moves: one posture says all
        for _ in range(n):
            qa, qm = m.qpos0.copy(), q_b.copy()
            for (j, j2, s, off) in cand["pairs"]:
                if s == 0.0:
                    continue
                v = self.random_joint_value(j)[0]
                qa[m.jnt_qposadr[j]] = v
                qm[m.jnt_qposadr[j2]] = s * v + off
            ka, km = _fk(m, self.data, qa), _fk(m, self.data, qm)
            worst = max(
                worst,
                float(np.linalg.norm(km.xpos[c] - self.mp(ka.xpos[b]))),
                float(np.abs(km.xmat[c] - self.M @ ka.xmat[b] @ loc0).max()),
            )
            for ch in kids_b:
                if not kids_c:
                    return math.inf
                d = np.linalg.norm(km.xpos[kids_c] - self.mp(ka.xpos[ch]), axis=-1)
                worst = max(worst, float(d.min()))
        return float(worst)

    def match_elements(self, kind, n, body_of, xa, xb, bodies, same=lambda a, b: True):
        """Match sites or cameras by their mirrored world position at the reference posture
        (in approximate mode a site takes its nearest candidate; the verification judges it)."""
        out = -np.ones(n, dtype=np.int64)
        used = set()
        for e in range(n):
            target_body = bodies[body_of[e]]
            best, best_res = -1, np.inf
            for e2 in range(n):
                if body_of[e2] != target_body or e2 in used or not same(e, e2):
                    continue
                res = np.linalg.norm(xb[e2] - self.mp(xa[e]))
                if res < best_res:
                    best, best_res = e2, res
            if best < 0 or (best_res > self.tol and not (self.approximate and kind == "site")):
                name = _name(self.m, getattr(mujoco.mjtObj, f"mjOBJ_{kind.upper()}"), e)
                self.errors.append(
                    f"{kind} '{name}' on body '{_body_name(self.m, body_of[e])}' has no mirror "
                    f"(best residual {best_res:.3g} m)"
                )
            else:
                out[e] = best
                used.add(best)
        return out

    def match_geoms(self, bodies, body_local) -> tuple[np.ndarray, list[Asymmetry]]:
        """Match each geom to a geom of the mirror body with the same type, size and colour,
        in the body frames (so that an approximate body-frame residual is not counted twice).

        Returns the geom map int [ngeom] (-1: none) and one :class:`Asymmetry` per geom
        without a mirror geom."""
        m = self.m
        out = -np.ones(m.ngeom, dtype=np.int64)
        items = []
        used = set()
        world_shift = self.mp(np.zeros(3))  # the world frame's own mirror offset
        for g in range(m.ngeom):
            b = m.geom_bodyid[g]
            c, loc = bodies[b], body_local[b]
            pos_img = loc.T @ m.geom_pos[g] + (world_shift if b == 0 else 0.0)
            rg = _quat2mat(m.geom_quat[g])
            cands = []
            for g2 in self.body_geoms[c]:
                if g2 in used or m.geom_type[g2] != m.geom_type[g]:
                    continue
                e_pos = float(np.linalg.norm(m.geom_pos[g2] - pos_img))
                q = _quat2mat(m.geom_quat[g2]).T @ loc.T @ rg
                e_shape, why = self.shape_residual(g, g2, q)
                res = max(e_pos, e_shape)
                colour_ok = bool(np.allclose(self.geom_color(g), self.geom_color(g2), atol=1e-6))
                if e_shape > self.geo_tol:
                    why = f"nearest '{_geom_name(m, g2)}': {why}"
                elif e_pos > self.geo_tol:
                    why = f"nearest '{_geom_name(m, g2)}' is {e_pos:.3g} m off its mirror position"
                else:
                    why = (f"nearest '{_geom_name(m, g2)}' has colour {np.round(self.geom_color(g2), 3)}, "
                           f"not {np.round(self.geom_color(g), 3)}")
                cands.append((not (res <= self.geo_tol and colour_ok), res, g2, why))
            best, best_res, best_why = -1, math.inf, "no geom of the mirror body has its type"
            if cands:
                bad, best_res, best, best_why = min(cands, key=lambda t: (t[0], t[1]))
                if bad:
                    best = -1
            if best >= 0:
                out[g] = best
                used.add(best)
            else:
                name = _geom_name(m, g)
                items.append(Asymmetry(
                    "geom", name, None, best_res,
                    f"geom '{name}' on body '{_body_name(m, b)}' has no mirror with the same type, size "
                    f"and colour (best residual {best_res:.3g} m; {best_why})",
                ))
        return out, items

    def mirror_joint_ranges(self, joints, jsigns, joffs) -> np.ndarray:
        """float [njnt, 2]: each hinge/slide joint's range intersected with the mirror image of
        its partner's range (NaN: unlimited or not a hinge/slide). Warns where they differ."""
        m = self.m
        out = np.full((m.njnt, 2), np.nan)
        for j in range(m.njnt):
            if m.jnt_type[j] not in (_HINGE, _SLIDE):
                continue
            j2, s, off = joints[j], jsigns[j], joffs[j]
            r1 = m.jnt_range[j] if m.jnt_limited[j] else np.array([-np.inf, np.inf])
            r2 = m.jnt_range[j2] if m.jnt_limited[j2] else np.array([-np.inf, np.inf])
            mapped = np.sort(s * r1 + off)
            inter = np.array([max(mapped[0], r2[0]), min(mapped[1], r2[1])])
            if np.all(np.isfinite(inter)):
                out[j2] = inter
            if j <= j2 and not np.allclose(mapped, r2, atol=self.geo_tol):
                back = np.sort(s * (inter - off))
                self.warnings.append(
                    f"joint '{_joint_name(m, j)}' range {_fmt_range(r1)} mirrors (sign {s:+.0f}, offset "
                    f"{off:+.4g}) to {_fmt_range(mapped)}, not the range {_fmt_range(r2)} of "
                    f"'{_joint_name(m, j2)}'; S is valid on the intersection: '{_joint_name(m, j)}' in "
                    f"{_fmt_range(back)}, '{_joint_name(m, j2)}' in {_fmt_range(inter)}"
                )
        return out

    def measure_dynamics(self, bodies, body_local, joints, extra: list[Asymmetry]) -> DynamicsReport:
        """Masses, centres of mass and inertias of every mirror pair of massive bodies, in the
        mirrored body frame; joint damping, armature, friction loss and stiffness."""
        m = self.m
        items: list[Asymmetry] = []
        max_com = max_mass = max_inertia = 0.0
        for b in range(1, m.nbody):
            c = int(bodies[b])
            if c < b:
                continue
            nb, nc = _body_name(m, b), _body_name(m, c)
            pair = f"'{nb}'" if b == c else f"'{nb}' and '{nc}'"
            mb, mc = float(m.body_mass[b]), float(m.body_mass[c])
            if max(mb, mc) <= _MIN_MASS:
                continue  # massless: no inertial frame to compare
            rel = abs(mb - mc) / max(mb, mc)
            max_mass = max(max_mass, rel)
            if rel > DYN_RTOL:
                items.append(Asymmetry("mass", nb, nc, rel, f"bodies {pair}: masses {mb:.4g} and {mc:.4g} kg "
                                                             f"differ by {100 * rel:.3g}%"))
            if min(mb, mc) <= _MIN_MASS:
                continue
            loc = body_local[b]
            com = float(np.linalg.norm(m.body_ipos[c] - loc.T @ m.body_ipos[b]))
            max_com = max(max_com, com)
            if com > self.geo_tol:
                if b == c:
                    detail = f"body '{nb}' maps to itself, but its centre of mass is {com:.3g} m from its mirror image"
                else:
                    detail = (f"bodies {pair}: the centre of mass of '{nc}' is {com:.3g} m from the mirror "
                              f"image of the centre of mass of '{nb}'")
                items.append(Asymmetry("com", nb, nc, com, detail))
            ib = _quat2mat(m.body_iquat[b]) @ np.diag(m.body_inertia[b]) @ _quat2mat(m.body_iquat[b]).T
            ic = _quat2mat(m.body_iquat[c]) @ np.diag(m.body_inertia[c]) @ _quat2mat(m.body_iquat[c]).T
            irel = _rel(ic, loc.T @ ib @ loc)
            max_inertia = max(max_inertia, irel)
            if irel > DYN_RTOL:
                items.append(Asymmetry("inertia", nb, nc, irel, f"bodies {pair}: inertia tensors differ from "
                                                                f"mirror images by {100 * irel:.3g}%"))
        for j in range(m.njnt):
            j2 = int(joints[j])
            if j2 < j or m.jnt_type[j] not in (_HINGE, _SLIDE):
                continue
            d, d2 = m.jnt_dofadr[j], m.jnt_dofadr[j2]
            va = [m.dof_damping[d], m.dof_armature[d], m.dof_frictionloss[d], m.jnt_stiffness[j]]
            vb = [m.dof_damping[d2], m.dof_armature[d2], m.dof_frictionloss[d2], m.jnt_stiffness[j2]]
            rel = _rel(va, vb)
            if rel > DYN_RTOL:
                n1, n2 = _joint_name(m, j), _joint_name(m, j2)
                items.append(Asymmetry("joint", n1, n2, rel, f"joints '{n1}' and '{n2}': damping, armature, "
                                                             f"friction loss or stiffness differ by {100 * rel:.3g}%"))
        return DynamicsReport(tuple(items + list(extra)), max_com, max_mass, max_inertia)
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

    def build_ctrl_map(self, joints, jsigns, joffs):
        """The ctrl JointMap [nu], the mirror-consistent control ranges float [nu, 2] (NaN:
        unlimited) and the actuators whose gains differ from their mirror's."""
        m = self.m
        perm, sign, off = np.arange(m.nu), np.ones(m.nu), np.zeros(m.nu)
        ranges = np.full((m.nu, 2), np.nan)
        items: list[Asymmetry] = []
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
            if abs(abs(g) - abs(g2)) > 1e-9:
                self.errors.append(
                    f"actuator '{names[a]}' and its mirror '{names[a2]}' differ in gear ({g:g}, {g2:g})"
                )
                continue
            if a <= a2:
                gain = _rel(np.r_[m.actuator_gainprm[a], m.actuator_biasprm[a]],
                            np.r_[m.actuator_gainprm[a2], m.actuator_biasprm[a2]])
                if gain > DYN_RTOL:
                    items.append(Asymmetry("actuator", names[a], names[a2], gain,
                                           f"actuators '{names[a]}' and '{names[a2]}' differ in gains or "
                                           f"biases by {100 * gain:.3g}%"))
            sa = s * np.sign(g * g2)
            # Position-like actuators (bias on length) take a target: add the joint offset.
            oa = g2 * const if abs(m.actuator_biasprm[a, 1]) > 0 else 0.0
            perm[a2], sign[a2], off[a2] = a, sa, oa
            r1 = m.actuator_ctrlrange[a] if m.actuator_ctrllimited[a] else np.array([-np.inf, np.inf])
            r2 = m.actuator_ctrlrange[a2] if m.actuator_ctrllimited[a2] else np.array([-np.inf, np.inf])
            mapped = np.sort(sa * r1 + oa)
            inter = np.array([max(mapped[0], r2[0]), min(mapped[1], r2[1])])
            if np.all(np.isfinite(inter)):
                ranges[a2] = inter
            if np.allclose(mapped, r2, atol=self.geo_tol):
                continue
            msg = (f"actuator '{names[a]}' ctrlrange {_fmt_range(r1)} mirrors to {_fmt_range(mapped)}, "
                   f"not the range {_fmt_range(r2)} of '{names[a2]}'")
            if not self.approximate:
                self.errors.append(msg)
            elif inter[0] >= inter[1]:
                self.errors.append(msg + ": the two do not overlap")
            elif a <= a2:
                self.warnings.append(msg + f"; S is valid on the intersection {_fmt_range(inter)} "
                                           f"for '{names[a2]}'")
        return JointMap(perm, sign, off, names), ranges, items


def derive_symmetry(
    model: mujoco.MjModel,
    mirror: Mirror,
    tol: float | None = None,
    n_verify: int = 64,
    seed: int = 0,
    *,
    approximate: bool = False,
    dynamics: str = "report",
) -> ModelSymmetry:
    """Derive ``S`` for a model: body, joint, geom, site, camera matches and joint maps.

    Args:
      model: a compiled MuJoCo model whose reference posture ``qpos0`` is mirror-symmetric.
      mirror: the mirror plane (e.g. ``Mirror.from_axis("y")``).
      tol: accepted forward-kinematics residual in metres; default :data:`DEFAULT_TOL`, or
        :data:`APPROX_TOL` with ``approximate=True``.
      n_verify: random configurations used to verify the result.
      seed: seed of those configurations (and of ambiguity resolution).
      approximate: derive the best joint map of a model that is only nearly symmetric:
        bodies and joints are matched to their nearest mirror within ``tol``, asymmetric
        joint and control ranges are intersected (with a :class:`SymmetryWarning`), and
        the residual of every body is reported in ``body_residual``.
      dynamics: ``"report"`` (default): masses, centres of mass, inertias, joint and
        actuator dynamics and geoms are measured and reported in ``dynamics``;
        ``"strict"``: any such asymmetry raises :class:`SymmetryError`.
    Returns:
      A :class:`ModelSymmetry`; ``residual`` holds the verified FK residual, ``dynamics``
      the dynamic and geometric report.
    Raises:
      SymmetryError: listing every unmatched body, joint, site or actuator with its
        residual, or every body whose verified residual exceeds ``tol``.
    """
    if not isinstance(model, mujoco.MjModel):
        raise TypeError(f"derive_symmetry expects a mujoco.MjModel, got {type(model).__name__}")
    if not isinstance(mirror, Mirror):
        raise TypeError(f"derive_symmetry expects a Mirror, got {type(mirror).__name__}")
    if dynamics not in ("report", "strict"):
        raise ValueError(f"dynamics must be 'report' or 'strict', got {dynamics!r}")
    kin_tol = float(tol) if tol is not None else (APPROX_TOL if approximate else DEFAULT_TOL)
    if not kin_tol > 0:
        raise ValueError(f"tol must be positive, got {tol!r}")
    geo_tol = min(kin_tol, DEFAULT_TOL) if approximate else kin_tol
    drv = _Deriver(model, mirror, kin_tol, seed, approximate=approximate, geo_tol=geo_tol, dynamics=dynamics)
    sym = drv.run()
    for w in sym.warnings:
        warnings.warn(w, SymmetryWarning, stacklevel=2)
    res, per_body, per_site = _verify(model, sym, n_verify, seed)
    sym = dataclasses.replace(sym, residual=res, body_residual=per_body, site_residual=per_site)
    if res > kin_tol:
        raise SymmetryError(
            f"the derived map fails forward kinematics at random postures (max residual "
            f"{res:.3g} m > tol {kin_tol:g} m):\n" + _residual_lines(sym, kin_tol)
        )
    return sym


def _residual_lines(sym: ModelSymmetry, above: float, limit: int = 16) -> str:
    """The bodies and sites whose residual exceeds ``above``, largest first (ties in tree
    order, so the body where an asymmetry starts comes first), one per line."""
    rows = []
    if sym.body_residual is not None:
        rows += [(r, f"body '{sym.body_names[b]}' residual {r:.3g} m") for b, r in enumerate(sym.body_residual)]
    if sym.site_residual is not None and sym.site_names:
        rows += [(r, f"site '{sym.site_names[s]}' residual {r:.3g} m") for s, r in enumerate(sym.site_residual)]
    rows = [(i, *t) for i, t in enumerate(rows) if t[0] > above]
    rows = [t[1:] for t in sorted(rows, key=lambda t: (-round(float(t[1]), 9), t[0]))]
    more = f"\n  ... and {len(rows) - limit} more" if len(rows) > limit else ""
    return "  - " + "\n  - ".join(t[1] for t in rows[:limit]) + more if rows else "  (geoms only)"


def _check_sizes(model, sym: ModelSymmetry) -> None:
    for what, have, want in (("nq", sym.qpos.size, model.nq), ("nv", sym.qvel.size, model.nv),
                             ("nu", sym.ctrl.size, model.nu), ("nbody", len(sym.bodies), model.nbody),
                             ("njnt", len(sym.joints), model.njnt), ("ngeom", len(sym.geoms), model.ngeom),
                             ("nsite", len(sym.sites), model.nsite), ("ncam", len(sym.cameras), model.ncam)):
        if have != want:
            raise SymmetryError(f"the mirror map was derived for a model with {what}={have}, but this model "
                                f"has {what}={want}")


def _verify(model, sym: ModelSymmetry, n: int, seed: int):
    """(max residual, per-body residual float [nbody], per-site residual float [nsite])."""
    _check_sizes(model, sym)
    d = _Deriver(model, sym.mirror, DEFAULT_TOL, seed)
    mj = mujoco.MjData(model)
    a, b = sym.qpos.as_matrix()
    per_body = np.zeros(model.nbody)
    per_site = np.zeros(model.nsite)
    geoms = np.flatnonzero(np.asarray(sym.geoms) >= 0)
    worst = 0.0
    for _ in range(n):
        q = model.qpos0.copy()
        for j in range(model.njnt):
            adr = model.jnt_qposadr[j]
            v = d.random_joint_value(j, sym.joint_ranges)
            q[adr : adr + len(v)] = v
        qm = a @ q + b
        ka, km = _fk(model, mj, q), _fk(model, mj, qm)
        pos_err = np.linalg.norm(km.xpos[sym.bodies] - d.mp(ka.xpos), axis=-1)
        pos_err[0] = 0.0  # the world frame is fixed; it is not moved onto its mirror image
        rot_err = np.abs(km.xmat[sym.bodies] - sym.mirror.matrix @ ka.xmat @ sym.body_local).max(axis=(1, 2))
        per_body = np.maximum(per_body, np.maximum(pos_err, rot_err))
        if len(geoms):
            e = np.linalg.norm(km.geom_xpos[sym.geoms[geoms]] - d.mp(ka.geom_xpos[geoms]), axis=-1)
            worst = max(worst, float(e.max()))
        if model.nsite:
            e = np.linalg.norm(km.site_xpos[sym.sites] - d.mp(ka.site_xpos), axis=-1)
            per_site = np.maximum(per_site, e)
    return max(worst, float(per_body.max(initial=0.0)), float(per_site.max(initial=0.0))), per_body, per_site


def verify_symmetry(model: mujoco.MjModel, sym: ModelSymmetry, n: int = 256, seed: int = 0) -> float:
    """Largest forward-kinematics residual of ``sym`` over ``n`` random configurations.

    For each random ``q`` inside the joint ranges (``sym.joint_ranges`` where set; free
    joints: random orientation, position near ``qpos0``), compares ``FK(S q)`` with the
    mirrored ``FK(q)`` for every body (position, and orientation ``M R L`` as the
    displacement of a point 1 m away), every geom that has a mirror geom and every site.

    Returns:
      The maximum residual in metres.
    Raises:
      SymmetryError: if ``sym`` was derived for a model of other sizes.
    """
    return _verify(model, sym, n, seed)[0]
