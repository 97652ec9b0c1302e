"""``chicken_hook``: both arms together pick up a toy chicken by its two wing knobs, carry
it forward, thread the loop on its back onto a hook's peg, let go, and back off (robot B).

Scene
-----
* **Toy chicken** ``chicken``: one free rigid body (about 85 g) made of primitives, every
  one its own mirror image or paired with its mirror image about the body's x-z plane:

  - the body, an ellipsoid (semi-axes ``body_half``, 4 x 3 x 3 cm by default), long axis
    along the body's x (the beak direction);
  - two *wing knobs*, vertical capsules at body ``(0, +-knob_y, knob_z)`` (radius
    ``knob_radius``, half-length ``knob_half_length``), joined to the body by visual wings:
    the grippers squeeze these, one arm per knob;
  - the *loop*: ``ring_segments`` capsules (radius ``ring_capsule``) whose ends are the
    corners of a regular polygon of circumradius ``ring_radius`` in the body's y-z plane,
    standing on the body's back, a corner at the top; its hole faces along the body's x;
  - three feet, spheres under the body (two at the front, one at the back), on which it
    stands.

  Collisions are chosen per part (MJX has no ellipsoid-box collision and the grippers'
  pads are boxes, and fewer pairs are cheaper): the feet touch the table; the body, through
  a hidden capsule inside the ellipsoid (group 3), touches the table and the hook's post;
  the knobs touch the table, the pads and the palms; the loop touches the hook's peg only. So the grippers touch the toy at its knobs only. The
  loop and the post/peg use two collision bits of their own (``RING_BIT`` = 16,
  ``POST_BIT`` = 32) beyond the robot's four (:mod:`equibim_jax.sim.robots`).
* **Hook**: a static fixture on the mirror plane: a vertical post (capsule, radius
  ``post_radius``) at ``x = hook_x`` rising to ``peg_root_height``, and a peg (capsule,
  radius ``peg_radius``, length ``peg_length``) leaving the post towards the robot
  (``-x``), tilted up by ``peg_tilt_deg`` so that a hanging loop slides back towards the
  post. Grippers pass through the hook; only the loop (peg) and the toy's body (post)
  touch it.

Initial state
-------------
The toy stands on its feet at the centre of the table, facing +x: ``x ~ U(toy_x_range)``,
``y = s * U(toy_y_range)`` (a jitter about the mirror plane), yaw ``s * U(yaw_range)``,
with ``s = +-1`` a fair coin (:meth:`ShiftScene.draw_side`; the task has no sides, so
``side`` must be ``"both"``); the free joint's quaternion is ``s (cos(yaw/2), 0, 0,
sin(yaw/2))``. So the law is mirror-symmetric and the mirrored start is exactly the start
drawn with ``-s``. Arms at home. With ``wide_init`` every range is widened about its
centre; ``mirrored_orientation`` flips the yaw's sign; ``asymmetric_quality`` marks that
fraction of all episodes ``perturbed`` (the expert then fails on purpose).

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
All of: some loop capsule touches the peg (a contact closer than ``touch_tol``); no toy
geom touches the table; the toy's centre is at least ``min_height`` above the table; no
gripper pad touches the toy (the arms have let go). So the toy hangs on the hook by its
loop.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from equibim_jax.sim import robots
from equibim_jax.sim.env import Env
from equibim_jax.tasks import TaskEntry
from equibim_jax.tasks._shifts import ShiftScene

__all__ = ["ChickenHook", "TASK", "RING_BIT", "POST_BIT"]

_CAPSULE = mujoco.mjtGeom.mjGEOM_CAPSULE
_ELLIPSOID = mujoco.mjtGeom.mjGEOM_ELLIPSOID
_SPHERE = mujoco.mjtGeom.mjGEOM_SPHERE
_BOX = mujoco.mjtGeom.mjGEOM_BOX

RING_BIT = 16
"""Collision bit of the toy's loop; only the hook's peg has it in its ``conaffinity``."""
POST_BIT = 32
"""Collision bit of the toy's body; only the hook's post has it in its ``conaffinity``."""

_YELLOW = [0.95, 0.8, 0.2, 1.0]
_ORANGE = [0.9, 0.45, 0.1, 1.0]
_RED = [0.8, 0.15, 0.1, 1.0]
_GREY = [0.45, 0.45, 0.5, 1.0]
_FRICTION = [1.0, 0.005, 0.0001]


def _quat_about(axis: int, angle: float) -> list[float]:
    """Quaternion (w, x, y, z) of a rotation by ``angle`` about world axis ``axis``."""
    q = [math.cos(angle / 2), 0.0, 0.0, 0.0]
    q[1 + axis] = math.sin(angle / 2)
    return q


@dataclasses.dataclass(frozen=True)
class ChickenHook(ShiftScene):
    """The ``chicken_hook`` task as an env scene (robot B); the shift options come from
    :class:`~equibim_jax.tasks._shifts.ShiftScene` (``side`` must stay ``"both"``).

    Attributes:
      toy_x_range: toy centre x range (m).
      toy_y_range: toy centre y jitter range (m), symmetric about 0 (``y = s * U``).
      yaw_range: toy yaw range (rad) (``yaw = s * U``).
      body_half: the body ellipsoid's semi-axes (m).
      body_mass: the body's mass (kg); the knobs, loop and feet add a little.
      knob_y, knob_z: body-frame |y| and z of the wing knobs' axes (m).
      knob_radius, knob_half_length: the knob capsules' radius and half-length (m).
      ring_radius: circumradius of the loop polygon (m).
      ring_capsule: radius of the loop's capsules (m).
      ring_segments: number of capsules in the loop (even, 8 to 12).
      hook_x: x of the post's axis (m).
      post_radius: the post's radius (m).
      peg_root_height: height of the peg's axis where it leaves the post (m).
      peg_length, peg_radius: the peg capsule's axis length and radius (m).
      peg_tilt_deg: the peg rises by this angle from the post to its tip (deg).
      min_height: the toy's centre must be this high for success (m).
      touch_tol: a contact closer than this counts as touching (m).
    """

    toy_x_range: tuple[float, float] = (0.13, 0.17)
    toy_y_range: tuple[float, float] = (-0.01, 0.01)
    yaw_range: tuple[float, float] = (-0.3, 0.3)
    body_half: tuple[float, float, float] = (0.04, 0.03, 0.03)
    body_mass: float = 0.06
    knob_y: float = 0.05
    knob_z: float = 0.008
    knob_radius: float = 0.008
    knob_half_length: float = 0.012
    ring_radius: float = 0.025
    ring_capsule: float = 0.004
    ring_segments: int = 8
    hook_x: float = 0.31
    post_radius: float = 0.008
    peg_root_height: float = 0.13
    peg_length: float = 0.1
    peg_radius: float = 0.005
    peg_tilt_deg: float = 8.0
    min_height: float = 0.05
    touch_tol: float = 0.001
    name = "chicken_hook"
    sided = False
    main_object = "chicken"
    # The table in front of the arms, up to above the hook; mirror-symmetric.
    point_cloud_crop = ((0.05, -0.3, 0.002), (0.4, 0.3, 0.25))

    # mass of the parts other than the body (kg)
    knob_mass = 0.006
    ring_mass = 0.001
    foot_mass = 0.002
    foot_radius = 0.008

    def __post_init__(self):
        super().__post_init__()
        for f in ("toy_x_range", "toy_y_range", "yaw_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{self.name}: {f} must be (low, high) with low <= high, got {r}")
        for f in ("toy_y_range", "yaw_range"):
            r = getattr(self, f)
            if abs(r[0] + r[1]) > 1e-9:
                raise ValueError(f"{self.name}: {f} must be symmetric about 0 (the toy sits on the "
                                 f"mirror plane), got {r}")
        if len(self.body_half) != 3 or min(self.body_half) <= 0:
            raise ValueError(f"{self.name}: body_half must be three positive semi-axes, got {self.body_half}")
        for f in ("body_mass", "knob_radius", "knob_half_length", "ring_radius", "ring_capsule",
                  "post_radius", "peg_length", "peg_radius", "min_height"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{self.name}: {f} must be positive, got {getattr(self, f)}")
        if self.touch_tol < 0:
            raise ValueError(f"{self.name}: touch_tol must be >= 0, got {self.touch_tol}")
        if not (isinstance(self.ring_segments, int) and self.ring_segments % 2 == 0
                and 8 <= self.ring_segments <= 12):
            raise ValueError(f"{self.name}: ring_segments must be an even int from 8 to 12 (a corner "
                             f"at the top, mirror-symmetric), got {self.ring_segments!r}")
        if self.knob_y - self.knob_radius <= self.body_half[1] * 0.5:
            raise ValueError(f"{self.name}: knob_y must put the knobs beside the body, got {self.knob_y}")
        hole = self.ring_radius * math.cos(math.pi / self.ring_segments) - self.ring_capsule
        if hole <= self.peg_radius + 0.005:
            raise ValueError(f"{self.name}: the loop's hole (inradius {hole:.4f} m) must exceed the peg's "
                             f"radius by 5 mm; got peg_radius {self.peg_radius}")
        if not 0.0 <= self.peg_tilt_deg < 45.0:
            raise ValueError(f"{self.name}: peg_tilt_deg must be in [0, 45), got {self.peg_tilt_deg}")

    # ------------------------------------------------------------------ geometry
    @property
    def rest_height(self) -> float:
        """Height (m) of the toy's centre standing on its feet."""
        return self.foot_z + self.foot_radius

    @property
    def hull(self) -> tuple[float, float]:
        """Radius and half-length (m) of the body's collision capsule (along the body's x,
        inside the ellipsoid)."""
        r = 0.83 * min(self.body_half[1], self.body_half[2])
        return r, max(self.body_half[0] - r - 0.003, 0.0)

    @property
    def foot_z(self) -> float:
        """Depth (m) of the feet's centres below the toy's centre."""
        return self.body_half[2] - 0.004

    @property
    def foot_local(self) -> np.ndarray:
        """Body-frame centres [3, 3] of the feet (two front, one back)."""
        hx, hy, _ = self.body_half
        z = -self.foot_z
        return np.array([[0.35 * hx, 0.5 * hy, z], [0.35 * hx, -0.5 * hy, z], [-0.6 * hx, 0.0, z]])

    @property
    def ring_centre_z(self) -> float:
        """Body-frame z (m) of the loop polygon's centre (its bottom corner sits on the back)."""
        return self.body_half[2] + self.ring_radius - 0.002

    def ring_corners(self) -> np.ndarray:
        """Body-frame corners [n, 3] of the loop polygon, corner 0 at the top."""
        th = 2 * np.pi * np.arange(self.ring_segments) / self.ring_segments
        return np.stack([np.zeros_like(th), self.ring_radius * np.sin(th),
                         self.ring_centre_z + self.ring_radius * np.cos(th)], axis=-1)

    def knob_local(self) -> np.ndarray:
        """Body-frame centres [2, 3] of the (left, right) wing knobs."""
        return np.array([[0.0, self.knob_y, self.knob_z], [0.0, -self.knob_y, self.knob_z]])

    @property
    def peg_root(self) -> np.ndarray:
        """World position [3] where the peg's axis leaves the post."""
        return np.array([self.hook_x, 0.0, self.peg_root_height])

    @property
    def peg_tip(self) -> np.ndarray:
        """World position [3] of the peg's free end (its axis)."""
        a = math.radians(self.peg_tilt_deg)
        return self.peg_root + self.peg_length * np.array([-math.cos(a), 0.0, math.sin(a)])

    def peg_axis_height(self, x):
        """Height (m) of the peg's axis at ``x`` (any shape; linear in ``x``)."""
        a = math.radians(self.peg_tilt_deg)
        return self.peg_root_height + (self.hook_x - x) * math.tan(a)

    @property
    def loop_hang_drop(self) -> float:
        """Height (m) of the peg's axis above the loop's centre when the loop hangs on it
        (its top corner's inner edge on the peg)."""
        return self.ring_radius - self.ring_capsule / math.cos(math.pi / self.ring_segments) - self.peg_radius

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free toy chicken and the static hook to robot B's spec."""
        if info.name != "robot_b":
            raise ValueError(f"{self.name} is built for robot_b, got {info.name!r}")
        z0 = info.table_height
        toy = spec.worldbody.add_body(name="chicken", pos=[0.15, 0.0, z0 + self.rest_height])
        toy.add_freejoint(name="chicken")
        hx, hy, hz = self.body_half
        # the body: a visual ellipsoid carrying the mass, and inside it a hidden capsule
        # (group 3) that collides with the table and the post (MJX's capsule pairs are
        # closed-form; its ellipsoid-capsule pair is an iterative SDF solve)
        toy.add_geom(name="chicken_body", type=_ELLIPSOID, size=[hx, hy, hz], mass=self.body_mass,
                     rgba=_YELLOW, contype=0, conaffinity=0, group=1)
        r, hl = self.hull
        toy.add_geom(name="chicken_hull", type=_CAPSULE, size=[r, hl, 0], quat=_quat_about(1, math.pi / 2),
                     rgba=_YELLOW, condim=3, friction=_FRICTION, contype=POST_BIT,
                     conaffinity=robots.TABLE_BIT, density=0, group=3)
        # head and beak: visual only
        toy.add_geom(name="chicken_head", type=_SPHERE, size=[0.6 * hy, 0, 0],
                     pos=[0.8 * hx, 0.0, 0.6 * hz], rgba=_YELLOW, contype=0, conaffinity=0,
                     density=0, group=1)
        toy.add_geom(name="chicken_beak", type=_SPHERE, size=[0.25 * hy, 0, 0],
                     pos=[0.8 * hx + 0.6 * hy, 0.0, 0.6 * hz], rgba=_ORANGE, contype=0,
                     conaffinity=0, density=0, group=1)
        for k, (pos, side) in enumerate(zip(self.knob_local(), ("left", "right"))):
            toy.add_geom(name=f"chicken_knob_{side}", type=_CAPSULE,
                         size=[self.knob_radius, self.knob_half_length, 0], pos=list(pos),
                         mass=self.knob_mass, rgba=_ORANGE, condim=4, friction=_FRICTION,
                         contype=0, conaffinity=robots.TABLE_BIT | robots.PAD_BIT | robots.PALM_BIT)
            wing_y = 0.5 * (0.6 * hy + self.knob_y)
            toy.add_geom(name=f"chicken_wing_{side}", type=_BOX,
                         size=[0.5 * hx, 0.5 * (self.knob_y - 0.6 * hy), 0.003],
                         pos=[0.0, wing_y if k == 0 else -wing_y, self.knob_z], rgba=_YELLOW,
                         contype=0, conaffinity=0, density=0, group=1)
        corners = self.ring_corners()
        n = self.ring_segments
        for k in range(n):
            a, b = corners[k], corners[(k + 1) % n]
            d = b - a
            half = 0.5 * float(np.linalg.norm(d))
            angle = math.atan2(-d[1], d[2])  # rotation about x taking z onto d
            toy.add_geom(name=f"chicken_loop_{k}", type=_CAPSULE, size=[self.ring_capsule, half, 0],
                         pos=list(0.5 * (a + b)), quat=_quat_about(0, angle), mass=self.ring_mass,
                         rgba=_RED, condim=3, friction=_FRICTION, contype=RING_BIT, conaffinity=0)
        for k, pos in enumerate(self.foot_local):
            toy.add_geom(name=f"chicken_foot_{k}", type=_SPHERE, size=[self.foot_radius, 0, 0],
                         pos=list(pos), mass=self.foot_mass, rgba=_ORANGE, condim=3,
                         friction=_FRICTION, contype=0, conaffinity=robots.TABLE_BIT)
        # the hook: post and tilted peg, static (world body)
        wb = spec.worldbody
        ph = self.peg_root_height
        wb.add_geom(name="hook_post", type=_CAPSULE, size=[self.post_radius, 0.5 * ph, 0],
                    pos=[self.hook_x, 0.0, z0 + 0.5 * ph], rgba=_GREY, condim=3, friction=_FRICTION,
                    contype=0, conaffinity=POST_BIT)
        mid = 0.5 * (self.peg_root + self.peg_tip) + np.array([0.0, 0.0, z0])
        tilt = math.radians(self.peg_tilt_deg)
        # rotation about y taking z onto the peg's direction (-cos t, 0, sin t)
        wb.add_geom(name="hook_peg", type=_CAPSULE, size=[self.peg_radius, 0.5 * self.peg_length, 0],
                    pos=list(mid), quat=_quat_about(1, -(math.pi / 2 - tilt)), rgba=_GREY, condim=3,
                    friction=_FRICTION, contype=0, conaffinity=RING_BIT)

    # ------------------------------------------------------------------ ids
    def _ids(self, env: Env) -> dict:
        m = env.mj_model
        g = lambda name: m.geom(name).id
        pads = [g(p) for side in env.info.gripper_pads for p in side]
        return {
            "body": m.body("chicken").id,
            "qadr": int(m.jnt_qposadr[m.joint("chicken").id]),
            "loop": np.array([g(f"chicken_loop_{k}") for k in range(self.ring_segments)]),
            "peg": np.array([g("hook_peg")]),
            "table": np.array([g("table")]),
            "toy_table": np.array([g("chicken_hull"), g("chicken_knob_left"), g("chicken_knob_right")]
                                  + [g(f"chicken_foot_{k}") for k in range(3)]),
            "knobs": np.array([g("chicken_knob_left"), g("chicken_knob_right")]),
            "pads": np.array(pads),
        }

    def toy_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """Toy centre [3] and rotation matrix [3, 3] (world frame)."""
        b = self._ids(env)["body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def knob_positions(self, data: mjx.Data, env: Env) -> jax.Array:
        """World centres [2, 3] of the (left, right) wing knobs (body +y first)."""
        pos, rot = self.toy_pose(data, env)
        return pos + jnp.asarray(self.knob_local(), pos.dtype) @ rot.T

    def placed_qpos(self, qpos: jax.Array, env: Env, xyz, quat=(1.0, 0.0, 0.0, 0.0)) -> jax.Array:
        """``qpos`` [nq] with the toy's free joint at ``xyz`` [3] and ``quat`` [4] (w, x, y, z)."""
        a = self._ids(env)["qadr"]
        pose = jnp.concatenate([jnp.asarray(xyz, qpos.dtype), jnp.asarray(quat, qpos.dtype)])
        return qpos.at[a : a + 7].set(pose)

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, the toy standing at the centre of the table.

        Returns qpos [nq] and ``{"side": s, "yaw": yaw, "perturbed": bool}`` ([] each).
        """
        k_side, k_x, k_y, k_yaw, k_pert = jax.random.split(key, 5)
        s = self.draw_side(k_side)
        x = self.uniform(k_x, self.toy_x_range)
        y = s * self.uniform(k_y, self.toy_y_range)
        yaw = self.draw_yaw(k_yaw, s, self.yaw_range).astype(jnp.float32)
        perturbed = self.draw_perturbed(k_pert, s)
        z = jnp.asarray(env.info.table_height + self.rest_height, jnp.float32)
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, jnp.stack([x, y, z]),
                                self.signed_yaw_quat(yaw, s))
        return qpos, {"side": s, "yaw": yaw, "perturbed": perturbed}

    @staticmethod
    def _min_dist(data: mjx.Data, a: np.ndarray, b: np.ndarray) -> jax.Array:
        """[] smallest distance of the contacts between geom sets ``a`` and ``b`` in MJX's
        contact list (a large value when there is none)."""
        c = data._impl.contact
        g1, g2 = c.geom[:, 0], c.geom[:, 1]
        ia, ib = jnp.asarray(a), jnp.asarray(b)
        in_a = lambda g: jnp.any(g[:, None] == ia[None, :], axis=-1)
        in_b = lambda g: jnp.any(g[:, None] == ib[None, :], axis=-1)
        pair = (in_a(g1) & in_b(g2)) | (in_b(g1) & in_a(g2))
        big = jnp.asarray(1e10, c.dist.dtype)
        return jnp.min(jnp.where(pair, c.dist, big), initial=big)

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: contact distances and height (m), [] bool checks."""
        ids = self._ids(env)
        pos, _ = self.toy_pose(data, env)
        loop_peg = self._min_dist(data, ids["loop"], ids["peg"])
        toy_table = self._min_dist(data, ids["toy_table"], ids["table"])
        pad_knob = self._min_dist(data, ids["pads"], ids["knobs"])
        height = pos[2] - env.info.table_height
        return {
            "loop_peg_dist": jnp.minimum(loop_peg, 1.0),
            "toy_table_dist": jnp.minimum(toy_table, 1.0),
            "pad_knob_dist": jnp.minimum(pad_knob, 1.0),
            "toy_height": height,
            "on_peg": loop_peg < self.touch_tol,
            "off_table": toy_table >= self.touch_tol,
            "high": height >= self.min_height,
            "released": pad_knob >= self.touch_tol,
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["on_peg"] & t["off_table"] & t["high"] & t["released"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics


TASK = TaskEntry(
    name="chicken_hook",
    scene=ChickenHook,
    robot="robot_b",
    step_limit=600,
    expert="equibim_jax.experts.chicken_hook:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
