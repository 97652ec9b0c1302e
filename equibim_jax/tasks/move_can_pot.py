"""``move_can_pot``: pick a can up and stand it beside a pot, on the can's side (robot A).

Scene
-----
* **Can**: a free box of 5 x 5 x 10 cm and 60 g (a can with a square section) with a thin
  visual lid on top. A box and not a cylinder: the gripper pads are boxes, and MJX has no
  box-cylinder collision (``put_model`` refuses the model), nor does the ray-cast
  renderer draw cylinders. One box is also the cheapest grasped object in contacts. It
  uses :func:`robots.object_collision`.
* **Pot**: a 12 x 12 x 8 cm block of 0.5 kg on three joints (slide x, slide y, yaw hinge)
  at table height, with a visual dark opening on its top face and two visual handles
  front and back; so its position and yaw are in ``qpos`` (randomised by ``init``,
  mirrored by ``mirror_state``: x keeps its sign, y and yaw flip). At yaw 0 it is its
  own mirror image. Joint ``frictionloss`` stands in for table friction. It collides with
  objects only (``contype 0, conaffinity OBJECT``): the can cannot pass through it, the
  grippers never need to touch it.

Initial state (mirror symmetric for ``side="both"``)
----------------------------------------------------
``s = +1`` (left, y > 0) or ``-1``. Pot at ``x ~ U(pot_x_range)``, ``y = 0``, yaw
``~ U(-pot_max_yaw, pot_max_yaw)`` (pi/8; a symmetric law, so its mirror image, the negated
yaw, has the same law). Can at ``x ~ U(can_x_range)``, ``y = s U(can_y_range)``
(|y| in [0.2, 0.3], docs/tasks.md); the checks in ``__post_init__`` keep it clear of the
pot at any yaw. Arms at home.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
With ``dx, dy`` the can's centre minus the pot's centre (world frame) and ``s`` the
episode's side (``info["side"]``), all of:

* beside the pot on the can's own side: ``|dx| < success_dx`` (3.5 cm) and
  ``0 < s dy <= beside_max_dy`` (0.2 m);
* not in or on the pot: the can's centre outside the pot's (yawed) footprint and the can's
  bottom face within ``success_z`` (1.5 cm) of the table;
* upright: the can's z axis within ``max_tilt_deg`` (15 deg) of vertical;
* both grippers open (normalised opening > ``open_threshold`` = 0.65; a gripper squeezing
  the 5 cm can reads about 0.51, as for ``place_empty_cup``'s cup).

The object sizes and ranges are the original benchmark's, in metres, so its tolerances
(3.5 cm and 0.2 m) are kept unscaled.
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

__all__ = ["MoveCanPot", "TASK"]

_BOX = mujoco.mjtGeom.mjGEOM_BOX


@dataclasses.dataclass(frozen=True)
class MoveCanPot(Scene):
    """The ``move_can_pot`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      side: ``"left"``, ``"right"`` or ``"both"`` (random side, mirror-symmetric).
      can_x_range, can_y_range: can centre x and |y| ranges (m).
      pot_x_range: pot centre x range (m); its y is 0.
      pot_max_yaw: the pot's yaw is uniform in ``[-pot_max_yaw, pot_max_yaw]`` (rad).
      can_half, can_mass: can box half sizes (m) and mass (kg).
      pot_half, pot_mass: pot block half sizes (m) and mass (kg).
      success_dx: largest ``|dx|`` between can and pot centres (m).
      beside_max_dy: largest ``|dy|`` between can and pot centres (m).
      success_z: largest height of the can's bottom face above the table (m).
      max_tilt_deg: largest can tilt that counts as upright.
      open_threshold: a gripper counts as open above this normalised opening.
    """

    side: str = "both"
    can_x_range: tuple[float, float] = (0.22, 0.34)
    can_y_range: tuple[float, float] = (0.20, 0.30)
    pot_x_range: tuple[float, float] = (0.25, 0.33)
    pot_max_yaw: float = math.pi / 8
    can_half: tuple[float, float, float] = (0.025, 0.025, 0.05)
    can_mass: float = 0.06
    pot_half: tuple[float, float, float] = (0.06, 0.06, 0.04)
    pot_mass: float = 0.5
    success_dx: float = 0.035
    beside_max_dy: float = 0.2
    success_z: float = 0.015
    max_tilt_deg: float = 15.0
    open_threshold: float = 0.65
    name = "move_can_pot"
    # The table in front of the arms' bases (see place_empty_cup); mirror-symmetric.
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.2))

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")
        for f in ("can_x_range", "can_y_range", "pot_x_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {r}")
        for f in ("can_half", "pot_half"):
            h = getattr(self, f)
            if len(h) != 3 or min(h) <= 0:
                raise ValueError(f"{f} must be three positive half sizes, got {h}")
        if not 0.0 <= self.pot_max_yaw < math.pi / 2:
            raise ValueError(f"pot_max_yaw must be in [0, pi/2), got {self.pot_max_yaw}")
        reach = self.pot_reach_y(self.pot_max_yaw) + self.can_half[1]
        if self.can_y_range[0] <= reach:
            raise ValueError(
                f"can_y_range[0] = {self.can_y_range[0]} must exceed the pot's half extent in "
                f"y at pot_max_yaw plus the can's half width ({reach:.4f} m), so that the can "
                f"starts clear of the pot")
        if self.beside_max_dy <= reach:
            raise ValueError(f"beside_max_dy = {self.beside_max_dy} leaves no room beside the pot "
                             f"(the can needs |dy| > {reach:.4f} m)")
        for f in ("can_mass", "pot_mass", "success_dx", "success_z"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        if not 0.0 < self.open_threshold < 1.0:
            raise ValueError(f"open_threshold must be in (0, 1), got {self.open_threshold}")

    def pot_reach_y(self, yaw):
        """Half extent in y of the pot's footprint at ``yaw`` (rad, float or [] array)."""
        hx, hy = self.pot_half[0], self.pot_half[1]
        if isinstance(yaw, (int, float)):
            return hx * abs(math.sin(yaw)) + hy * abs(math.cos(yaw))
        return hx * jnp.abs(jnp.sin(yaw)) + hy * jnp.abs(jnp.cos(yaw))

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free can and the slide/yaw-jointed pot to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"move_can_pot is built for robot_a, got {info.name!r}")
        z0 = info.table_height
        cx, cy, cz = self.can_half
        can = spec.worldbody.add_body(name="can", pos=[0.3, 0.0, z0 + cz])
        can.add_freejoint(name="can")
        can.add_geom(
            name="can", type=_BOX, size=[cx, cy, cz], mass=self.can_mass,
            rgba=[0.75, 0.78, 0.82, 1.0], condim=4, friction=[1.0, 0.005, 0.0001],
            **robots.object_collision(),
        )
        can.add_geom(  # the lid (visual only, massless)
            name="can_lid", type=_BOX, size=[cx - 0.003, cy - 0.003, 0.0005],
            pos=[0.0, 0.0, cz + 0.0005], rgba=[0.8, 0.15, 0.12, 1.0], contype=0,
            conaffinity=0, density=0.0, group=1,
        )
        px, py, pz = self.pot_half
        pot = spec.worldbody.add_body(name="pot", pos=[0.0, 0.0, z0 + pz])
        for axis, jname, jtype in (([1.0, 0.0, 0.0], "pot_x", mujoco.mjtJoint.mjJNT_SLIDE),
                                   ([0.0, 1.0, 0.0], "pot_y", mujoco.mjtJoint.mjJNT_SLIDE),
                                   ([0.0, 0.0, 1.0], "pot_yaw", mujoco.mjtJoint.mjJNT_HINGE)):
            pot.add_joint(name=jname, type=jtype, axis=axis, damping=5.0, frictionloss=1.0,
                          armature=0.01)
        pot.add_geom(
            name="pot", type=_BOX, size=[px, py, pz], mass=self.pot_mass,
            rgba=[0.3, 0.32, 0.36, 1.0], condim=3, friction=[1.0, 0.005, 0.0001],
            contype=0, conaffinity=robots.OBJECT_BIT,
        )
        visual = dict(contype=0, conaffinity=0, density=0.0, group=1)
        pot.add_geom(  # the opening
            name="pot_opening", type=_BOX, size=[px - 0.008, py - 0.008, 0.0005],
            pos=[0.0, 0.0, pz + 0.0005], rgba=[0.08, 0.08, 0.09, 1.0], **visual,
        )
        for sign, hname in ((1.0, "pot_handle_front"), (-1.0, "pot_handle_back")):
            pot.add_geom(
                name=hname, type=_BOX, size=[0.012, 0.025, 0.006],
                pos=[sign * (px + 0.012), 0.0, pz - 0.012], rgba=[0.15, 0.15, 0.17, 1.0], **visual,
            )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, int]:
        m = env.mj_model
        return {
            "can_body": m.body("can").id,
            "pot_body": m.body("pot").id,
            "can_qadr": int(m.jnt_qposadr[m.joint("can").id]),
            "pot_x_qadr": int(m.jnt_qposadr[m.joint("pot_x").id]),
            "pot_y_qadr": int(m.jnt_qposadr[m.joint("pot_y").id]),
            "pot_yaw_qadr": int(m.jnt_qposadr[m.joint("pot_yaw").id]),
        }

    def can_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """Can centre [3] and rotation matrix [3, 3] (world frame)."""
        b = self._ids(env)["can_body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def pot_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """Pot centre [3] and rotation matrix [3, 3] (world frame)."""
        b = self._ids(env)["pot_body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def poses_from_qpos(self, qpos: jax.Array, env: Env) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(can centre [3], pot centre [3], pot yaw []) read directly from ``qpos`` [nq]."""
        ids = self._ids(env)
        a = ids["can_qadr"]
        pot = jnp.stack([
            qpos[ids["pot_x_qadr"]], qpos[ids["pot_y_qadr"]],
            jnp.asarray(env.info.table_height + self.pot_half[2], qpos.dtype),
        ])
        return qpos[a : a + 3], pot, qpos[ids["pot_yaw_qadr"]]

    def placed_qpos(self, qpos: jax.Array, env: Env, can_xyz, can_quat=(1.0, 0.0, 0.0, 0.0),
                    pot_xy_yaw=None) -> jax.Array:
        """``qpos`` [nq] with the can's free joint at ``can_xyz`` [3], ``can_quat`` [4], and the
        pot at ``pot_xy_yaw`` = (x, y, yaw) if given (for building states by hand)."""
        ids = self._ids(env)
        a = ids["can_qadr"]
        pose = jnp.concatenate([jnp.asarray(can_xyz, qpos.dtype), jnp.asarray(can_quat, qpos.dtype)])
        qpos = qpos.at[a : a + 7].set(pose)
        if pot_xy_yaw is not None:
            x, y, yaw = pot_xy_yaw
            qpos = (qpos.at[ids["pot_x_qadr"]].set(x).at[ids["pot_y_qadr"]].set(y)
                    .at[ids["pot_yaw_qadr"]].set(yaw))
        return qpos

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, pot at the centre, can on one side. Returns qpos [nq], ``{"side": []}``."""
        k_side, k_cx, k_cy, k_px, k_yaw = jax.random.split(key, 5)
        s = side_sign(k_side, self.side)
        u = lambda k, lo, hi: jax.random.uniform(k, (), minval=lo, maxval=hi)
        can = jnp.stack([u(k_cx, *self.can_x_range), s * u(k_cy, *self.can_y_range),
                         jnp.asarray(env.info.table_height + self.can_half[2])])
        pot = (u(k_px, *self.pot_x_range), jnp.zeros(()), u(k_yaw, -self.pot_max_yaw, self.pot_max_yaw))
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, can, pot_xy_yaw=pot)
        return qpos, {"side": s}

    def terms(self, data: mjx.Data, side: jax.Array, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state for the episode side ``side`` ([] +-1):
        distances (m), tilt (deg) and [] bool checks."""
        can, rot = self.can_pose(data, env)
        pot, pot_rot = self.pot_pose(data, env)
        d = can - pot
        local = pot_rot[:2, :2].T @ d[:2]  # can centre in the pot's frame (x, y)
        inside = jnp.all(jnp.abs(local) < jnp.asarray(self.pot_half[:2]))
        bottom = can[2] - self.can_half[2] * rot[2, 2]
        tilt = jnp.degrees(jnp.arccos(jnp.clip(rot[2, 2], -1.0, 1.0)))
        opening = env.gripper_opening(data.qpos)
        height = bottom - env.info.table_height
        return {
            "can_pot_dx": d[0],
            "can_pot_dy_own_side": side * d[1],
            "can_height": height,
            "can_tilt_deg": tilt,
            "min_gripper_opening": jnp.min(opening),
            "beside": (jnp.abs(d[0]) < self.success_dx) & (side * d[1] > 0.0)
                      & (side * d[1] <= self.beside_max_dy),
            "clear_of_pot": ~inside & (jnp.abs(height) < self.success_z),
            "upright": tilt < self.max_tilt_deg,
            "released": jnp.all(opening > self.open_threshold),
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics.

        ``info["side"]`` ([] +-1, set by ``init``) is the side the can must end up on."""
        t = self.terms(data, info["side"], env)
        success = t["beside"] & t["clear_of_pot"] & t["upright"] & t["released"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirrored episode has its can on the other side."""
        return {**info, "side": -info["side"]} if "side" in info else info


TASK = TaskEntry(
    name="move_can_pot",
    scene=MoveCanPot,
    robot="robot_a",
    step_limit=400,
    expert="equibim_jax.experts.move_can_pot:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
