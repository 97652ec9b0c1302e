"""The mirror plane and the pure operators that reflect each kind of quantity.

A mirror is the Householder reflection ``M = I - 2 n n^T`` about a plane with unit normal
``n`` through a point ``p0``. Every operator here is pure, works under ``jit`` and ``vmap``,
accepts any number of leading batch dimensions, and is an involution (``S(S(x)) == x``).

| quantity                              | operator                         |
|---------------------------------------|----------------------------------|
| position ``p``                        | ``p0 + M (p - p0)``              |
| polar vector (velocity, slide axis)   | ``M v``                          |
| axial vector (angular vel., hinge)    | ``-M w``                         |
| rotation of a mirror-symmetric body   | ``M R L`` (``L``: local reflection) |
| quaternion ``q`` (w, x, y, z)         | ``-(0, n) * q * (0, l)``         |
| image                                 | horizontal flip                  |
| point cloud                           | each point as a position         |
| point cloud in a camera frame         | ``T_cam^-1 reflect(T_cam p)``    |
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

Array = jnp.ndarray

_AXES = {"x": 0, "y": 1, "z": 2}


def _as_vec3(v, what: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"Mirror {what} must be 3 finite numbers, got {v!r}")
    return tuple(float(x) for x in a)


@dataclasses.dataclass(frozen=True)
class Mirror:
    """A reflection plane: unit ``normal`` [3] through ``point`` [3] (world frame).

    Hashable and static, so it can be closed over or passed as a static argument.
    """

    normal: tuple[float, float, float] = (0.0, 1.0, 0.0)
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        n = np.asarray(_as_vec3(self.normal, "normal"))
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            raise ValueError("Mirror normal must be non-zero")
        object.__setattr__(self, "normal", tuple(float(x) for x in n / norm))
        object.__setattr__(self, "point", _as_vec3(self.point, "point"))

    @classmethod
    def from_axis(cls, axis: str = "y", offset: float = 0.0) -> "Mirror":
        """The plane ``{axis} = offset``, e.g. ``Mirror.from_axis("y")`` for y = 0."""
        if axis not in _AXES:
            raise ValueError(f"axis must be one of x, y, z; got {axis!r}")
        n = np.zeros(3)
        n[_AXES[axis]] = 1.0
        return cls(tuple(n), tuple(n * offset))

    @property
    def matrix(self) -> np.ndarray:
        """``M = I - 2 n n^T``, [3, 3] (symmetric, orthogonal, det -1)."""
        n = np.asarray(self.normal)
        return np.eye(3) - 2.0 * np.outer(n, n)

    @property
    def homogeneous(self) -> np.ndarray:
        """The affine map ``p -> p0 + M (p - p0)`` as a 4x4 matrix, [4, 4]."""
        m = self.matrix
        t = np.asarray(self.point) - m @ np.asarray(self.point)
        h = np.eye(4)
        h[:3, :3] = m
        h[:3, 3] = t
        return h

    def axis_index(self) -> int | None:
        """Index of the coordinate axis the normal lies on, or None if it is oblique."""
        n = np.abs(np.asarray(self.normal))
        i = int(np.argmax(n))
        return i if abs(n[i] - 1.0) < 1e-12 else None


def axis_reflection(axis: int | str) -> np.ndarray:
    """The local reflection ``diag`` with -1 on one axis, [3, 3]."""
    i = _AXES[axis] if isinstance(axis, str) else int(axis)
    d = np.ones(3)
    d[i] = -1.0
    return np.diag(d)


def _mat(mirror: Mirror, dtype) -> Array:
    return jnp.asarray(mirror.matrix, dtype=dtype)


def _float(x) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def reflect_points(mirror: Mirror, p: Array) -> Array:
    """Positions: ``p0 + M (p - p0)``. ``p``: [..., 3] -> [..., 3]."""
    p = _float(p)
    m = _mat(mirror, p.dtype)
    p0 = jnp.asarray(mirror.point, p.dtype)
    return p0 + (p - p0) @ m.T


def reflect_polar(mirror: Mirror, v: Array) -> Array:
    """Polar vectors (velocities, forces, slide axes): ``M v``. [..., 3] -> [..., 3]."""
    v = _float(v)
    return v @ _mat(mirror, v.dtype).T


def reflect_axial(mirror: Mirror, w: Array) -> Array:
    """Axial vectors (angular velocities, torques, hinge axes): ``-M w``. [..., 3]."""
    w = _float(w)
    return -(w @ _mat(mirror, w.dtype).T)


def _local(local) -> np.ndarray:
    if local is None:
        return None
    loc = np.asarray(local, dtype=np.float64)
    if loc.shape != (3, 3):
        raise ValueError(f"local reflection must be [3, 3], got shape {loc.shape}")
    if not np.allclose(loc @ loc.T, np.eye(3), atol=1e-6) or np.linalg.det(loc) > 0:
        raise ValueError("local reflection must be orthogonal with det -1")
    if not np.allclose(loc, loc.T, atol=1e-6):
        raise ValueError("local reflection must be symmetric (an involution)")
    return loc


def default_local(mirror: Mirror) -> np.ndarray:
    """The local reflection used when none is given: the world mirror's own matrix."""
    return mirror.matrix


def reflect_rotmat(mirror: Mirror, r: Array, local=None) -> Array:
    """Rotation of a mirror-symmetric body: ``M R L``. ``r``: [..., 3, 3].

    ``local`` [3, 3] is the body's own reflection in its frame (defaults to ``M``, right
    for a body whose frame is aligned with the world at the mirror).
    """
    r = _float(r)
    loc = _local(local) if local is not None else default_local(mirror)
    return _mat(mirror, r.dtype) @ r @ jnp.asarray(loc, r.dtype)


def _quat_of_reflection(refl: np.ndarray) -> np.ndarray:
    """Unit axis ``u`` of a reflection ``I - 2 u u^T`` (the pure quaternion (0, u))."""
    w, v = np.linalg.eigh(refl)
    u = v[:, int(np.argmin(w))]
    return np.concatenate([[0.0], u])


def _quat_left_matrix(a: np.ndarray) -> np.ndarray:
    """``L(a)`` with ``a * q = L(a) q`` (Hamilton product, w-first)."""
    w, x, y, z = a
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def _quat_right_matrix(b: np.ndarray) -> np.ndarray:
    """``R(b)`` with ``q * b = R(b) q`` (Hamilton product, w-first)."""
    w, x, y, z = b
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def quat_reflection_matrix(mirror: Mirror, local=None) -> np.ndarray:
    """The linear map on quaternions that matches ``M R L``, [4, 4].

    ``-M`` and ``-L`` are half-turns about ``n`` and ``l``, so
    ``M R L = (-M) R (-L)`` has quaternion ``(0, n) * q * (0, l)``; the extra sign makes the
    map an involution and keeps ``w`` for the y-plane case: (w,x,y,z) -> (w,-x,y,-z).
    """
    loc = _local(local) if local is not None else default_local(mirror)
    qn = _quat_of_reflection(mirror.matrix)
    ql = _quat_of_reflection(loc)
    return -(_quat_left_matrix(qn) @ _quat_right_matrix(ql))


def reflect_quat(mirror: Mirror, q: Array, local=None) -> Array:
    """Quaternions (w, x, y, z) of a mirror-symmetric body. [..., 4] -> [..., 4]."""
    q = _float(q)
    a = jnp.asarray(quat_reflection_matrix(mirror, local), q.dtype)
    return q @ a.T


def reflect_pose_quat(mirror: Mirror, pose: Array, local=None) -> Array:
    """Pose as position + quaternion. [..., 7] (x, y, z, qw, qx, qy, qz) -> [..., 7]."""
    pose = _float(pose)
    return jnp.concatenate(
        [reflect_points(mirror, pose[..., :3]), reflect_quat(mirror, pose[..., 3:7], local)],
        axis=-1,
    )


def rot6d_to_matrix(r6: Array) -> Array:
    """6D rotation (first two columns, [c0, c1]) to a rotation matrix by Gram-Schmidt.

    ``r6``: [..., 6] -> [..., 3, 3].
    """
    a, b = r6[..., :3], r6[..., 3:6]
    c0 = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
    b = b - jnp.sum(c0 * b, axis=-1, keepdims=True) * c0
    c1 = b / jnp.linalg.norm(b, axis=-1, keepdims=True)
    c2 = jnp.cross(c0, c1)
    return jnp.stack([c0, c1, c2], axis=-1)


def matrix_to_rot6d(r: Array) -> Array:
    """Rotation matrix [..., 3, 3] to its 6D form [..., 6] = [column 0, column 1]."""
    return jnp.concatenate([r[..., :, 0], r[..., :, 1]], axis=-1)


def reflect_rot6d(mirror: Mirror, r6: Array, local=None) -> Array:
    """6D rotation ``[c0, c1]`` under ``M R L``. [..., 6] -> [..., 6].

    When ``L`` does not mix column 2 into columns 0 and 1 (e.g. any axis-aligned local
    reflection), the map is linear in ``(c0, c1)``, so it is exact and an involution even
    for non-orthonormal network outputs. Otherwise ``c2 = c0 x c1`` is reconstructed.
    """
    r6 = _float(r6)
    loc = _local(local) if local is not None else default_local(mirror)
    m = _mat(mirror, r6.dtype)
    c0, c1 = r6[..., :3], r6[..., 3:6]
    cols = [c0, c1]
    if np.any(np.abs(loc[2, :2]) > 0) or np.any(np.abs(loc[:2, 2]) > 0):
        cols.append(jnp.cross(c0, c1))
    out = []
    for k in range(2):
        col = sum(cols[i] * float(loc[i, k]) for i in range(len(cols)))
        out.append(col @ m.T)
    return jnp.concatenate(out, axis=-1)


def reflect_pose_6d(mirror: Mirror, pose: Array, local=None) -> Array:
    """Pose as position + 6D rotation. [..., 9] -> [..., 9]."""
    pose = _float(pose)
    return jnp.concatenate(
        [reflect_points(mirror, pose[..., :3]), reflect_rot6d(mirror, pose[..., 3:9], local)],
        axis=-1,
    )


def flip_image(img: Array, layout: str = "NHWC") -> Array:
    """Horizontal flip (the image of a camera on the plane, horizontal axis normal to it).

    ``layout`` names the trailing axes: ``"NHWC"`` / ``"HWC"`` -> [..., H, W, C] (flip
    axis -2); ``"NCHW"`` / ``"CHW"`` -> [..., C, H, W] (flip axis -1).
    """
    if layout in ("NHWC", "HWC"):
        axis = -2
    elif layout in ("NCHW", "CHW"):
        axis = -1
    else:
        raise ValueError(f"layout must be NHWC, HWC, NCHW or CHW, got {layout!r}")
    img = jnp.asarray(img)
    if img.ndim < 3:
        raise ValueError(f"flip_image expects an image with >= 3 dims, got shape {img.shape}")
    return jnp.flip(img, axis=axis)


def reflect_point_cloud(mirror: Mirror, points: Array) -> Array:
    """World-frame point cloud: each point as a position. [..., N, 3] (extra channels such as
    colour after the first 3 are kept as they are) -> same shape."""
    points = _float(points)
    xyz = reflect_points(mirror, points[..., :3])
    return jnp.concatenate([xyz, points[..., 3:]], axis=-1) if points.shape[-1] > 3 else xyz


def reflect_point_cloud_camera(mirror: Mirror, points: Array, t_cam: Array) -> Array:
    """Camera-frame point cloud: the world mirror expressed in the camera frame.

    With ``T_cam`` the camera-to-world transform (rotation ``R``, camera position ``c``),
    each point ``p`` given in the camera frame is taken to the world, reflected about the
    mirror plane, and taken back::

        S_cam(p) = T_cam^-1 reflect(mirror, T_cam p)
                 = R^T M R p - 2 (n . (c - p0)) R^T n

    (``M = I - 2 n n^T``, plane through ``p0``). This is right for any camera pose. For a
    camera on the plane (``n . (c - p0) = 0``) whose x axis is normal to it (``R^T n =
    +-e_x``) it reduces to negating the camera-frame x coordinate, ``diag(-1, 1, 1) p``.
    An involution, like every operator here.

    Args:
      mirror: the reflection plane (world frame).
      points: [..., N, 3] in the camera frame; extra trailing channels after the first 3
        (e.g. colour) are kept as they are.
      t_cam: [4, 4] or [..., 4, 4] camera-to-world transform (a rigid transform); leading
        dims broadcast against those of ``points`` before ``N``.
    Returns:
      [..., N, 3+], in the camera frame.
    """
    points = _float(points)
    t = jnp.asarray(t_cam, points.dtype)
    if t.ndim < 2 or t.shape[-2:] != (4, 4):
        raise ValueError(f"t_cam must be a [..., 4, 4] camera-to-world transform, got shape {t.shape}")
    rot, cam_pos = t[..., :3, :3], t[..., :3, 3]
    n = jnp.asarray(mirror.normal, points.dtype)
    p0 = jnp.asarray(mirror.point, points.dtype)
    n_cam = jnp.einsum("...ji,j->...i", rot, n)  # R^T n: the normal in the camera frame
    lin = jnp.eye(3, dtype=points.dtype) - 2.0 * n_cam[..., :, None] * n_cam[..., None, :]
    dist = jnp.sum((cam_pos - p0) * n, axis=-1)  # signed distance of the camera to the plane
    shift = -2.0 * dist[..., None] * n_cam  # [..., 3]
    xyz = jnp.einsum("...ij,...nj->...ni", lin, points[..., :3]) + shift[..., None, :]
    if points.shape[-1] == 3:
        return xyz
    rest = jnp.broadcast_to(points[..., 3:], xyz.shape[:-1] + (points.shape[-1] - 3,))
    return jnp.concatenate([xyz, rest], axis=-1)
