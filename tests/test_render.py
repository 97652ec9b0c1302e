"""Tests of the mjx.ray camera renderer: shapes, hand-checked pixels, depth, mirror
equivariance of images and point clouds, agreement of the two ray implementations."""

from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.sim.render import (
    CameraConfig,
    PointCloudConfig,
    camera_rays,
    make_renderer,
)
from equibim_jax.symmetry import Mirror, derive_symmetry, flip_image, reflect_points

# A scene mirror-symmetric about y = 0 in geometry and colour: a table, two mirrored
# two-link "arms" (hinges about x and about y), two free objects that are themselves
# symmetric, a floor in group 3 (hidden by default), and two cameras on the plane.
# "top" looks straight down from 1 m above the table top (z = 0), image x = world +y;
# "front" looks down at 45 degrees from behind, image x = world -y.
SCENE_XML = """
<mujoco model="render_test">
  <default><geom contype="0" conaffinity="0"/></default>
  <asset>
    <material name="table_mat" rgba="0.6 0.45 0.3 1"/>
    <material name="red_mat" rgba="0.9 0.1 0.1 1"/>
  </asset>
  <worldbody>
    <camera name="top" pos="0 0 1.0" xyaxes="0 1 0 -1 0 0" fovy="60"/>
    <camera name="front" pos="-0.7 0 0.7" xyaxes="0 -1 0 0.7071068 0 0.7071068" fovy="55"/>
    <geom name="floor" type="plane" size="2 2 0.1" pos="0 0 -0.5" rgba="0.2 0.2 0.8 1" group="3"/>
    <geom name="table" type="box" size="0.3 0.4 0.02" pos="0 0 -0.02" material="table_mat"/>
    <body name="left_link" pos="0.1 0.2 0.15">
      <joint name="left_hinge" type="hinge" axis="1 0 0"/>
      <geom name="left_capsule" type="capsule" fromto="0 0 0 0 0.12 0" size="0.025" material="red_mat"/>
      <body name="left_tip" pos="0 0.12 0">
        <joint name="left_tip_hinge" type="hinge" axis="0 1 0"/>
        <geom name="left_sphere" type="sphere" size="0.03" pos="0.05 0 0" rgba="0.1 0.8 0.8 1"/>
        <geom name="left_ell" type="ellipsoid" size="0.04 0.02 0.015" pos="-0.05 0 0" rgba="0.8 0.8 0.1 1"/>
      </body>
    </body>
    <body name="right_link" pos="0.1 -0.2 0.15">
      <joint name="right_hinge" type="hinge" axis="1 0 0"/>
      <geom name="right_capsule" type="capsule" fromto="0 0 0 0 -0.12 0" size="0.025" material="red_mat"/>
      <body name="right_tip" pos="0 -0.12 0">
        <joint name="right_tip_hinge" type="hinge" axis="0 1 0"/>
        <geom name="right_sphere" type="sphere" size="0.03" pos="0.05 0 0" rgba="0.1 0.8 0.8 1"/>
        <geom name="right_ell" type="ellipsoid" size="0.04 0.02 0.015" pos="-0.05 0 0" rgba="0.8 0.8 0.1 1"/>
      </body>
    </body>
    <body name="cube" pos="-0.15 0 0.03">
      <freejoint name="cube_free"/>
      <geom name="cube_geom" type="box" size="0.03 0.02 0.03" rgba="0.1 0.8 0.1 1"/>
    </body>
    <body name="stick" pos="0.2 0 0.03">
      <freejoint name="stick_free"/>
      <geom name="stick_geom" type="capsule" size="0.015 0.05" quat="0.7071068 0 0.7071068 0" rgba="0.9 0.5 0.9 1"/>
    </body>
  </worldbody>
</mujoco>
"""

ROBOT_A = pathlib.Path(__file__).resolve().parents[1] / "equibim_jax/sim/assets/robot_a.xml"
MIRROR = Mirror.from_axis("y")
ALL_OUTPUTS = ("rgb", "depth", "segmentation", "points", "point_colors")
WORKSPACE = PointCloudConfig(n_points=256, workspace_min=(-0.3, -0.4, 0.005),
                             workspace_max=(0.3, 0.4, 0.5))


class _Scene:
    """The test scene, its derived symmetry, a forward function, and jitted renderers."""

    def __init__(self, xml: str):
        self.mj_model = mujoco.MjModel.from_xml_string(xml)
        self.m = mjx.put_model(self.mj_model, impl="jax")
        self.ms = derive_symmetry(self.mj_model, MIRROR)
        self.forward = _make_forward(self.mj_model)
        self._cache = {}

    def renderer(self, **kw):
        """(Renderer, jitted render) for CameraConfig(**kw), compiled once per config."""
        cfg = CameraConfig(**kw)
        if cfg not in self._cache:
            r = make_renderer(self.mj_model, cfg, self.m)
            self._cache[cfg] = (r, jax.jit(r.render))
        return self._cache[cfg]

    def cloud(self, n_points=256, sampler="pairs"):
        """Jitted (data, lo [3], hi [3]) -> PointCloud of the "front" camera."""
        key = ("cloud", n_points, sampler)
        if key not in self._cache:
            r = self.renderer(camera="front")[0]
            self._cache[key] = jax.jit(
                lambda d, lo, hi: r.point_cloud(d, n_points, lo, hi, sampler=sampler))
        return self._cache[key]


@pytest.fixture(scope="module")
def scene():
    return _Scene(SCENE_XML)


def _make_forward(mj_model):
    """qpos [nq] -> mjx.Data with geom and camera poses, by MuJoCo C forward kinematics.

    (Compiling mjx.kinematics for robot_a took ~15 s on 2 shared cores; this takes ms.)
    """
    d = mujoco.MjData(mj_model)

    def forward(qpos):
        d.qpos[:] = np.asarray(qpos)
        mujoco.mj_kinematics(mj_model, d)
        mujoco.mj_camlight(mj_model, d)
        return mjx.put_data(mj_model, d, impl="jax")

    return forward


def _batched(fn, base):
    """vmap ``fn(data)`` over batched geom and camera poses, other fields from ``base``."""
    def one(gx, gm, cx, cm):
        return fn(base.replace(geom_xpos=gx, geom_xmat=gm, cam_xpos=cx, cam_xmat=cm))

    def run(datas):
        stack = lambda f: jnp.stack([getattr(x, f) for x in datas])
        return jax.jit(jax.vmap(one))(*(stack(f) for f in
                                         ("geom_xpos", "geom_xmat", "cam_xpos", "cam_xmat")))

    return run


def _random_scene_qpos(mj_model, rng) -> np.ndarray:
    """Random hinge angles and free-object poses (not mirror-symmetric)."""
    q = mj_model.qpos0.copy()
    for j in range(mj_model.njnt):
        adr = mj_model.jnt_qposadr[j]
        if mj_model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            q[adr] = rng.uniform(-1.2, 1.2)
        elif mj_model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            q[adr:adr + 3] = rng.uniform([-0.2, -0.3, 0.03], [0.2, 0.3, 0.1])
            quat = rng.normal(size=4)
            q[adr + 3:adr + 7] = quat / np.linalg.norm(quat)
    return q


def _set_free(mj_model, q, body, pos):
    j = mj_model.body_jntadr[mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, body)]
    adr = mj_model.jnt_qposadr[j]
    q = q.copy()
    q[adr:adr + 3] = pos
    return q


def _equal_fraction(a, b) -> tuple[float, int]:
    """Fraction of pixels [H, W, ...] equal in all channels, and the count that differ."""
    eq = np.all(np.asarray(a) == np.asarray(b), axis=tuple(range(2, np.ndim(a))))
    return float(eq.mean()), int((~eq).sum())


def _assert_close_mostly(a, b, tol=1e-5, worst=2e-4):
    """float32 agreement: 99.9% of entries within tol, all within worst (metres).

    Rays that graze a surface turn the ~1e-7 rounding of poses into ~1e-5 of distance.
    """
    err = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
    err = err.reshape(err.shape[0], -1).max(-1) if err.ndim > 1 else err
    assert (err <= tol).mean() >= 0.999 and err.max() <= worst, (err.max(), (err > tol).sum())


def _same_multiset(a, b, tol=2e-4) -> bool:
    """Whether point sets a, b [N, 3] are equal as multisets (points within tol)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d_ab = np.linalg.norm(a[:, None] - b[None], axis=-1) < tol
    d_aa = np.linalg.norm(a[:, None] - a[None], axis=-1) < tol
    d_bb = np.linalg.norm(b[:, None] - b[None], axis=-1) < tol
    return bool(np.all(d_ab.sum(1) == d_aa.sum(1)) and np.all(d_ab.sum(0) == d_bb.sum(1)))


# --------------------------------------------------------------------------- config

TOP = dict(camera="top", outputs=("rgb", "depth", "segmentation"))
# One "front" config for most tests: each distinct config costs a compile.
FRONT = dict(camera="front", outputs=ALL_OUTPUTS, point_cloud=WORKSPACE)
FRONT_IMG = dict(camera="front", outputs=("rgb", "depth", "segmentation"))
LO, HI = jnp.array([-0.3, -0.4, 0.005]), jnp.array([0.3, 0.4, 0.5])


def test_config_validation(scene):
    with pytest.raises(ValueError):
        CameraConfig("top", width=0)
    with pytest.raises(ValueError):
        CameraConfig("top", geom_groups=(7,))
    with pytest.raises(ValueError):
        CameraConfig("top", outputs=("nope",))
    with pytest.raises(ValueError):
        CameraConfig("top", ray_impl="gl")
    with pytest.raises(ValueError):
        PointCloudConfig(workspace_min=(1, 0, 0), workspace_max=(0, 1, 1))
    with pytest.raises(ValueError):
        make_renderer(scene.mj_model, CameraConfig("no_such_camera"), scene.m)
    assert hash(CameraConfig("top")) == hash(CameraConfig("top"))
    assert CameraConfig("top", geom_groups=(2, 0, 1)) == CameraConfig("top")


def test_camera_rays_mirror_exact():
    d = camera_rays(8, 6, 60.0)
    assert d.shape == (6, 8, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=1e-6)
    # Column c and W-1-c: x negated bit for bit, y and z identical.
    np.testing.assert_array_equal(d[:, ::-1, 0], -d[:, :, 0])
    np.testing.assert_array_equal(d[:, ::-1, 1:], d[:, :, 1:])
    assert np.all(d[0, :, 1] > 0) and np.all(d[:, 0, 0] < 0)  # row 0 top, column 0 left
    # Vertical field of view: the top and bottom pixel edges are fovy apart.
    f = 3 / np.tan(np.radians(30.0))
    np.testing.assert_allclose(d[0, 4, 1] / -d[0, 4, 2], 2.5 / f, rtol=1e-6)


# --------------------------------------------------------------------------- outputs


def test_shapes_dtypes_64_and_vmap(scene):
    r1, render = scene.renderer(**FRONT)
    rng = np.random.default_rng(3)
    qs = np.stack([_random_scene_qpos(scene.mj_model, rng) for _ in range(3)])
    datas = [scene.forward(q) for q in qs]
    batched = _batched(r1.render, datas[0])(datas)
    for i in range(3):
        out = render(datas[i])
        assert out["rgb"].shape == (64, 64, 3) and out["rgb"].dtype == jnp.uint8
        assert out["depth"].shape == (64, 64) and out["depth"].dtype == jnp.float32
        assert out["segmentation"].shape == (64, 64) and out["segmentation"].dtype == jnp.int32
        assert out["points"].shape == (256, 3) and out["point_colors"].shape == (256, 3)
        assert np.all(np.isfinite(out["depth"])) and np.all(np.isfinite(out["points"]))
        # vmap over environments gives the per-environment frames.
        for k in ("rgb", "segmentation"):
            frac, _ = _equal_fraction(batched[k][i][..., None], out[k][..., None])
            assert frac >= 0.999


@pytest.mark.parametrize("res", [96, 128])
def test_shapes_dtypes_larger(scene, res):
    _, render = scene.renderer(**FRONT_IMG, width=res, height=res)
    out = render(scene.forward(jnp.asarray(scene.mj_model.qpos0)))
    assert out["rgb"].shape == (res, res, 3) and out["rgb"].dtype == jnp.uint8
    assert out["depth"].shape == (res, res) and out["depth"].dtype == jnp.float32
    assert out["segmentation"].shape == (res, res)


def test_non_square_and_float_rgb(scene):
    r = make_renderer(scene.mj_model, CameraConfig("top", width=40, height=30,
                                                   rgb_dtype="float32"), scene.m)
    img = jax.jit(r.rgb)(scene.forward(jnp.asarray(scene.mj_model.qpos0)))
    assert img.shape == (30, 40, 3) and img.dtype == jnp.float32
    assert float(img.min()) >= 0.0 and float(img.max()) <= 1.0


def test_centre_colour_corner_background_and_table_depth(scene):
    mj_model = scene.mj_model
    r, render = scene.renderer(**TOP)
    out = render(scene.forward(jnp.asarray(mj_model.qpos0)))
    table = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    # Pixel (32, 32) looks (almost) straight down at the table top: its material colour
    # times (0.3 + 0.7 |n.d|), |n.d| = -d_z of that pixel's ray.
    shade = 0.3 + 0.7 * -camera_rays(64, 64, 60.0)[32, 32, 2]
    assert int(out["segmentation"][32, 32]) == table
    np.testing.assert_allclose(np.asarray(out["rgb"][32, 32], float),
                               255 * shade * np.array([0.6, 0.45, 0.3]), atol=0.51)
    # Corners look past the table (half-width 0.58 m at 1 m > 0.3, 0.4): background.
    for r_, c_ in [(0, 0), (0, 63), (63, 0), (63, 63)]:
        assert int(out["segmentation"][r_, c_]) == -1
        np.testing.assert_array_equal(np.asarray(out["rgb"][r_, c_]), [0, 0, 0])
        assert float(out["depth"][r_, c_]) == r.config.far
    # z-depth of the flat table top is the camera height (1 m) at every table pixel.
    on_table = np.asarray(out["segmentation"]) == table
    assert on_table.sum() > 1000
    np.testing.assert_allclose(np.asarray(out["depth"])[on_table], 1.0, atol=1e-5)
    # And the back-projected table points lie on z = 0.
    pts, hit = jax.jit(r.point_map)(scene.forward(jnp.asarray(mj_model.qpos0)))
    np.testing.assert_allclose(np.asarray(pts)[on_table][:, 2], 0.0, atol=1e-5)
    assert np.array_equal(np.asarray(hit), np.asarray(out["segmentation"]) >= 0)


def test_object_colour_at_centre_and_geom_groups(scene):
    mj_model = scene.mj_model
    q = jnp.asarray(_set_free(mj_model, mj_model.qpos0, "cube", [0.0, 0.0, 0.03]))
    _, render = scene.renderer(**TOP)
    out = render(scene.forward(q))
    cube = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_GEOM, "cube_geom")
    shade = 0.3 + 0.7 * -camera_rays(64, 64, 60.0)[32, 32, 2]  # top face, normal +z
    assert int(out["segmentation"][32, 32]) == cube
    np.testing.assert_allclose(np.asarray(out["rgb"][32, 32], float),
                               255 * shade * np.array([0.1, 0.8, 0.1]), atol=0.51)
    assert float(out["depth"][32, 32]) == pytest.approx(1.0 - 0.06, abs=1e-5)
    # With group 3 drawn, the floor plane (0.5 m below the table top) fills the corners.
    _, render3 = scene.renderer(**TOP, geom_groups=(0, 1, 2, 3))
    out3 = render3(scene.forward(q))
    floor = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    assert int(out3["segmentation"][0, 0]) == floor
    assert float(out3["depth"][0, 0]) == pytest.approx(1.5, abs=1e-4)
    shade = 0.3 + 0.7 * -camera_rays(64, 64, 60.0)[0, 0, 2]
    np.testing.assert_allclose(np.asarray(out3["rgb"][0, 0], float),
                               255 * shade * np.array([0.2, 0.2, 0.8]), atol=0.51)


def test_sphere_shading_darker_at_silhouette(scene):
    """Lambert with analytic normals: a sphere is brightest facing the camera."""
    _, render = scene.renderer(**FRONT_IMG, width=128, height=128)
    out = render(scene.forward(jnp.asarray(scene.mj_model.qpos0)))
    sphere = mujoco.mj_name2id(scene.mj_model, mujoco.mjtObj.mjOBJ_GEOM, "left_sphere")
    mask = np.asarray(out["segmentation"]) == sphere
    assert mask.sum() > 20
    green = np.asarray(out["rgb"])[..., 1][mask] / 255.0
    assert green.max() > 0.78 and green.min() < 0.6  # 0.8 * (0.3 + 0.7 |n.d|)


def test_determinism(scene):
    _, render = scene.renderer(**FRONT)
    q = jnp.asarray(_random_scene_qpos(scene.mj_model, np.random.default_rng(5)))
    a, b = render(scene.forward(q)), render(scene.forward(q))
    for k in ALL_OUTPUTS:
        np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]))


def test_fused_matches_mjx_ray(scene):
    """The default caster agrees with mjx.ray (vmapped per pixel): ids, distances, shading."""
    rf = scene.renderer(camera="front", geom_groups=(0, 1, 2, 3))[0]
    rm = scene.renderer(camera="front", geom_groups=(0, 1, 2, 3), ray_impl="mjx")[0]
    cf, cm = jax.jit(rf.cast), jax.jit(rm.cast)
    rng = np.random.default_rng(4)
    for _ in range(3):
        d = scene.forward(jnp.asarray(_random_scene_qpos(scene.mj_model, rng)))
        hf, hm = cf(d), cm(d)
        same = np.asarray(hf.geom) == np.asarray(hm.geom)
        print(f"fused vs mjx.ray: geom ids differ on {(~same).sum()} of {same.size} pixels")
        assert same.mean() >= 0.999
        both = same & (np.asarray(hf.geom) >= 0)
        assert both.sum() > 1000
        _assert_close_mostly(np.asarray(hf.dist)[both], np.asarray(hm.dist)[both])
        # Lambert terms: fused computes them in the geom frame, mjx in the world frame.
        _assert_close_mostly(np.asarray(hf.cos)[both], np.asarray(hm.cos)[both], 1e-3, 2e-2)


def test_fused_needs_no_material_or_mjx_model():
    xml = SCENE_XML.replace('material="table_mat"', 'rgba="0.6 0.45 0.3 1"').replace(
        'material="red_mat"', 'rgba="0.9 0.1 0.1 1"')
    xml = xml[: xml.index("<asset>")] + xml[xml.index("</asset>") + len("</asset>"):]
    mj_model = mujoco.MjModel.from_xml_string(xml)
    assert mj_model.nmat == 0
    with pytest.raises(ValueError, match="material"):
        make_renderer(mj_model, CameraConfig("top", ray_impl="mjx"))
    r = make_renderer(mj_model, CameraConfig("top"))
    seg = jax.jit(r.segmentation)(_make_forward(mj_model)(mj_model.qpos0))
    assert int(seg[32, 32]) == mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_GEOM, "table")


# --------------------------------------------------------------------------- equivariance


@pytest.mark.parametrize("cam,light", [("top", None), ("front", None), ("front", (0.5, 0, 1))])
def test_image_flip_equivariance(scene, cam, light):
    """A world light in the mirror plane keeps equivariance, like the headlight."""
    _, render = scene.renderer(**(TOP if cam == "top" else FRONT), light_dir=light)
    geom_map = np.asarray(scene.ms.geoms)
    rng = np.random.default_rng(0)
    total_px, total_diff = 0, 0
    for _ in range(4):
        q = jnp.asarray(_random_scene_qpos(scene.mj_model, rng))
        a, b = render(scene.forward(q)), render(scene.forward(scene.ms.qpos(q)))
        frac, n_diff = _equal_fraction(flip_image(a["rgb"], "HWC"), b["rgb"])
        total_px, total_diff = total_px + 64 * 64, total_diff + n_diff
        assert frac >= 0.999, f"{n_diff} pixels differ"
        seg_a = np.asarray(a["segmentation"])[:, ::-1]
        seg_a = np.where(seg_a >= 0, geom_map[np.maximum(seg_a, 0)], -1)
        seg_same = seg_a == np.asarray(b["segmentation"])
        assert seg_same.mean() >= 0.999
        _assert_close_mostly(np.asarray(a["depth"])[:, ::-1][seg_same],
                             np.asarray(b["depth"])[seg_same])
    print(f"{cam}, light {light}: rgb(mirror(s)) vs hflip(rgb(s)) differ on {total_diff} of "
          f"{total_px} pixels")


def test_point_map_mirror_equivariance(scene):
    """Before subsampling: the mirrored state's points are the mirrored points."""
    r, _ = scene.renderer(**FRONT)
    pmap = jax.jit(r.point_map)
    rng = np.random.default_rng(1)
    for _ in range(3):
        q = jnp.asarray(_random_scene_qpos(scene.mj_model, rng))
        pa, ha = pmap(scene.forward(q))
        pb, hb = pmap(scene.forward(scene.ms.qpos(q)))
        ra = np.asarray(reflect_points(MIRROR, pa))[:, ::-1]
        ha = np.asarray(ha)[:, ::-1]
        same = ha == np.asarray(hb)
        assert same.mean() >= 0.999
        both = same & ha
        _assert_close_mostly(ra[both], np.asarray(pb)[both])


@pytest.mark.parametrize("zmin", [-0.01, 0.08])
def test_point_cloud_mirror_consistent_after_subsampling(scene, zmin):
    """The "pairs" sampler: cloud(mirror(s)) == mirror(cloud(s)) as multisets.

    zmin = -0.01 keeps the table top: ~1500 valid points, more than N = 256.
    zmin = 0.08 keeps only parts of the arms: fewer than N, which exercises the padding.
    """
    cloud = scene.cloud(256)
    lo = jnp.array([-0.3, -0.4, zmin])
    rng = np.random.default_rng(2)
    for _ in range(3):
        q = jnp.asarray(_random_scene_qpos(scene.mj_model, rng))
        a = cloud(scene.forward(q), lo, HI)
        b = cloud(scene.forward(scene.ms.qpos(q)), lo, HI)
        n_valid = int(a.n_valid)
        assert a.points.shape == (256, 3) and n_valid == int(b.n_valid)
        assert (n_valid > 256) if zmin < 0 else (0 < n_valid < 256)
        pts = np.asarray(a.points)
        if n_valid >= 256:  # distinct in-box points (with padding, one may be a mean)
            assert np.all((pts >= np.asarray(lo) - 1e-5) & (pts <= np.asarray(HI) + 1e-5))
            assert len(np.unique(pts, axis=0)) == 256
        assert _same_multiset(reflect_points(MIRROR, a.points), b.points), n_valid
        # Colours travel with their points.
        ca = np.concatenate([np.asarray(reflect_points(MIRROR, a.points)), np.asarray(a.colors)], 1)
        cb = np.concatenate([np.asarray(b.points), np.asarray(b.colors)], 1)
        assert _same_multiset(ca, cb, tol=2e-3)


@pytest.mark.parametrize("n", [7, 8])
def test_pair_sampler_property(n):
    """Random masks: the mirrored mask picks the mirrored pixels (as a multiset), every
    pick is valid, at most one slot holds the mean, and all slots are pixels when the
    mask has >= n valid pixels unless the last free slot fits no whole pair."""
    from equibim_jax.sim.render import _pair_units, _sample_pairs

    h, w = 5, 7  # odd width: a centre column of self-mirror pixels
    units = _pair_units(w, h)
    sample = jax.jit(lambda v: _sample_pairs(units, v, n))
    mirror_pix = (np.arange(h * w) // w) * w + (w - 1 - np.arange(h * w) % w)
    rng = np.random.default_rng(0)
    for p_valid in (0.05, 0.2, 0.5, 0.9):
        for _ in range(10):
            v = rng.random((h, w)) < p_valid
            if not v.any():
                continue
            pa, ma = (np.asarray(x) for x in sample(jnp.asarray(v.reshape(-1))))
            pb, mb = (np.asarray(x) for x in sample(jnp.asarray(v[:, ::-1].reshape(-1))))
            assert ma.sum() == mb.sum() <= 1
            assert np.all(v.reshape(-1)[pa[~ma]])
            assert sorted(mirror_pix[pa[~ma]]) == sorted(pb[~mb])
            if v.sum() >= n and ma.any():  # the last slot found no whole unit of size 1
                assert len(set(pa[~ma])) == n - 1


def test_fps_sampler_covers_workspace(scene):
    d = scene.forward(jnp.asarray(scene.mj_model.qpos0))
    lo = jnp.array([-0.3, -0.4, -0.01])  # with the table top: more points than N
    fps = scene.cloud(256, "fps")(d, lo, HI)
    pairs = scene.cloud(256)(d, lo, HI)
    assert int(fps.n_valid) > 1000
    pts = np.asarray(fps.points)
    assert np.all((pts >= np.asarray(lo) - 1e-6) & (pts <= np.asarray(HI) + 1e-6))
    assert len(np.unique(pts, axis=0)) == 256
    gap = lambda p: np.sort(np.linalg.norm(p[:, None] - p[None], axis=-1), 1)[:, 1]
    # FPS spreads its points out: the typical nearest-neighbour gap is larger.
    assert np.median(gap(pts)) > np.median(gap(np.asarray(pairs.points)))


def test_empty_workspace_gives_centre(scene):
    pc = scene.cloud(256)(scene.forward(jnp.asarray(scene.mj_model.qpos0)),
                          jnp.array([5.0, 5, 5]), jnp.array([6.0, 6, 6]))
    assert int(pc.n_valid) == 0
    np.testing.assert_allclose(np.asarray(pc.points), 5.5)


# --------------------------------------------------------------------------- robot A


@pytest.mark.skipif(not ROBOT_A.exists(), reason="robot_a.xml not written yet")
def test_robot_a_head_camera_flip_equivariance():
    mj_model = mujoco.MjModel.from_xml_path(str(ROBOT_A))
    ms = derive_symmetry(mj_model, MIRROR)
    # robot_a colours its pads per arm (pad_left / pad_right materials), which is not a
    # mirror-symmetric colouring; give the right pads the left colour so that this test
    # checks geometry and shading.
    left = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_MATERIAL, "pad_left")
    right = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_MATERIAL, "pad_right")
    if left >= 0 and right >= 0:
        mj_model.mat_rgba[right] = mj_model.mat_rgba[left]
    m = mjx.put_model(mj_model, impl="jax")
    forward = _make_forward(mj_model)
    render = jax.jit(make_renderer(mj_model, CameraConfig("head", outputs=("rgb",)), m).render)
    rng = np.random.default_rng(0)
    n, n_diff = 6, 0
    for i in range(n):  # the home posture, then random postures inside the joint ranges
        q = (mj_model.key_qpos[0] if mj_model.nkey else mj_model.qpos0).copy()
        if i:
            for j in range(mj_model.njnt):
                q[mj_model.jnt_qposadr[j]] = rng.uniform(*mj_model.jnt_range[j])
        a = render(forward(q))["rgb"]
        b = render(forward(ms.qpos(jnp.asarray(q))))["rgb"]
        frac, k = _equal_fraction(flip_image(a, "HWC"), b)
        n_diff += k
        assert frac >= 0.999, f"{k} pixels differ"
    print(f"robot_a head: {n_diff} of {n * 64 * 64} pixels differ")
