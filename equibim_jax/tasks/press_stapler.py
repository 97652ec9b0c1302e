"""``press_stapler``: press a stapler's sprung top plate shut (robot A).

Scene
-----
* **Stapler base**: a body at table height on two slide joints (x, y) and a hinge about
  the vertical (``stapler_yaw``), so its position and heading are part of ``qpos`` (drawn
  by ``init``, mirrored by ``mirror_state``). Joint ``frictionloss`` stands in for table
  friction, as for ``place_empty_cup``'s coaster. Its box is visual only (no contacts):
  nothing in the task touches it.
* **Top plate**: a box on a hinge ``stapler_hinge`` at the back of the base (axis along
  the base's -y, so positive angles lift the front), with a spring (``stiffness``; rest
  angle ``springref`` past the open stop, so it preloads the plate against the stop),
  damping, and a range ``[0, open_angle]``: 0 is shut against the base, ``open_angle``
  is the open stop. The plate collides with the finger pads only (``contype 0,
  conaffinity PAD``): 4 box-box pairs.
* **Press point**: on the plate's top face, ``press_offset`` from the hinge along the
  plate (near its front end), marked by a thin visual square.

Every geom is a primitive centred on the stapler's long axis, so at yaw 0 the stapler is
its own mirror image about its x-z plane: ``derive_symmetry`` maps its bodies and joints
to themselves, ``stapler_y`` and ``stapler_yaw`` flip sign, ``stapler_x`` and the plate
hinge keep it.

Initial state (mirror symmetric for ``side="both"``)
----------------------------------------------------
``s = +1`` (left, y > 0) or ``-1``. Stapler at ``x ~ U(stapler_x_range)``,
``y = s U(stapler_y_range)``, yaw ``~ U(-max_yaw, max_yaw)`` (the mirror maps yaw to
-yaw, so the yaw distribution is its own mirror image), plate open at ``open_angle``,
arms at home.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
Both: the plate's hinge angle is below ``closed_angle`` (the plate was pushed shut), and
some gripper's ee site is within ``success_xy`` of the press point in x-y (the plate was
pressed near its press point).
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

__all__ = ["PressStapler", "TASK"]

_BOX = mujoco.mjtGeom.mjGEOM_BOX
# Time constant (s) of the plate's stops: twice the physics step, the stiffest MuJoCo
# integrates stably (the default 0.02 s lets the preloaded spring push the plate visibly
# past its open stop).
_STOP_TIMECONST = 0.008


@dataclasses.dataclass(frozen=True)
class PressStapler(Scene):
    """The ``press_stapler`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      side: ``"left"``, ``"right"`` or ``"both"`` (random side, mirror-symmetric).
      stapler_x_range, stapler_y_range: base centre x and |y| ranges (m).
      max_yaw: yaw is drawn from ``U(-max_yaw, max_yaw)`` (rad), at most pi.
      base_half: half sizes of the base box (m).
      plate_half: half sizes of the top plate box (m).
      hinge_inset: distance from the base's back end to the hinge (m).
      hinge_gap: gap between the base's top and the shut plate's bottom (m).
      open_angle: the plate's open stop (rad).
      spring_stiffness: hinge spring (N m / rad).
      spring_preload: spring rest angle past the open stop (rad).
      hinge_damping: hinge damping (N m s / rad).
      press_offset: distance of the press point from the hinge along the plate (m).
      closed_angle: the plate counts as shut below this hinge angle (rad).
      success_xy: largest x-y distance from a gripper's ee site to the press point (m).
    """

    side: str = "both"
    stapler_x_range: tuple[float, float] = (0.2, 0.3)
    stapler_y_range: tuple[float, float] = (0.0, 0.2)
    max_yaw: float = math.pi
    base_half: tuple[float, float, float] = (0.06, 0.018, 0.012)
    plate_half: tuple[float, float, float] = (0.06, 0.015, 0.004)
    hinge_inset: float = 0.005
    hinge_gap: float = 0.002
    open_angle: float = 0.3
    spring_stiffness: float = 0.3
    spring_preload: float = 0.2
    hinge_damping: float = 0.02
    press_offset: float = 0.1
    closed_angle: float = 0.06
    success_xy: float = 0.03
    name = "press_stapler"
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.2))

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")
        for f in ("stapler_x_range", "stapler_y_range"):
            lo, hi = getattr(self, f)
            if not lo <= hi:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {(lo, hi)}")
        if self.stapler_y_range[0] < 0:
            raise ValueError(f"stapler_y_range holds |y| values (>= 0), got {self.stapler_y_range}")
        if not 0 <= self.max_yaw <= math.pi:
            raise ValueError(f"max_yaw must be in [0, pi], got {self.max_yaw}")
        if any(not v > 0 for v in (*self.base_half, *self.plate_half)):
            raise ValueError("base_half and plate_half must be positive")
        if not 0 < self.closed_angle < self.open_angle < math.pi / 2:
            raise ValueError(f"need 0 < closed_angle ({self.closed_angle}) < open_angle "
                             f"({self.open_angle}) < pi/2")
        if not 0 < self.press_offset <= 2 * self.plate_half[0]:
            raise ValueError(f"press_offset ({self.press_offset}) must lie on the plate "
                             f"(0, {2 * self.plate_half[0]}]")
        for f in ("spring_stiffness", "success_xy"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        if self.spring_preload < 0 or self.hinge_damping < 0 or self.hinge_inset < 0 or self.hinge_gap < 0:
            raise ValueError("spring_preload, hinge_damping, hinge_inset and hinge_gap must be >= 0")

    # ------------------------------------------------------------------ geometry
    @property
    def hinge_pos(self) -> tuple[float, float, float]:
        """Hinge position in the base's frame (m; the base frame sits on the table)."""
        return (-self.base_half[0] + self.hinge_inset, 0.0, 2 * self.base_half[2] + self.hinge_gap)

    @property
    def press_local(self) -> tuple[float, float, float]:
        """The press point in the plate's frame (origin at the hinge; m)."""
        return (self.press_offset, 0.0, 2 * self.plate_half[2])

    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the jointed stapler base and its sprung, hinged top plate to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"press_stapler is built for robot_a, got {info.name!r}")
        base = spec.worldbody.add_body(name="stapler", pos=[0.0, 0.0, info.table_height])
        for axis, jname in (([1.0, 0.0, 0.0], "stapler_x"), ([0.0, 1.0, 0.0], "stapler_y")):
            base.add_joint(name=jname, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis, damping=5.0,
                           frictionloss=3.0, armature=0.01)
        base.add_joint(name="stapler_yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 0.0, 1.0],
                       damping=0.2, frictionloss=0.2, armature=0.002)
        bx, by, bz = self.base_half
        base.add_geom(name="stapler_base", type=_BOX, size=[bx, by, bz], pos=[0.0, 0.0, bz],
                      mass=0.3, rgba=[0.15, 0.15, 0.17, 1.0], contype=0, conaffinity=0, group=1)
        plate = base.add_body(name="stapler_plate", pos=list(self.hinge_pos))
        plate.add_joint(
            name="stapler_hinge", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, -1.0, 0.0],
            range=[0.0, self.open_angle], stiffness=self.spring_stiffness,
            springref=self.open_angle + self.spring_preload, damping=self.hinge_damping,
            armature=0.001, solref_limit=[_STOP_TIMECONST, 1.0],
        )
        px, py, pz = self.plate_half
        plate.add_geom(
            name="stapler_plate", type=_BOX, size=[px, py, pz], pos=[px, 0.0, pz], mass=0.05,
            rgba=[0.75, 0.75, 0.78, 1.0], condim=3, friction=[1.0, 0.005, 0.0001],
            contype=0, conaffinity=robots.PAD_BIT,
        )
        x, _, z = self.press_local
        plate.add_geom(
            name="stapler_press_mark", type=_BOX, size=[0.01, 0.01, 0.0005], pos=[x, 0.0, z + 0.0005],
            rgba=[0.8, 0.15, 0.1, 1.0], contype=0, conaffinity=0, density=0.0, group=1,
        )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, int]:
        m = env.mj_model
        qadr = lambda n: int(m.jnt_qposadr[m.joint(n).id])
        return {
            "base_body": m.body("stapler").id,
            "plate_body": m.body("stapler_plate").id,
            "x_qadr": qadr("stapler_x"),
            "y_qadr": qadr("stapler_y"),
            "yaw_qadr": qadr("stapler_yaw"),
            "hinge_qadr": qadr("stapler_hinge"),
        }

    def hinge_angle(self, qpos: jax.Array, env: Env) -> jax.Array:
        """[] plate hinge angle (rad; 0 shut, ``open_angle`` open)."""
        return qpos[self._ids(env)["hinge_qadr"]]

    def pose_from_qpos(self, qpos: jax.Array, env: Env) -> jax.Array:
        """Stapler (x, y, yaw) [3] read from ``qpos`` [nq]."""
        ids = self._ids(env)
        return jnp.stack([qpos[ids["x_qadr"]], qpos[ids["y_qadr"]], qpos[ids["yaw_qadr"]]])

    def press_point(self, data: mjx.Data, env: Env) -> jax.Array:
        """World position [3] of the press point on the plate as it is now."""
        b = self._ids(env)["plate_body"]
        local = jnp.asarray(self.press_local, data.xpos.dtype)
        return data.xpos[b] + data.xmat[b].reshape(3, 3) @ local

    def shut_press_point(self, data: mjx.Data, env: Env) -> jax.Array:
        """World position [3] the press point has when the plate is shut (angle 0)."""
        b = self._ids(env)["base_body"]
        local = jnp.asarray(self.hinge_pos, data.xpos.dtype) + jnp.asarray(self.press_local, data.xpos.dtype)
        return data.xpos[b] + data.xmat[b].reshape(3, 3) @ local

    def placed_qpos(self, qpos: jax.Array, env: Env, x, y, yaw, angle=None) -> jax.Array:
        """``qpos`` [nq] with the stapler at (``x``, ``y``, ``yaw``) and the plate at
        ``angle`` (default: open)."""
        ids = self._ids(env)
        angle = self.open_angle if angle is None else angle
        vals = (("x_qadr", x), ("y_qadr", y), ("yaw_qadr", yaw), ("hinge_qadr", angle))
        for k, v in vals:
            qpos = qpos.at[ids[k]].set(jnp.asarray(v, qpos.dtype))
        return qpos

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, stapler on one side with a random yaw, plate open.

        Returns qpos [nq], ``{"side": []}``."""
        k_side, k_x, k_y, k_yaw = jax.random.split(key, 4)
        s = side_sign(k_side, self.side)
        u = lambda k, lo, hi: jax.random.uniform(k, (), minval=lo, maxval=hi)
        x = u(k_x, *self.stapler_x_range)
        ay = u(k_y, *self.stapler_y_range)
        yaw = u(k_yaw, -self.max_yaw, self.max_yaw)
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, x, s * ay, yaw)
        return qpos, {"side": s}

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: angle (rad), distance (m), [] bool checks."""
        angle = self.hinge_angle(data.qpos, env)
        p = self.press_point(data, env)
        ee = data.site_xpos[env.ee_site]  # [2, 3]
        xy = jnp.min(jnp.linalg.norm(ee[:, :2] - p[None, :2], axis=-1))
        return {
            "hinge_angle": angle,
            "ee_press_xy": xy,
            "shut": angle < self.closed_angle,
            "at_press_point": xy < self.success_xy,
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["shut"] & t["at_press_point"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirrored episode has its stapler on the other side."""
        return {**info, "side": -info["side"]} if "side" in info else info


TASK = TaskEntry(
    name="press_stapler",
    scene=PressStapler,
    robot="robot_a",
    step_limit=400,
    expert="equibim_jax.experts.press_stapler:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
