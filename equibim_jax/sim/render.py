"""A pure-JAX pinhole camera built on ``mujoco.mjx.ray``'s ray-geom intersection: RGB,
depth, segmentation and point clouds, for one environment at a time (``jax.vmap`` it over
environments).

``make_renderer(mj_model, config)`` does the static work once (camera id, per-pixel ray
directions, geom colours and geom types, which geoms are visible, the point-cloud sampling
order) and returns a :class:`Renderer`: a named tuple of pure functions of ``mjx.Data``.

Conventions
-----------
* Image ``[H, W, C]``: row 0 is the top of the image, column 0 the left. The image's
  horizontal axis is the camera-frame x axis; MuJoCo cameras look along their -z axis with
  y up. The principal point is the image centre and pixels are square, with the vertical
  field of view ``cam_fovy`` of the model's camera. Pixel ``(r, c)`` looks along
  ``(c + 0.5 - W/2, H/2 - r - 0.5, -f)`` in the camera frame, ``f = (H/2) / tan(fovy/2)``.
  So a camera on a mirror plane whose x axis is normal to the plane sees the mirrored scene
  as a pure horizontal flip (column ``c`` <-> ``W - 1 - c``): the two rays are exact mirror
  images of each other, bit for bit, before the camera rotation is applied.
* ``data`` must hold the camera pose (``cam_xpos``, ``cam_xmat``) and geom poses
  (``geom_xpos``, ``geom_xmat``) of the current ``qpos``: use it after ``mjx.step`` or
  ``mjx.forward``, or after ``mjx.kinematics`` followed by ``mjx.camlight``.
* Depth is the distance along the camera's viewing axis (``-z``), in metres, i.e. OpenGL
  style "z-depth", not the length of the ray. Pixels whose ray hits nothing, or hits
  beyond ``config.far``, are misses: depth ``config.far``, background colour, segmentation
  ``-1``, and no point in the cloud.
* Rays are cast either with ``mujoco.mjx.ray`` itself, ``jax.vmap``-ed over pixels
  (``ray_impl="mjx"``), or (default, ``"fused"``) with the same per-geom-type formulas
  laid out with pixels on the minor axis and cast in cache-sized chunks, which is several
  times faster on CPU and gives the same geom ids (see ``CameraConfig.ray_impl``).
* Shading is Lambertian with an ambient term. Surface normals are analytic per geom type
  (plane, sphere, capsule, ellipsoid, box). Meshes (``"mjx"`` only) are shaded as if
  facing the camera. Neither implementation intersects cylinders, so cylinder geoms are
  invisible (``make_renderer`` warns about any visible cylinder). Textures are ignored:
  each geom has the single colour MuJoCo would give it without texture (its ``rgba`` if
  that was set, else its material's ``rgba``). No shadows.
* Point clouds are back-projected from the ray hits (``camera position + distance * ray
  direction``), in the world frame, cropped to an axis-aligned workspace box, then
  subsampled deterministically to exactly ``n_points`` (see :func:`make_renderer` and
  ``PointCloudConfig.sampler``).

Mirror equivariance
-------------------
For a scene that is mirror-symmetric about a plane (geometry *and* colours), with the
camera on the plane and its x axis normal to the plane, and the light direction (if not
the default headlight) lying in the plane: ``rgb(mirror(s)) == hflip(rgb(s))`` up to
rounding at geom silhouettes, and ``point_map(mirror(s))`` is the mirror image of
``point_map(s)`` with columns flipped. The default ``"pairs"`` point-cloud sampler keeps
this after subsampling: ``point_cloud(mirror(s))`` equals ``reflect(point_cloud(s))`` as a
multiset (the order of points inside a mirrored pixel pair can differ). The ``"fps"``
sampler is deterministic but does not keep it (greedy ``argmax`` breaks near-ties
differently in the two scenes).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

Array = jax.Array

OUTPUTS = ("rgb", "depth", "segmentation", "points", "point_colors")
SAMPLERS = ("pairs", "fps")
RAY_IMPLS = ("fused", "mjx")
_DEFAULT_GEOM_RGBA = np.array([0.5, 0.5, 0.5, 1.0], dtype=np.float32)
_GT = mujoco.mjtGeom


def _vec3(v, what: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be 3 finite numbers, got {v!r}")
    return tuple(float(x) for x in a)


@dataclasses.dataclass(frozen=True)
class PointCloudConfig:
    """How ``render`` builds its point cloud (``points`` / ``point_colors`` outputs).

    Attributes:
      n_points: number of points N returned.
      workspace_min: world-frame lower corner [3] of the crop box (inclusive).
      workspace_max: world-frame upper corner [3] of the crop box (inclusive).
      sampler: ``"pairs"`` (default; mirror-consistent, see ``make_renderer``) or
        ``"fps"`` (farthest-point sampling; better spatial coverage, slower, not
        mirror-consistent).
    """

    n_points: int = 512
    workspace_min: tuple[float, float, float] = (-1.0, -1.0, -1.0)
    workspace_max: tuple[float, float, float] = (1.0, 1.0, 1.0)
    sampler: str = "pairs"

    def __post_init__(self):
        if not isinstance(self.n_points, int) or self.n_points < 1:
            raise ValueError(f"n_points must be a positive int, got {self.n_points!r}")
        lo = _vec3(self.workspace_min, "workspace_min")
        hi = _vec3(self.workspace_max, "workspace_max")
        if any(a > b for a, b in zip(lo, hi)):
            raise ValueError(f"workspace_min {lo} must be <= workspace_max {hi}")
        object.__setattr__(self, "workspace_min", lo)
        object.__setattr__(self, "workspace_max", hi)
        if self.sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {SAMPLERS}, got {self.sampler!r}")


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Static configuration of one camera. Frozen and hashable.

    Attributes:
      camera: name of an MJCF ``<camera>`` in the model.
      width, height: image size W, H in pixels (any positive size).
      geom_groups: geom groups that are drawn (MuJoCo groups 0..5); other geoms are
        skipped by ``mjx.ray`` and cost nothing.
      flg_static: draw geoms welded to the world body (the table, the floor).
      far: far clip distance in metres; hits beyond it are misses. Also the depth value
        of a miss.
      background: RGB in [0, 1] of a miss.
      ambient, diffuse: shading ``colour * (ambient + diffuse * max(n . l, 0))``.
      light_dir: world-frame direction *towards* the light [3], or ``None`` for a
        headlight (light from the camera, ``l = -ray direction``). For mirror equivariance
        a world light must lie in the mirror plane; the headlight always does.
      rgb_dtype: ``"uint8"`` (0..255) or ``"float32"`` (0..1).
      ray_impl: ``"mjx"`` casts each pixel with ``mujoco.mjx.ray`` under ``jax.vmap``;
        ``"fused"`` (default) runs the same per-geom-type intersection formulas as
        ``mjx.ray`` (same ``safe_div``, same tie order: plane, sphere, capsule, ellipsoid,
        box, then geom id) with pixels on the minor axis, which XLA vectorises several
        times better on CPU. It does not support meshes. The tests check that both agree.
      ray_chunk: ``"fused"`` casts this many pixels per step of a ``lax.map`` (0: all at
        once), so that the [geoms, pixels] temporaries stay in cache; under ``vmap`` over
        B environments a step holds B * ray_chunk rays. 256 was fastest on 2 CPU cores
        for 64 environments at 64x64 (about 2x faster than no chunking).
      outputs: fields ``render`` returns, from ``OUTPUTS``.
      point_cloud: settings for the ``points`` / ``point_colors`` outputs of ``render``.
    """

    camera: str
    width: int = 64
    height: int = 64
    geom_groups: tuple[int, ...] = (0, 1, 2)
    flg_static: bool = True
    far: float = 10.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ambient: float = 0.3
    diffuse: float = 0.7
    light_dir: tuple[float, float, float] | None = None
    rgb_dtype: str = "uint8"
    ray_impl: str = "fused"
    ray_chunk: int = 256
    outputs: tuple[str, ...] = ("rgb",)
    point_cloud: PointCloudConfig = PointCloudConfig()

    def __post_init__(self):
        if not isinstance(self.camera, str) or not self.camera:
            raise ValueError(f"camera must be a non-empty name, got {self.camera!r}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        groups = tuple(int(g) for g in self.geom_groups)
        if not groups or any(g < 0 or g >= mujoco.mjNGROUP for g in groups):
            raise ValueError(f"geom_groups must be non-empty, in 0..5; got {groups}")
        object.__setattr__(self, "geom_groups", tuple(sorted(set(groups))))
        if not (self.far > 0 and math.isfinite(self.far)):
            raise ValueError(f"far must be positive and finite, got {self.far}")
        bg = _vec3(self.background, "background")
        if any(c < 0 or c > 1 for c in bg):
            raise ValueError(f"background must be in [0, 1], got {bg}")
        object.__setattr__(self, "background", bg)
        if self.ambient < 0 or self.diffuse < 0:
            raise ValueError("ambient and diffuse must be >= 0")
        if self.light_dir is not None:
            ld = np.asarray(_vec3(self.light_dir, "light_dir"))
            if np.linalg.norm(ld) < 1e-9:
                raise ValueError("light_dir must be non-zero")
            object.__setattr__(self, "light_dir", tuple(float(x) for x in ld / np.linalg.norm(ld)))
        if not isinstance(self.ray_chunk, int) or self.ray_chunk < 0:
            raise ValueError(f"ray_chunk must be an int >= 0, got {self.ray_chunk!r}")
        if self.ray_impl not in RAY_IMPLS:
            raise ValueError(f"ray_impl must be one of {RAY_IMPLS}, got {self.ray_impl!r}")
        if self.rgb_dtype not in ("uint8", "float32"):
            raise ValueError(f"rgb_dtype must be 'uint8' or 'float32', got {self.rgb_dtype!r}")
        outs = tuple(self.outputs)
        bad = [o for o in outs if o not in OUTPUTS]
        if not outs or bad:
            raise ValueError(f"outputs must be a non-empty subset of {OUTPUTS}; bad: {bad}")
        object.__setattr__(self, "outputs", outs)
        if not isinstance(self.point_cloud, PointCloudConfig):
            raise ValueError("point_cloud must be a PointCloudConfig")


class PointCloud(NamedTuple):
    """A fixed-size point cloud.

    Attributes:
      points: [N, 3] world-frame points.
      colors: [N, 3] float32 shaded colours in [0, 1] (the RGB image at those pixels).
      n_valid: [] int32, number of pixels inside the workspace before subsampling. When it
        is below N the cloud repeats points (see ``make_renderer``); when it is 0 every
        point is the workspace centre and every colour the background.
    """

    points: Array
    colors: Array
    n_valid: Array


class Hits(NamedTuple):
    """Raw result of casting every pixel's ray (one environment).

    Attributes:
      dist: [H, W] distance along the (unit) ray, ``inf`` for a miss.
      geom: [H, W] int32 geom id, -1 for a miss.
      origin: [3] camera position (world frame).
      dirs: [H, W, 3] unit ray directions (world frame).
      cos: [H, W] Lambert term: ``|n . d|`` for the headlight, ``n . l`` for a world
        light (``n`` the surface normal); 1 for a surface without a normal; 0 on a miss.
    """

    dist: Array
    geom: Array
    origin: Array
    dirs: Array
    cos: Array


class Renderer(NamedTuple):
    """Pure functions of one environment's ``mjx.Data``; see :func:`make_renderer`."""

    config: CameraConfig
    cast: Callable[..., Hits]
    rgb: Callable[..., Array]
    depth: Callable[..., Array]
    segmentation: Callable[..., Array]
    point_map: Callable[..., tuple[Array, Array]]
    point_cloud: Callable[..., PointCloud]
    render: Callable[..., dict]


def camera_rays(width: int, height: int, fovy_deg: float) -> np.ndarray:
    """Unit ray directions of every pixel in the camera frame.

    Args:
      width, height: image size W, H.
      fovy_deg: vertical field of view in degrees.

    Returns:
      [H, W, 3] float32 unit vectors; pixel (r, c) looks along
      ``(c + 0.5 - W/2, H/2 - r - 0.5, -f)``, normalised. Columns ``c`` and ``W-1-c`` are
      exact mirror images (x negated bit for bit).
    """
    f = (height / 2.0) / math.tan(math.radians(fovy_deg) / 2.0)
    x = np.arange(width, dtype=np.float64) + 0.5 - width / 2.0
    y = height / 2.0 - np.arange(height, dtype=np.float64) - 0.5
    xx, yy = np.meshgrid(x, y)  # [H, W]
    d = np.stack([xx, yy, np.full_like(xx, -f)], axis=-1)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return d.astype(np.float32)


def _geom_colors(m: mujoco.MjModel) -> np.ndarray:
    """[ngeom, 3] colour MuJoCo gives each geom, ignoring textures."""
    rgba = m.geom_rgba.astype(np.float32).copy()
    for g in range(m.ngeom):
        mat = m.geom_matid[g]
        # An explicit geom rgba (anything but the default) overrides the material.
        if mat >= 0 and np.allclose(m.geom_rgba[g], _DEFAULT_GEOM_RGBA):
            rgba[g] = m.mat_rgba[mat]
    return rgba[:, :3]


def _pair_units(width: int, height: int) -> np.ndarray:
    """[U, 2] pixel-index pairs ``(r, c), (r, W-1-c)`` in a fixed pseudo-random order.

    A pixel on the centre column (odd W) is its own mirror; its second entry is -1.
    """
    units = []
    for r in range(height):
        for c in range((width + 1) // 2):
            c2 = width - 1 - c
            units.append((r * width + c, r * width + c2 if c2 != c else -1))
    units = np.asarray(units, dtype=np.int32).reshape(-1, 2)
    order = np.random.default_rng(0).permutation(len(units))
    return units[order]


def _fit_units(k: Array, budget: Array) -> Array:
    """Which units to take so that their sizes sum to ``budget`` without splitting any.

    Takes the longest prefix (in unit order) that fits, then, if exactly one slot is left,
    the first later unit of size 1. Whole units only, so the choice is the same for a scene
    and its mirror image (a unit's size is mirror-invariant).

    Args:
      k: [U] int32 unit sizes in {0, 1, 2}.
      budget: [] int32.

    Returns:
      [U] bool, units taken. Their sizes sum to ``min(budget, sum(k))`` or one less.
    """
    c = jnp.cumsum(k)
    prefix = c <= budget
    used = jnp.max(jnp.where(prefix, c, 0))
    cand = (k == 1) & ~prefix
    first = jnp.argmax(cand)
    extra = (budget - used >= 1) & cand[first]
    one_hot = jnp.arange(k.shape[0]) == first
    return (prefix & (k > 0)) | (one_hot & extra)


def _compact(take: Array, size: int) -> tuple[Array, Array]:
    """Positions of the first ``size`` True entries of ``take`` [L], and their count."""
    (idx,) = jnp.nonzero(take, size=size, fill_value=0)
    return idx, jnp.minimum(jnp.sum(take), size).astype(jnp.int32)


def _sample_pairs(units: np.ndarray, valid: Array, n: int) -> tuple[Array, Array]:
    """Mirror-consistent deterministic subsampling of valid pixels to exactly ``n`` slots.

    Args:
      units: [U, 2] static pixel pairs in priority order (second entry -1 for a singleton).
      valid: [P] bool, pixel validity (flattened image).
      n: output size N.

    Returns:
      (pix [N] int32 flat pixel index per slot, use_mean [N] bool): slots with ``use_mean``
      hold the mean of the selected points instead of a pixel (at most one slot, and only
      when no whole unit fits the last free slot).
    """
    flat_units = jnp.asarray(units.reshape(-1))
    v_ext = jnp.concatenate([valid, jnp.zeros((1,), bool)])
    v_u = v_ext[jnp.where(flat_units >= 0, flat_units, valid.shape[0])].reshape(-1, 2)
    k = jnp.sum(v_u, axis=1).astype(jnp.int32)

    take1 = _fit_units(k, jnp.int32(n))
    pos1, k1 = _compact((take1[:, None] & v_u).reshape(-1), n)
    # Fewer than N points: repeat the whole selection q times, then whole units again.
    q = n // jnp.maximum(k1, 1)
    rem = n - q * k1
    take2 = _fit_units(jnp.where(take1, k, 0), rem)
    pos2, k2 = _compact((take2[:, None] & v_u).reshape(-1), n)

    s = jnp.arange(n)
    first = s < q * k1
    second = (~first) & (s < q * k1 + k2)
    pos = jnp.where(first, pos1[s % jnp.maximum(k1, 1)], pos2[jnp.clip(s - q * k1, 0, n - 1)])
    pix = flat_units[pos]
    use_mean = ~(first | second)
    return jnp.maximum(pix, 0), use_mean


def _sample_fps(points: Array, valid: Array, n: int) -> Array:
    """Farthest-point sampling of valid points; returns [N] int32 indices into ``points``.

    Starts at the valid point farthest from the centroid of the valid points (lowest index
    on ties). Once every valid point is taken it repeats taken points.
    """
    vf = valid.astype(points.dtype)
    centroid = jnp.sum(points * vf[:, None], 0) / jnp.maximum(jnp.sum(vf), 1.0)
    d0 = jnp.where(valid, jnp.sum((points - centroid) ** 2, -1), -1.0)
    start = jnp.argmax(d0).astype(jnp.int32)

    def body(i, carry):
        idx, mind = carry
        last = points[idx[i - 1]]
        mind = jnp.minimum(mind, jnp.sum((points - last) ** 2, -1))
        return idx.at[i].set(jnp.argmax(mind).astype(jnp.int32)), mind

    mind = jnp.where(valid, jnp.inf, -1.0)
    idx = jnp.zeros((n,), jnp.int32).at[0].set(start)
    idx, _ = jax.lax.fori_loop(1, n, body, (idx, mind))
    return idx


_MINVAL = mujoco.mjMINVAL


def _safe_div(num: Array, den: Array) -> Array:
    # Same as mjx's math.safe_div, so both ray implementations agree bit for bit.
    return num / (den + _MINVAL * (den == 0))


def _quad(a: Array, b: Array, c: Array) -> tuple[Array, Array]:
    """The two roots of ``a x^2 + 2 b x + c = 0``, ``inf`` when absent or negative."""
    det = b * b - a * c
    det2 = jnp.sqrt(jnp.maximum(det, 0.0))
    x0, x1 = _safe_div(-b - det2, a), _safe_div(-b + det2, a)
    bad = det < _MINVAL
    return (jnp.where(bad | (x0 < 0), jnp.inf, x0), jnp.where(bad | (x1 < 0), jnp.inf, x1))


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


# Each takes size [3] x [n, 1], local ray origin p [3] x [n, 1] and local directions
# v [3] x [n, P] as component lists (pixels on the minor axis) and returns [n, P] distances.
def _hit_plane(s, p, v):
    x = -_safe_div(p[2], v[2])
    ok = (v[2] <= -_MINVAL) & (x >= 0)
    for i in (0, 1):
        ok &= (s[i] <= 0) | (jnp.abs(p[i] + x * v[i]) <= s[i])
    return jnp.where(ok, x, jnp.inf)


def _hit_sphere(s, p, v):
    x0, x1 = _quad(_dot(v, v), _dot(v, p), _dot(p, p) - s[0] * s[0])
    return jnp.where(jnp.isinf(x0), x1, x0)


def _hit_capsule(s, p, v):
    r, h = s[0], s[1]
    x0, x1 = _quad(v[0] * v[0] + v[1] * v[1], v[0] * p[0] + v[1] * p[1],
                   p[0] * p[0] + p[1] * p[1] - r * r)
    x = jnp.where(jnp.isinf(x0), x1, x0)
    x = jnp.where(jnp.abs(p[2] + x * v[2]) <= h, x, jnp.inf)
    vv = _dot(v, v)
    for sign in (1.0, -1.0):
        dif = (p[0], p[1], p[2] - sign * h)
        y0, y1 = _quad(vv, _dot(v, dif), _dot(dif, dif) - r * r)
        for y in (y0, y1):
            z = p[2] + y * v[2]
            cap = (z >= h) if sign > 0 else (z <= -h)
            x = jnp.where(cap & (y < x), y, x)
    return x


def _hit_ellipsoid(s, p, v):
    inv = [_safe_div(1.0, s[i] * s[i]) for i in range(3)]
    sv = [inv[i] * v[i] for i in range(3)]
    x0, x1 = _quad(_dot(sv, v), _dot(sv, p), sum(inv[i] * p[i] * p[i] for i in range(3)) - 1)
    return jnp.where(jnp.isinf(x0), x1, x0)


def _hit_box(s, p, v):
    best = None
    for sign in (1.0, -1.0):  # mjx order: all +size faces, then all -size faces
        for a in range(3):
            x = _safe_div(sign * s[a] - p[a], v[a])
            b, c = [i for i in range(3) if i != a]
            ok = (jnp.abs(p[b] + x * v[b]) <= s[b]) & (jnp.abs(p[c] + x * v[c]) <= s[c]) & (x >= 0)
            x = jnp.where(ok, x, jnp.inf)
            best = x if best is None else jnp.minimum(best, x)
    return best


_HIT_FUNCS = (
    (_GT.mjGEOM_PLANE, _hit_plane),
    (_GT.mjGEOM_SPHERE, _hit_sphere),
    (_GT.mjGEOM_CAPSULE, _hit_capsule),
    (_GT.mjGEOM_ELLIPSOID, _hit_ellipsoid),
    (_GT.mjGEOM_BOX, _hit_box),
)


_SHADED_TYPES = (_GT.mjGEOM_PLANE, _GT.mjGEOM_SPHERE, _GT.mjGEOM_CAPSULE,
                 _GT.mjGEOM_ELLIPSOID, _GT.mjGEOM_BOX)


def _local_normals(p, size, is_type) -> list:
    """Outward unit normals at geom-local points, one component array [K] per axis.

    Args:
      p: 3 arrays [K], local hit point. size: 3 arrays [K], geom size.
      is_type: dict geom type -> [K] bool (types from ``_SHADED_TYPES``).

    Returns:
      3 arrays [K]; all zero for a geom type without an analytic normal (mesh).
    """
    def unit(v):
        inv = jax.lax.rsqrt(jnp.maximum(v[0] * v[0] + v[1] * v[1] + v[2] * v[2], 1e-24))
        return [c * inv for c in v]

    sphere = unit(p)
    ellipsoid = unit([p[i] / jnp.maximum(size[i], 1e-9) ** 2 for i in range(3)])
    capsule = unit([p[0], p[1], p[2] - jnp.clip(p[2], -size[1], size[1])])
    rel = [jnp.abs(p[i]) / jnp.maximum(size[i], 1e-9) for i in range(3)]
    fx = (rel[0] >= rel[1]) & (rel[0] >= rel[2])  # ties (edges): lowest axis, like argmax
    fy = ~fx & (rel[1] >= rel[2])
    fz = ~fx & ~fy
    box = [jnp.where(f, jnp.sign(p[i]), 0.0) for i, f in enumerate((fx, fy, fz))]
    zero = jnp.zeros_like(p[0])
    plane = [zero, zero, jnp.ones_like(p[0])]
    out = [zero, zero, zero]
    for gtype, n in ((_GT.mjGEOM_PLANE, plane), (_GT.mjGEOM_SPHERE, sphere),
                     (_GT.mjGEOM_CAPSULE, capsule), (_GT.mjGEOM_ELLIPSOID, ellipsoid),
                     (_GT.mjGEOM_BOX, box)):
        out = [jnp.where(is_type[gtype], n[i], out[i]) for i in range(3)]
    return out


def _cast_fused(groups, geom_xpos: Array, geom_xmat: Array, origin: Array, dirs: Array,
                light: Array | None) -> tuple[Array, Array, Array]:
    """Nearest hit of rays ``origin + t * dirs`` [P, 3] against static geom groups.

    Args:
      groups: static list of (geom type, hit_fn, geom ids np [n], sizes np [n, 3]).
      geom_xpos: [ngeom, 3]; geom_xmat: [ngeom, 3, 3] world poses.
      origin: [3]; dirs: [P, 3] world frame, unit.
      light: world direction [3] towards the light, or None for the headlight.

    Returns:
      dist [P] (-1 for a miss) and geom id [P] (int32, -1 for a miss), like mjx.ray; and
      the Lambert term [P] (see ``Hits.cos``), computed in the hit geom's local frame,
      where the ray's local origin and direction are already at hand.
    """
    n_rays = dirs.shape[0]
    if not groups:
        return -jnp.ones((n_rays,), dirs.dtype), -jnp.ones((n_rays,), jnp.int32), jnp.zeros(
            (n_rays,), dirs.dtype)
    dists, ps, vs, ls = [], [], [], []
    for _, fn, gid, size in groups:
        rot = geom_xmat[gid]  # [n, 3, 3]
        p = jnp.einsum("nji,nj->in", rot, origin - geom_xpos[gid])[..., None]  # [3, n, 1]
        v = jnp.einsum("pj,nji->inp", dirs, rot)  # [3, n, P]
        s = jnp.asarray(size.T)[..., None]  # [3, n, 1]
        dists.append(fn(list(s), list(p), list(v)))
        ps.append(p)
        vs.append(v)
        if light is not None:
            ls.append(jnp.einsum("j,nji->in", light, rot)[..., None])  # [3, n, 1]
    dist = jnp.concatenate(dists, axis=0)  # [G, P]
    ids = jnp.asarray(np.concatenate([g[2] for g in groups]).astype(np.int32))
    k = jnp.argmin(dist, axis=0)
    best = jnp.min(dist, axis=0)
    miss = jnp.isinf(best)

    # The winner's local ray, size and type, by masked sums over the geoms (vectorises,
    # unlike a gather); then its analytic normal in its own frame. Dot products do not
    # change under rotation, so no world-frame normal is needed.
    bounds = np.cumsum([0] + [len(g[2]) for g in groups])
    sizes = np.concatenate([g[3] for g in groups]).astype(np.float32)  # [G, 3]
    all_ids = np.concatenate([g[2] for g in groups])
    per_geom = jnp.concatenate([jnp.concatenate(ps, axis=1)[..., 0].T, jnp.asarray(sizes),
                                geom_xmat[all_ids].reshape(-1, 9)], 1)  # [G, 15]
    att = jnp.take(per_geom, k, axis=0).T  # [15, P]
    p_k, s_k = list(att[0:3]), list(att[3:6])
    v_k = [att[6 + i] * dirs[:, 0] + att[9 + i] * dirs[:, 1] + att[12 + i] * dirs[:, 2]
           for i in range(3)]
    is_type = {t: jnp.zeros_like(miss) for t in _SHADED_TYPES}
    for (gtype, _, _, _), a, b in zip(groups, bounds[:-1], bounds[1:]):
        is_type[gtype] = (k >= a) & (k < b)
    t = jnp.where(miss, 0.0, best)
    n = _local_normals([p_k[i] + t * v_k[i] for i in range(3)], s_k, is_type)
    if light is None:
        cos = jnp.abs(n[0] * v_k[0] + n[1] * v_k[1] + n[2] * v_k[2])
    else:
        l_k = list(jnp.take(jnp.concatenate(ls, axis=1)[..., 0].T, k, axis=0).T)
        cos = n[0] * l_k[0] + n[1] * l_k[1] + n[2] * l_k[2]
    cos = jnp.where(miss, 0.0, cos)
    return jnp.where(miss, -1.0, best), jnp.where(miss, -1, ids[k]), cos


def make_renderer(
    mj_model: mujoco.MjModel,
    config: CameraConfig,
    mjx_model: mjx.Model | None = None,
) -> Renderer:
    """Build a camera renderer for ``config.camera`` of ``mj_model``.

    Args:
      mj_model: the MuJoCo model. Its camera must use ``fovy`` (no ``sensorsize``). For
        ``ray_impl="mjx"`` it needs at least one ``<material>`` (``mjx.ray`` indexes
        ``mat_rgba``).
      config: the static camera configuration.
      mjx_model: for ``ray_impl="mjx"``, the ``mjx.put_model(mj_model, impl="jax")`` to
        ray-cast against, if you already have one; built otherwise. Unused by
        ``"fused"``, which needs only the static arrays of ``mj_model``.

    Returns:
      A :class:`Renderer` whose functions all take one environment's ``mjx.Data``:

      * ``cast(data) -> Hits`` (dist [H, W], geom [H, W], origin [3], dirs [H, W, 3],
        cos [H, W]), the raw ray cast the others are made from;
      * ``rgb(data) -> [H, W, 3]`` uint8 or float32 (``config.rgb_dtype``);
      * ``depth(data) -> [H, W]`` float32 z-depth in metres, ``config.far`` on misses;
      * ``segmentation(data) -> [H, W]`` int32 geom id, -1 on misses;
      * ``point_map(data) -> (points [H, W, 3], hit [H, W] bool)`` world-frame hit point
        of every pixel (misses hold the camera position);
      * ``point_cloud(data, n_points, workspace_min=None, workspace_max=None,
        sampler=None) -> PointCloud`` (points [N, 3], colors [N, 3], n_valid []);
        ``n_points`` and ``sampler`` are static, the bounds [3] may be traced, and
        ``None`` takes the value from ``config.point_cloud``;
      * ``render(data) -> dict`` with the fields in ``config.outputs`` (one ray cast
        shared by all of them); ``points`` / ``point_colors`` follow
        ``config.point_cloud``.

      The ``"pairs"`` sampler groups pixels into mirror pairs ``(r, c), (r, W-1-c)`` in a
      fixed pseudo-random order and takes whole pairs of valid (in-workspace) pixels until
      N points are chosen; if one slot is left it takes the next pair with exactly one
      valid pixel. Fewer than N valid points are repeated whole, then whole pairs again;
      a last slot that no whole pair fits holds the mean of the chosen points. Since a
      pair's validity count is mirror-invariant, the mirrored scene chooses the mirrored
      pixels: the cloud is mirror-consistent as a multiset.
    """
    cfg = config
    cam_id = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_CAMERA, cfg.camera)
    if cam_id < 0:
        names = [mujoco.mj_id2name(mj_model, mujoco.mjtObj.mjOBJ_CAMERA, i)
                 for i in range(mj_model.ncam)]
        raise ValueError(f"no camera named {cfg.camera!r}; cameras: {names}")
    if cfg.ray_impl == "mjx" and mj_model.nmat == 0:
        raise ValueError("mjx.ray needs at least one <material> in the model")
    if np.any(mj_model.cam_sensorsize[cam_id] > 0):
        raise ValueError(f"camera {cfg.camera!r} uses sensorsize/focal; only fovy is supported")

    group_mask = tuple(int(g in cfg.geom_groups) for g in range(mujoco.mjNGROUP))
    drawn = np.array([group_mask[min(int(g), mujoco.mjNGROUP - 1)] for g in mj_model.geom_group],
                     dtype=bool)
    if not cfg.flg_static:
        drawn &= mj_model.body_weldid[mj_model.geom_bodyid] != 0
    cyl = np.nonzero(drawn & (mj_model.geom_type == _GT.mjGEOM_CYLINDER))[0]
    if cyl.size:
        names = [mujoco.mj_id2name(mj_model, mujoco.mjtObj.mjOBJ_GEOM, int(g)) or f"#{g}"
                 for g in cyl]
        warnings.warn(f"mjx.ray ignores cylinders; invisible to camera {cfg.camera!r}: {names}")

    # mjx.ray also skips fully transparent geoms; for a fixed model that is static.
    mat_a = np.append(mj_model.mat_rgba[:, 3], 1.0)[mj_model.geom_matid]  # -1 -> 1.0
    drawn &= ((mj_model.geom_matid != -1) | (mj_model.geom_rgba[:, 3] != 0)) & (mat_a != 0)
    fused_groups = []
    for gtype, fn in _HIT_FUNCS:
        (gid,) = np.nonzero(drawn & (mj_model.geom_type == gtype))
        if gid.size:
            fused_groups.append((gtype, fn, gid, mj_model.geom_size[gid].astype(np.float32)))
    if cfg.ray_impl == "fused" and np.any(drawn & (mj_model.geom_type == _GT.mjGEOM_MESH)):
        raise ValueError("ray_impl='fused' does not draw meshes; use ray_impl='mjx'")

    m = mjx_model
    if m is None and cfg.ray_impl == "mjx":
        # On this process's first device (MJX's default is the global device 0).
        m = mjx.put_model(mj_model, impl="jax", device=jax.local_devices()[0])
    dirs_cam = jnp.asarray(camera_rays(cfg.width, cfg.height, float(mj_model.cam_fovy[cam_id])))
    zscale = -dirs_cam[..., 2]  # z-depth per unit of ray length
    colors = jnp.asarray(_geom_colors(mj_model))
    geom_static = jnp.asarray(np.concatenate(  # [ngeom, 3 + ntypes]: size, type flags
        [mj_model.geom_size] + [(mj_model.geom_type == t)[:, None] for t in _SHADED_TYPES],
        axis=1).astype(np.float32))
    background = jnp.asarray(cfg.background, jnp.float32)
    light = None if cfg.light_dir is None else jnp.asarray(cfg.light_dir, jnp.float32)
    units = _pair_units(cfg.width, cfg.height)
    pc_cfg = cfg.point_cloud
    H, W = cfg.height, cfg.width
    chunk = cfg.ray_chunk if cfg.ray_chunk > 0 else H * W

    def cast(data: mjx.Data) -> Hits:
        """Cast every pixel's ray.

        Returns:
          Hits(dist [H, W], geom [H, W], origin [3], dirs [H, W, 3], cos [H, W]).
        """
        origin = data.cam_xpos[cam_id]
        rot = data.cam_xmat[cam_id]
        dirs = dirs_cam @ rot.T  # [H, W, 3] world frame
        flat = dirs.reshape(-1, 3)
        if cfg.ray_impl == "mjx":
            ray = lambda v: mjx.ray(m, data, origin, v, group_mask, cfg.flg_static)
            dist, geom = jax.vmap(ray)(flat)
            cos = _lambert_world(data, origin, dist, geom.astype(jnp.int32), flat)
        else:
            cast_chunk = lambda d: _cast_fused(fused_groups, data.geom_xpos, data.geom_xmat,
                                               origin, d, light)
            if chunk < flat.shape[0]:
                # Chunks of pixels keep the [geoms, pixels] temporaries in cache.
                n_chunks = -(-flat.shape[0] // chunk)
                pad = n_chunks * chunk - flat.shape[0]
                flat = jnp.concatenate([flat, jnp.broadcast_to(flat[:1], (pad, 3))])
                out = jax.lax.map(cast_chunk, flat.reshape(n_chunks, chunk, 3))
                dist, geom, cos = (x.reshape(-1)[: H * W] for x in out)
            else:
                dist, geom, cos = cast_chunk(flat)
        dist, cos = dist.reshape(H, W), cos.reshape(H, W)
        geom = geom.reshape(H, W).astype(jnp.int32)
        hit = (geom >= 0) & (dist <= cfg.far)
        return Hits(jnp.where(hit, dist, jnp.inf), jnp.where(hit, geom, -1), origin, dirs,
                    jnp.where(hit, cos, 0.0))

    def _lambert_world(data: mjx.Data, origin: Array, dist: Array, geom: Array,
                       dirs: Array) -> Array:
        """Lambert term [K] of rays dist [K], geom [K], dirs [K, 3] (for ray_impl="mjx")."""
        hit = geom >= 0
        g = jnp.maximum(geom, 0)
        d = list(dirs.T)  # 3 x [K]: components on the minor axis
        rot = data.geom_xmat[g]  # [K, 3, 3]
        rel = (origin + jnp.where(hit, dist, 0.0)[:, None] * dirs - data.geom_xpos[g])
        p_loc = list(jnp.einsum("kji,kj->ik", rot, rel))
        attrs = geom_static[g].T  # [3 + ntypes, K]
        is_type = {t: attrs[3 + i] > 0.5 for i, t in enumerate(_SHADED_TYPES)}
        n_loc = jnp.stack(_local_normals(p_loc, list(attrs[:3]), is_type), axis=-1)
        n = list(jnp.einsum("kij,kj->ik", rot, n_loc))
        no_normal = n[0] * n[0] + n[1] * n[1] + n[2] * n[2] < 0.5  # mesh: faces the camera
        if light is None:
            cos = jnp.where(no_normal, 1.0, jnp.abs(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]))
        else:
            n = [jnp.where(no_normal, -d[i], n[i]) for i in range(3)]
            cos = n[0] * light[0] + n[1] * light[1] + n[2] * light[2]
        return jnp.where(hit, cos, 0.0)

    def _colour(geom: Array, cos: Array) -> Array:
        """Float colours [..., 3] in [0, 1] from geom ids [...] and Lambert terms [...]."""
        shade = cfg.ambient + cfg.diffuse * jnp.maximum(cos, 0.0)
        lit = jnp.clip(colors[jnp.maximum(geom, 0)] * shade[..., None], 0.0, 1.0)
        return jnp.where((geom >= 0)[..., None], lit, background)

    def _to_dtype(img: Array) -> Array:
        if cfg.rgb_dtype == "uint8":
            return jnp.round(img * 255.0).astype(jnp.uint8)
        return img.astype(jnp.float32)

    def _depth(hits: Hits) -> Array:
        return jnp.where(hits.geom >= 0, hits.dist * zscale, cfg.far)

    def _point_map(hits: Hits) -> tuple[Array, Array]:
        hit = hits.geom >= 0
        t = jnp.where(hit, hits.dist, 0.0)
        return hits.origin + t[..., None] * hits.dirs, hit

    def _cloud(hits: Hits, n_points: int, lo, hi, sampler: str) -> PointCloud:
        pts, hit = _point_map(hits)
        pts, hit = pts.reshape(-1, 3), hit.reshape(-1)
        lo = jnp.asarray(pc_cfg.workspace_min if lo is None else lo, jnp.float32)
        hi = jnp.asarray(pc_cfg.workspace_max if hi is None else hi, jnp.float32)
        valid = hit & jnp.all((pts >= lo) & (pts <= hi), axis=-1)
        n_valid = jnp.sum(valid).astype(jnp.int32)
        # Colour only the chosen pixels.
        geom, cos = hits.geom.reshape(-1), hits.cos.reshape(-1)
        shade_at = lambda i: _colour(geom[i], cos[i])
        if sampler == "fps":
            idx = _sample_fps(pts, valid, n_points)
            out_p, out_c = pts[idx], shade_at(idx)
        else:
            pix, use_mean = _sample_pairs(units, valid, n_points)
            out_p, out_c = pts[pix], shade_at(pix)
            chosen = (~use_mean).astype(jnp.float32)[:, None]
            denom = jnp.maximum(jnp.sum(chosen), 1.0)
            mean_p = jnp.sum(out_p * chosen, 0) / denom
            mean_c = jnp.sum(out_c * chosen, 0) / denom
            out_p = jnp.where(use_mean[:, None], mean_p, out_p)
            out_c = jnp.where(use_mean[:, None], mean_c, out_c)
        none = n_valid == 0
        out_p = jnp.where(none, (lo + hi) / 2.0, out_p)
        out_c = jnp.where(none, background, out_c)
        return PointCloud(out_p, out_c, n_valid)

    def rgb(data: mjx.Data) -> Array:
        """[H, W, 3] shaded image (uint8 0..255 or float32 0..1, per config)."""
        hits = cast(data)
        return _to_dtype(_colour(hits.geom, hits.cos))

    def depth(data: mjx.Data) -> Array:
        """[H, W] float32 z-depth in metres; ``config.far`` where nothing is hit."""
        return _depth(cast(data))

    def segmentation(data: mjx.Data) -> Array:
        """[H, W] int32 geom id of each pixel, -1 where nothing is hit."""
        return cast(data).geom

    def point_map(data: mjx.Data) -> tuple[Array, Array]:
        """World-frame hit point of every pixel: (points [H, W, 3], hit [H, W] bool)."""
        return _point_map(cast(data))

    def point_cloud(data: mjx.Data, n_points: int | None = None, workspace_min=None,
                    workspace_max=None, sampler: str | None = None) -> PointCloud:
        """Workspace-cropped cloud of exactly N points: PointCloud([N, 3], [N, 3], [])."""
        n = pc_cfg.n_points if n_points is None else int(n_points)
        smp = pc_cfg.sampler if sampler is None else sampler
        if n < 1 or smp not in SAMPLERS:
            raise ValueError(f"need n_points >= 1 and sampler in {SAMPLERS}")
        return _cloud(cast(data), n, workspace_min, workspace_max, smp)

    def render(data: mjx.Data) -> dict:
        """Dict with the ``config.outputs`` fields, from one shared ray cast."""
        hits = cast(data)
        out = {}
        if "rgb" in cfg.outputs:
            out["rgb"] = _to_dtype(_colour(hits.geom, hits.cos))
        if "depth" in cfg.outputs:
            out["depth"] = _depth(hits)
        if "segmentation" in cfg.outputs:
            out["segmentation"] = hits.geom
        if "points" in cfg.outputs or "point_colors" in cfg.outputs:
            pc = _cloud(hits, pc_cfg.n_points, None, None, pc_cfg.sampler)
            if "points" in cfg.outputs:
                out["points"] = pc.points
            if "point_colors" in cfg.outputs:
                out["point_colors"] = pc.colors
        return out

    return Renderer(cfg, cast, rgb, depth, segmentation, point_map, point_cloud, render)
