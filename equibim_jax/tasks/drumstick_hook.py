"""``drumstick_hook``: one arm picks a drumstick up from the table and hangs it on a rack
at the centre of the table (robot B).

Scene
-----
* **Drumstick**: one free body (joint ``drumstick``) lying flat on the table: a shaft
  (capsule, ``stick_radius`` 9 mm, segment ``2 * stick_half_length`` = 15 cm, so 16.8 cm
  long) along the body's x axis, centred on the body origin, and a bead (sphere,
  ``tip_radius`` 8 mm, thinner than the shaft so the stick lies on its shaft) at
  ``tip_offset`` along +x (the tip; the stick is 17.7 cm long in all). Masses
  ``shaft_mass`` + ``tip_mass`` (50 g). The shaft collides as a task object
  (:func:`robots.object_collision`: table, pads, palms, rack), with the jaw pads' contact
  softness (``solref``, ``solimp``), so that a pinched stick does not creep along the pads
  while the gripper turns; the bead collides with the table only (``contype 0``,
  ``conaffinity TABLE``), which keeps the contact count down. Both geoms lie on the
  body's x axis, so the stick is its own mirror image about its x-z plane.
* **Rack** (static, welded to the world, its own mirror image about y = 0): two
  horizontal pegs (capsules of radius ``peg_radius``) along x at ``y = +-peg_y`` and
  height ``peg_z``, from ``hook_x + peg_back`` (where a short upward tip of
  ``tip_height`` stops the stick from sliding off towards the robot) to ``hook_x +
  peg_front``, where two posts carry them (visual only). The pegs and tips collide with
  task objects only (``contype 0``, ``conaffinity OBJECT``): the grippers pass through
  them. A stick laid across both pegs, its centre of mass between them, hangs there by
  gravity and friction.

Initial state
-------------
``s = +1`` (stick on the left, y > 0) or ``-1``. The stick's body origin (the shaft's
centre) at ``x ~ U(stick_x_range)``, ``y = s U(stick_y_range)``, resting on the table
(``z = stick_radius``), its axis at yaw ``s u`` with ``u ~ U(yaw_range)`` (about +90 deg:
the stick lies roughly along y, its tip pointing away from the mirror plane); its
quaternion is ``s (cos(yaw / 2), 0, 0, sin(yaw / 2))``, whose mirror image (as
``env.sym.qpos`` maps it) is the other side's draw. Arms at home. ``wide_init`` widens
every range (the ``|y|`` range is kept above ``min_abs_y``, so the whole stick stays on
its side); ``mirrored_orientation`` draws the yaw as ``-s u``;
``asymmetric_quality`` sets ``info["perturbed"]`` (the expert then releases the stick
short of the rack). The default law is mirror-symmetric.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
All of: the shaft touches the rack (some shaft-peg/tip pair in MJX's contact list has a
distance below ``touch_tol``); neither stick geom touches the table (every stick-table
distance above ``touch_tol``); the stick's centre of mass is above ``success_height``
(the pegs' top is at ``peg_z + peg_radius``); no gripper pad or palm touches the shaft
(every such distance above ``release_tol``); the stick is at rest (its origin's speed
below ``rest_speed``, so a stick that grazes the rack while falling does not count).
MJX lists every candidate pair with its distance (host MuJoCo only those within the
margin, so a hand-built state converted with ``mjx.put_data`` lists only near pairs; a
pair that is not listed counts as far).
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

__all__ = ["DrumstickHook", "TASK"]

_CAPSULE = mujoco.mjtGeom.mjGEOM_CAPSULE
_SPHERE = mujoco.mjtGeom.mjGEOM_SPHERE

_STICK_RGBA = [0.8, 0.6, 0.35, 1.0]
_RACK_RGBA = [0.3, 0.3, 0.35, 1.0]


@dataclasses.dataclass(frozen=True)
class DrumstickHook(ShiftScene):
    """The ``drumstick_hook`` task as an env scene (robot B); shift options from
    :class:`~equibim_jax.tasks._shifts.ShiftScene`.

    Attributes:
      stick_x_range, stick_y_range: the stick's centre x and |y| ranges (m).
      yaw_range: range of ``u`` (rad); the stick's yaw is ``s u`` (``-s u`` with
        ``mirrored_orientation``).
      min_abs_y: lowest |y| of the stick's centre under ``wide_init`` (m).
      stick_radius, stick_half_length: the shaft capsule's radius and half segment (m).
      tip_radius, tip_offset: the bead's radius and its centre's x in the body frame (m).
      shaft_mass, tip_mass: masses (kg).
      hook_x: x of the rack's centre (the stick hangs across the pegs about here) (m).
      peg_y, peg_z, peg_radius: the pegs' |y|, axis height and radius (m).
      peg_back, peg_front: x of the pegs' ends relative to ``hook_x`` (m); the upward tips
        stand at the back end (towards the robot), the posts at the front end.
      tip_height: height of the upward tips above the pegs' axis (m).
      success_height: the stick's centre of mass must be above this (m).
      touch_tol: a contact distance below this counts as touching (m).
      release_tol: every pad/palm-shaft distance must exceed this (m).
      rest_speed: the stick's origin must move slower than this (m/s): a stick that only
        grazes the rack while falling does not count.
    """

    stick_x_range: tuple[float, float] = (0.15, 0.21)
    stick_y_range: tuple[float, float] = (0.15, 0.23)
    yaw_range: tuple[float, float] = (math.pi / 2 - 0.3, math.pi / 2 + 0.3)
    min_abs_y: float = 0.10
    stick_radius: float = 0.009
    stick_half_length: float = 0.075
    tip_radius: float = 0.008
    tip_offset: float = 0.085
    shaft_mass: float = 0.045
    tip_mass: float = 0.005
    hook_x: float = 0.2
    peg_y: float = 0.04
    peg_z: float = 0.12
    peg_radius: float = 0.005
    peg_back: float = -0.08
    peg_front: float = 0.07
    tip_height: float = 0.025
    success_height: float = 0.1
    touch_tol: float = 1e-3
    release_tol: float = 2e-3
    rest_speed: float = 0.05
    name = "drumstick_hook"
    main_object = "drumstick"
    # the table in front of the arms' bases, up to above the rack; mirror-symmetric
    point_cloud_crop = ((0.05, -0.4, 0.002), (0.45, 0.4, 0.3))

    def __post_init__(self):
        super().__post_init__()
        for f in ("stick_x_range", "stick_y_range", "yaw_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{self.name}: {f} must be (low, high) with low <= high, got {r}")
        for f in ("stick_radius", "stick_half_length", "tip_radius", "shaft_mass", "tip_mass",
                  "peg_radius", "tip_height", "success_height"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{self.name}: {f} must be positive, got {getattr(self, f)}")
        if self.tip_radius > self.stick_radius:
            raise ValueError(f"{self.name}: tip_radius must not exceed stick_radius (the stick "
                             f"lies on its shaft), got {self.tip_radius} > {self.stick_radius}")
        if self.min_abs_y <= self.stick_extent:
            raise ValueError(f"{self.name}: min_abs_y must exceed the stick's half extent "
                             f"{self.stick_extent:.3f} m so it lies wholly on its side, got "
                             f"{self.min_abs_y}")
        if self.stick_y_range[0] < self.min_abs_y:
            raise ValueError(f"{self.name}: stick_y_range must start at or above min_abs_y "
                             f"{self.min_abs_y}, got {self.stick_y_range}")
        if not self.peg_back < 0 < self.peg_front:
            raise ValueError(f"{self.name}: need peg_back < 0 < peg_front, got {self.peg_back}, "
                             f"{self.peg_front}")
        if not 0 < self.peg_y < self.stick_half_length:
            raise ValueError(f"{self.name}: peg_y must be in (0, stick_half_length), got "
                             f"{self.peg_y}")
        if self.touch_tol < 0 or self.release_tol < 0:
            raise ValueError(f"{self.name}: touch_tol and release_tol must be >= 0")
        if not self.rest_speed > 0:
            raise ValueError(f"{self.name}: rest_speed must be positive, got {self.rest_speed}")

    @property
    def stick_extent(self) -> float:
        """Distance (m) from the body origin to the farthest point of the stick."""
        return max(self.stick_half_length + self.stick_radius, self.tip_offset + self.tip_radius)

    @property
    def com_offset(self) -> float:
        """x of the stick's centre of mass in its body frame (m)."""
        return self.tip_mass * self.tip_offset / (self.shaft_mass + self.tip_mass)

    @property
    def hang_height(self) -> float:
        """Height (m) of the stick's axis when it lies across the pegs."""
        return self.peg_z + self.peg_radius + self.stick_radius

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free drumstick and the static rack to robot B's spec."""
        if info.name != "robot_b":
            raise ValueError(f"{self.name} is built for robot_b, got {info.name!r}")
        z0 = info.table_height
        body = spec.worldbody.add_body(name="drumstick", pos=[0.2, 0.2, z0 + self.stick_radius])
        body.add_freejoint(name="drumstick")
        h = self.stick_half_length
        body.add_geom(
            name="drumstick_shaft", type=_CAPSULE, size=[self.stick_radius, 0, 0],
            fromto=[-h, 0, 0, h, 0, 0], mass=self.shaft_mass, rgba=_STICK_RGBA, condim=4,
            friction=[1.0, 0.005, 0.0001], solref=[0.01, 1.0], solimp=[0.95, 0.99, 0.001, 0.5, 2.0],
            **robots.object_collision(),
        )
        body.add_geom(
            name="drumstick_tip", type=_SPHERE, size=[self.tip_radius, 0, 0],
            pos=[self.tip_offset, 0, 0], mass=self.tip_mass, rgba=_STICK_RGBA, condim=3,
            friction=[1.0, 0.005, 0.0001], contype=0, conaffinity=robots.TABLE_BIT,
        )
        rack = {"contype": 0, "conaffinity": robots.OBJECT_BIT, "condim": 3,
                "friction": [1.0, 0.005, 0.0001], "rgba": _RACK_RGBA}
        x0, x1 = self.hook_x + self.peg_back, self.hook_x + self.peg_front
        zp = z0 + self.peg_z
        for tag, y in (("left", self.peg_y), ("right", -self.peg_y)):
            spec.worldbody.add_geom(name=f"rack_peg_{tag}", type=_CAPSULE,
                                    size=[self.peg_radius, 0, 0], fromto=[x0, y, zp, x1, y, zp],
                                    **rack)
            spec.worldbody.add_geom(name=f"rack_tip_{tag}", type=_CAPSULE,
                                    size=[self.peg_radius, 0, 0],
                                    fromto=[x0, y, zp, x0, y, zp + self.tip_height], **rack)
            spec.worldbody.add_geom(name=f"rack_post_{tag}", type=_CAPSULE,
                                    size=[1.6 * self.peg_radius, 0, 0],
                                    fromto=[x1, y, z0, x1, y, zp], contype=0, conaffinity=0,
                                    rgba=_RACK_RGBA)

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict:
        m = env.mj_model
        g = lambda n: m.geom(n).id
        pads = [g(p) for side in env.info.gripper_pads for p in side]
        palms = [g(f"{side}_palm") for side in env.info.sides]
        return {
            "body": m.body("drumstick").id,
            "qadr": int(m.jnt_qposadr[m.joint("drumstick").id]),
            "dofadr": int(m.jnt_dofadr[m.joint("drumstick").id]),
            "shaft": g("drumstick_shaft"),
            "tip": g("drumstick_tip"),
            "table": g("table"),
            "rack": np.array([g(f"rack_{k}_{t}") for k in ("peg", "tip")
                              for t in ("left", "right")]),
            "gripper": np.array(pads + palms),
        }

    def stick_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """The stick's body origin (the shaft's centre) [3] and rotation matrix [3, 3]."""
        b = self._ids(env)["body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def stick_from_qpos(self, qpos: jax.Array, env: Env) -> tuple[jax.Array, jax.Array]:
        """(body origin [3], axis direction [3], a unit vector towards the tip) from ``qpos``."""
        a = self._ids(env)["qadr"]
        w, x, y, z = qpos[a + 3], qpos[a + 4], qpos[a + 5], qpos[a + 6]
        n = w * w + x * x + y * y + z * z
        axis = jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)]) / n
        return qpos[a : a + 3], axis

    def placed_qpos(self, qpos: jax.Array, env: Env, xyz, quat=(1.0, 0.0, 0.0, 0.0)) -> jax.Array:
        """``qpos`` [nq] with the stick's free joint at ``xyz`` [3], ``quat`` [4] (w, x, y, z)."""
        a = self._ids(env)["qadr"]
        pose = jnp.concatenate([jnp.asarray(xyz, qpos.dtype), jnp.asarray(quat, qpos.dtype)])
        return qpos.at[a : a + 7].set(pose)

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, the stick flat on the table on side ``s``.

        Returns qpos [nq] and ``{"side": [] f32, "yaw": [] f32, "perturbed": [] bool}``.
        """
        k_side, k_x, k_y, k_yaw, k_pert = jax.random.split(key, 5)
        s = self.draw_side(k_side)
        x = self.uniform(k_x, self.stick_x_range)
        y = s * self.uniform_abs(k_y, self.stick_y_range, self.min_abs_y)
        yaw = self.draw_yaw(k_yaw, s, self.yaw_range).astype(jnp.float32)
        perturbed = self.draw_perturbed(k_pert, s)
        z = jnp.asarray(env.info.table_height + self.stick_radius, jnp.float32)
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, jnp.stack([x, y, z]),
                                self.signed_yaw_quat(yaw, s))
        return qpos, {"side": s, "yaw": yaw, "perturbed": perturbed}

    def contact_distances(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Smallest distances [] (m) in MJX's contact list of the shaft-rack pairs, the
        stick-table pairs and the shaft-gripper (pads and palms) pairs; 1.0 when a group
        has no listed pair."""
        ids = self._ids(env)
        c = data._impl.contact
        g1, g2 = c.geom[:, 0], c.geom[:, 1]
        big = jnp.asarray(1.0, c.dist.dtype)

        def between(a, others):
            others = jnp.asarray(others)
            hit = lambda g: jnp.any(g[:, None] == others[None, :], axis=1)
            pair = ((g1 == a) & hit(g2)) | ((g2 == a) & hit(g1))
            return pair

        rack = between(ids["shaft"], ids["rack"])
        table = between(ids["shaft"], [ids["table"]]) | between(ids["tip"], [ids["table"]])
        grip = between(ids["shaft"], ids["gripper"])
        d = lambda p: jnp.minimum(jnp.min(jnp.where(p, c.dist, big), initial=big), big)
        return {"rack": d(rack), "table": d(table), "gripper": d(grip)}

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: distances and heights (m), [] bool checks."""
        dist = self.contact_distances(data, env)
        ids = self._ids(env)
        com = data.xipos[ids["body"]]
        height = com[2] - env.info.table_height
        speed = jnp.linalg.norm(data.qvel[ids["dofadr"] : ids["dofadr"] + 3])
        return {
            "stick_height": height,
            "stick_speed": speed,
            "rack_dist": dist["rack"],
            "table_dist": dist["table"],
            "gripper_dist": dist["gripper"],
            "on_rack": dist["rack"] < self.touch_tol,
            "off_table": dist["table"] > self.touch_tol,
            "raised": height > self.success_height,
            "released": dist["gripper"] > self.release_tol,
            "at_rest": speed < self.rest_speed,
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["on_rack"] & t["off_table"] & t["raised"] & t["released"] & t["at_rest"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics


TASK = TaskEntry(
    name="drumstick_hook",
    scene=DrumstickHook,
    robot="robot_b",
    step_limit=600,
    expert="equibim_jax.experts.drumstick_hook:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
