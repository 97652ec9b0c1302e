"""``beat_block_hammer``: pick a hammer up by its handle and strike a block with its head
(robot A).

Scene
-----
* **Hammer**: a free body lying at the centre of the table, on the mirror plane, its
  handle along x pointing toward the robot (-x) and its head away from it (+x). Three
  primitives, each its own mirror image about the body's x-z plane, so the hammer is its
  own mirror image:

  - the *handle*, a box (13 x 2.4 x 2.4 cm by default) that the gripper squeezes. It
    collides with the finger pads and palms only (``contype 0``, ``conaffinity PAD |
    PALM``);
  - the *head*, a box at the handle's +x end, taller than the handle and reaching
    ``head_half[2] - handle_half[2]`` below it, so its bottom face is the striking face
    and the handle stays clear of whatever the face touches. It collides with the table
    and the block only, through a collision bit private to this task
    (:data:`HEAD_BIT`: ``contype HEAD_BIT``, ``conaffinity TABLE``); the grippers pass
    through it;
  - a *foot*, a sphere under the handle's -x end whose bottom is level with the striking
    face, so the hammer rests level on its head and foot. It collides with the table only
    (``contype 0``, ``conaffinity TABLE``).

* **Block**: a box on two slide joints (x, y) and a hinge about the vertical
  (``block_yaw``) at table height, like ``press_stapler``'s base: its position and yaw
  are in ``qpos`` (drawn by ``init``, mirrored by ``mirror_state``) and joint
  ``frictionloss`` stands in for table friction; the joints carry its weight and the
  blows it takes. It collides with the hammer's head only (``contype 0``,
  ``conaffinity HEAD_BIT``): the grippers pass through it.

Contact pairs added: head-table and foot-table, the handle's 6 with the pads and palms,
and head-block.

Initial state (mirror symmetric for ``side="both"``)
----------------------------------------------------
``s = +1`` (left, y > 0) or ``-1``. The hammer always lies at the same place (handle
centre at ``(hammer_x, 0)``, level, resting on its head and foot). The block is on side
``s`` at ``x ~ U(block_x_range)``, ``y = s U(block_y_range)``, yaw ``s U(-max_yaw,
max_yaw)`` (the mirror maps yaw to -yaw, so the law is its own mirror image). Arms at
home. ``block_y_range[0]`` must keep the block's footprint clear of the head at any yaw
(checked).

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
Both: the centre of the head's striking face is within ``success_xy`` (2 cm) of the
block's top-face centre in x-y, and the head touches the block: some contact of the
head-block pair in MJX's contact list (``data._impl.contact``) has a distance below
``touch_tol`` (default 0: the soft contact is active, i.e. pushes the two apart; a resting
or pressing contact has a small negative distance). After a step, that list is the one MJX
computed for the control step's last physics substep.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from equibim_jax.sim import robots
from equibim_jax.sim.env import Env, Scene
from equibim_jax.sim.scenes import SIDES, side_sign
from equibim_jax.tasks import TaskEntry

__all__ = ["BeatBlockHammer", "HEAD_BIT", "TASK"]

_BOX = mujoco.mjtGeom.mjGEOM_BOX
_SPHERE = mujoco.mjtGeom.mjGEOM_SPHERE

HEAD_BIT = 16
"""Collision bit of this task's hammer head (unused by :mod:`equibim_jax.sim.robots`'s
scheme): the block's ``conaffinity`` is this bit alone, so the head is the only geom that
touches the block."""


def _max_half_extent_y(half_x: float, half_y: float, max_yaw: float) -> float:
    """Largest |y| reach of a box footprint (half sizes ``half_x``, ``half_y``) turned by
    any yaw in ``[-max_yaw, max_yaw]`` (``max_yaw`` <= pi)."""
    peak = math.atan2(half_x, half_y)  # yaw at which half_x sin + half_y cos peaks
    if max_yaw >= peak:
        return math.hypot(half_x, half_y)
    return half_x * math.sin(max_yaw) + half_y * math.cos(max_yaw)


@dataclasses.dataclass(frozen=True)
class BeatBlockHammer(Scene):
    """The ``beat_block_hammer`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      side: ``"left"``, ``"right"`` or ``"both"`` (random side, mirror-symmetric).
      hammer_x: x of the handle's centre (m); the hammer lies on the mirror plane.
      handle_half: half sizes of the handle box (m).
      head_half: half sizes of the head box (m); the head is centred on the handle's axis
        at its +x end, so ``head_half[2] > handle_half[2]`` makes it reach below the handle.
      foot_radius: radius of the foot sphere under the handle's -x end (m).
      handle_mass, head_mass, foot_mass: masses (kg).
      block_x_range, block_y_range: block centre x and |y| ranges (m).
      max_yaw: block yaw is drawn from ``U(-max_yaw, max_yaw)`` (rad, at most pi / 2).
      block_half: half sizes of the block box (m).
      block_mass: its mass (kg).
      success_xy: largest x-y distance from the striking face's centre to the block's
        top-face centre (m).
      touch_tol: a head-block contact with a distance below this counts as a touch (m,
        >= 0; at 0 only active contacts, which exert force, count).
    """

    side: str = "both"
    hammer_x: float = 0.2
    handle_half: tuple[float, float, float] = (0.065, 0.012, 0.012)
    head_half: tuple[float, float, float] = (0.02, 0.016, 0.025)
    foot_radius: float = 0.013
    handle_mass: float = 0.03
    head_mass: float = 0.06
    foot_mass: float = 0.005
    block_x_range: tuple[float, float] = (0.22, 0.42)
    block_y_range: tuple[float, float] = (0.05, 0.25)
    max_yaw: float = 0.5
    block_half: tuple[float, float, float] = (0.02, 0.02, 0.02)
    block_mass: float = 0.1
    success_xy: float = 0.02
    touch_tol: float = 0.0
    name = "beat_block_hammer"
    # The table in front of the arms' bases (see place_empty_cup); mirror-symmetric.
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.2))

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")
        for f in ("block_x_range", "block_y_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {r}")
        for f in ("handle_half", "head_half", "block_half"):
            h = getattr(self, f)
            if len(h) != 3 or min(h) <= 0:
                raise ValueError(f"{f} must be three positive half sizes, got {h}")
        for f in ("foot_radius", "handle_mass", "head_mass", "foot_mass", "block_mass", "success_xy"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        if not self.touch_tol >= 0:
            raise ValueError(f"touch_tol must be >= 0, got {self.touch_tol}")
        if not 0.0 <= self.max_yaw <= math.pi / 2:
            raise ValueError(f"max_yaw must be in [0, pi/2], got {self.max_yaw}")
        if not self.head_half[2] > self.handle_half[2]:
            raise ValueError("head_half[2] must exceed handle_half[2]: the head's striking face "
                             "must reach below the handle")
        if not self.foot_radius <= self.head_half[2]:
            raise ValueError(f"foot_radius ({self.foot_radius}) must not exceed head_half[2] "
                             f"({self.head_half[2]}): the foot hangs under the handle")
        if not self.foot_radius <= self.handle_half[0]:
            raise ValueError("the foot must fit under the handle (foot_radius <= handle_half[0])")
        reach = _max_half_extent_y(self.block_half[0], self.block_half[1], self.max_yaw)
        if self.block_y_range[0] <= reach + self.head_half[1]:
            raise ValueError(
                f"block_y_range[0] must exceed the block's largest half extent in y at any "
                f"allowed yaw plus the head's half width ({reach + self.head_half[1]:.4f} m): the "
                f"block must lie wholly on its side of the mirror plane, clear of the hammer's head"
            )

    # ------------------------------------------------------------------ geometry
    @property
    def rest_height(self) -> float:
        """z of the hammer's body frame (the handle's centre) above the table at rest (m)."""
        return self.head_half[2]

    @property
    def head_local(self) -> tuple[float, float, float]:
        """The head box's centre in the hammer's body frame (m)."""
        return (self.handle_half[0] + self.head_half[0], 0.0, 0.0)

    @property
    def face_local(self) -> tuple[float, float, float]:
        """The striking face's centre (the head's bottom) in the hammer's body frame (m)."""
        return (self.handle_half[0] + self.head_half[0], 0.0, -self.head_half[2])

    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free hammer (handle, head, foot) and the jointed block to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"beat_block_hammer is built for robot_a, got {info.name!r}")
        z0 = info.table_height
        hx, hy, hz = self.handle_half
        hammer = spec.worldbody.add_body(name="hammer", pos=[self.hammer_x, 0.0, z0 + self.rest_height])
        hammer.add_freejoint(name="hammer")
        hammer.add_geom(
            name="hammer_handle", type=_BOX, size=[hx, hy, hz], mass=self.handle_mass,
            rgba=[0.55, 0.38, 0.2, 1.0], condim=4, friction=[1.0, 0.005, 0.0001],
            contype=0, conaffinity=robots.PAD_BIT | robots.PALM_BIT,
        )
        hammer.add_geom(
            name="hammer_head", type=_BOX, size=list(self.head_half), pos=list(self.head_local),
            mass=self.head_mass, rgba=[0.3, 0.3, 0.33, 1.0], condim=3,
            friction=[1.0, 0.005, 0.0001], contype=HEAD_BIT, conaffinity=robots.TABLE_BIT,
        )
        r = self.foot_radius
        hammer.add_geom(
            name="hammer_foot", type=_SPHERE, size=[r, 0.0, 0.0],
            pos=[-hx + r, 0.0, -self.head_half[2] + r], mass=self.foot_mass,
            rgba=[0.2, 0.2, 0.2, 1.0], condim=3, friction=[1.0, 0.005, 0.0001],
            contype=0, conaffinity=robots.TABLE_BIT,
        )
        bx, by, bz = self.block_half
        block = spec.worldbody.add_body(name="block", pos=[0.0, 0.0, z0])
        for axis, jname in (([1.0, 0.0, 0.0], "block_x"), ([0.0, 1.0, 0.0], "block_y")):
            block.add_joint(name=jname, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis, damping=3.0,
                            frictionloss=1.0, armature=0.01)
        block.add_joint(name="block_yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 0.0, 1.0],
                        damping=0.05, frictionloss=0.05, armature=0.001)
        block.add_geom(
            name="block", type=_BOX, size=[bx, by, bz], pos=[0.0, 0.0, bz], mass=self.block_mass,
            rgba=[0.85, 0.55, 0.15, 1.0], condim=3, friction=[1.0, 0.005, 0.0001],
            contype=0, conaffinity=HEAD_BIT,
        )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, int]:
        m = env.mj_model
        qadr = lambda n: int(m.jnt_qposadr[m.joint(n).id])
        return {
            "hammer_body": m.body("hammer").id,
            "block_body": m.body("block").id,
            "head_geom": m.geom("hammer_head").id,
            "block_geom": m.geom("block").id,
            "hammer_qadr": qadr("hammer"),
            "x_qadr": qadr("block_x"),
            "y_qadr": qadr("block_y"),
            "yaw_qadr": qadr("block_yaw"),
        }

    def hammer_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """Hammer body position (the handle's centre) [3] and rotation matrix [3, 3]."""
        b = self._ids(env)["hammer_body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def hammer_point(self, data: mjx.Data, env: Env, local) -> jax.Array:
        """World position [3] of a point given in the hammer's body frame (``local`` [3])."""
        pos, rot = self.hammer_pose(data, env)
        return pos + rot @ jnp.asarray(local, pos.dtype)

    def face_centre(self, data: mjx.Data, env: Env) -> jax.Array:
        """World position [3] of the centre of the head's striking face."""
        return self.hammer_point(data, env, self.face_local)

    def block_top(self, data: mjx.Data, env: Env) -> jax.Array:
        """World position [3] of the centre of the block's top face."""
        b = self._ids(env)["block_body"]
        return data.xpos[b] + jnp.asarray([0.0, 0.0, 2 * self.block_half[2]], data.xpos.dtype)

    def block_from_qpos(self, qpos: jax.Array, env: Env) -> jax.Array:
        """Block (x, y, yaw) [3] read from ``qpos`` [nq]."""
        ids = self._ids(env)
        return jnp.stack([qpos[ids["x_qadr"]], qpos[ids["y_qadr"]], qpos[ids["yaw_qadr"]]])

    def head_block_distance(self, data: mjx.Data, env: Env) -> jax.Array:
        """[] smallest distance of the head-block contacts in MJX's contact list (m; 0 is
        touching, negative penetrating, a large positive value when none is near)."""
        ids = self._ids(env)
        c = data._impl.contact
        g1, g2 = c.geom[:, 0], c.geom[:, 1]
        h, b = ids["head_geom"], ids["block_geom"]
        pair = ((g1 == h) & (g2 == b)) | ((g1 == b) & (g2 == h))
        big = jnp.asarray(1e10, c.dist.dtype)
        return jnp.min(jnp.where(pair, c.dist, big), initial=big)

    def placed_qpos(self, qpos: jax.Array, env: Env, block_x, block_y, block_yaw=0.0,
                    hammer_xyz=None, hammer_quat=(1.0, 0.0, 0.0, 0.0)) -> jax.Array:
        """``qpos`` [nq] with the block at (``block_x``, ``block_y``, ``block_yaw``) and, if
        ``hammer_xyz`` [3] is given, the hammer's free joint at it with ``hammer_quat`` [4]
        (for building states by hand)."""
        ids = self._ids(env)
        for k, v in (("x_qadr", block_x), ("y_qadr", block_y), ("yaw_qadr", block_yaw)):
            qpos = qpos.at[ids[k]].set(jnp.asarray(v, qpos.dtype))
        if hammer_xyz is not None:
            a = ids["hammer_qadr"]
            pose = jnp.concatenate([jnp.asarray(hammer_xyz, qpos.dtype), jnp.asarray(hammer_quat, qpos.dtype)])
            qpos = qpos.at[a : a + 7].set(pose)
        return qpos

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, hammer at its rest pose, block on one side. Returns qpos [nq],
        ``{"side": []}``."""
        k_side, k_x, k_y, k_yaw = jax.random.split(key, 4)
        s = side_sign(k_side, self.side)
        u = lambda k, lo, hi: jax.random.uniform(k, (), minval=lo, maxval=hi)
        x = u(k_x, *self.block_x_range)
        y = s * u(k_y, *self.block_y_range)
        yaw = s * u(k_yaw, -self.max_yaw, self.max_yaw)
        # the hammer's rest pose is the model's qpos0 (in home_qpos)
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, x, y, yaw)
        return qpos, {"side": s}

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: distances (m) and [] bool checks."""
        face = self.face_centre(data, env)
        top = self.block_top(data, env)
        xy = jnp.linalg.norm(face[:2] - top[:2])
        dist = self.head_block_distance(data, env)
        return {
            "face_block_xy": xy,
            "face_block_dz": face[2] - top[2],
            "head_block_dist": jnp.minimum(dist, 1.0),
            "on_target": xy < self.success_xy,
            "touching": dist < self.touch_tol,
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["on_target"] & t["touching"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirrored episode has its block on the other side."""
        return {**info, "side": -info["side"]} if "side" in info else info


TASK = TaskEntry(
    name="beat_block_hammer",
    scene=BeatBlockHammer,
    robot="robot_a",
    step_limit=400,
    expert="equibim_jax.experts.beat_block_hammer:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
