"""``click_bell``: press the button of a desk bell with a closed gripper (robot A).

Scene
-----
* **Bell**: a body on two slide joints (x, y) at table height, like ``place_empty_cup``'s
  coaster: its position is part of ``qpos`` (drawn by ``init``, mirrored by
  ``mirror_state``) and joint ``frictionloss`` stands in for table friction. It carries a
  flat square base (box) and a dome (ellipsoid), both visual only (no contacts).
* **Button**: a sphere on top of the dome, on a vertical slide joint ``bell_button`` with
  a spring (``stiffness``, rest point ``springref`` above the top of its travel, so the
  spring preloads the button against its upper stop), damping and a range
  ``[-button_travel, 0]``. ``qpos = 0`` is the button up, negative values are pressed.
  The button collides with the finger pads only (``contype 0, conaffinity PAD``): 4
  sphere-box pairs, one contact each, and nothing else in the task adds contacts.

Every geom is a primitive centred on the bell's vertical axis, so the scene is its own
mirror image about the bell's x-z plane and ``derive_symmetry`` maps the bell body,
joints and geoms to themselves (``bell_y`` flips sign, ``bell_x`` and the button keep it).

Initial state (mirror symmetric for ``side="both"``)
----------------------------------------------------
``s = +1`` (left, y > 0) or ``-1``. Bell at ``x ~ U(bell_x_range)``,
``y = s U(bell_y_range)``, button up, arms at home.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
Both: the button is down by at least ``press_depth`` (its slide joint, so it physically
moved), and some gripper is closed (normalised opening below ``closed_threshold``) with
its ee site within ``success_xy`` of the button centre in x-y.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from equibim_jax.sim import robots
from equibim_jax.sim.env import Env, Scene
from equibim_jax.sim.scenes import SIDES, side_sign
from equibim_jax.tasks import TaskEntry

__all__ = ["ClickBell", "TASK"]

_SLIDE = mujoco.mjtJoint.mjJNT_SLIDE
# Time constant (s) of the button's stops: twice the physics step, the stiffest MuJoCo
# integrates stably. The default (0.02 s) lets the preloaded spring push the button about
# half a millimetre past its upper stop.
_STOP_TIMECONST = 0.008


@dataclasses.dataclass(frozen=True)
class ClickBell(Scene):
    """The ``click_bell`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      side: ``"left"``, ``"right"`` or ``"both"`` (random side, mirror-symmetric).
      bell_x_range, bell_y_range: bell centre x and |y| ranges (m).
      base_half: half sizes of the square base (m).
      dome_radii: radii of the dome ellipsoid (m), centred on the base's top face.
      button_radius: radius of the button sphere (m).
      button_protrusion: how far the button's top stands above the dome's top at rest (m).
      button_travel: length of the button's slide range (m).
      spring_stiffness: button spring (N/m).
      spring_preload: rest point of the spring above the button's upper stop (m), so the
        spring holds the button up with ``stiffness * preload`` newtons.
      button_damping: button slide damping (N s/m).
      press_depth: how far the button must go down for success (m).
      success_xy: largest x-y distance from a closed gripper's ee site to the button (m).
      closed_threshold: a gripper counts as closed below this normalised opening.
    """

    side: str = "both"
    bell_x_range: tuple[float, float] = (0.18, 0.38)
    bell_y_range: tuple[float, float] = (0.05, 0.25)
    base_half: tuple[float, float, float] = (0.04, 0.04, 0.008)
    dome_radii: tuple[float, float, float] = (0.032, 0.032, 0.024)
    button_radius: float = 0.012
    button_protrusion: float = 0.014
    button_travel: float = 0.014
    spring_stiffness: float = 80.0
    spring_preload: float = 0.005
    button_damping: float = 1.0
    press_depth: float = 0.007
    success_xy: float = 0.025
    closed_threshold: float = 0.3
    name = "click_bell"
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.2))

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")
        for f in ("bell_x_range", "bell_y_range"):
            lo, hi = getattr(self, f)
            if not lo <= hi:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {(lo, hi)}")
        if self.bell_y_range[0] < 0:
            raise ValueError(f"bell_y_range holds |y| values (>= 0), got {self.bell_y_range}")
        positive = ("button_radius", "button_travel", "spring_stiffness", "press_depth",
                    "success_xy", "button_protrusion")
        for f in positive:
            if not getattr(self, f) > 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        if any(not v > 0 for v in (*self.base_half, *self.dome_radii)):
            raise ValueError("base_half and dome_radii must be positive")
        if self.spring_preload < 0 or self.button_damping < 0:
            raise ValueError("spring_preload and button_damping must be >= 0")
        if not self.press_depth < self.button_travel:
            raise ValueError(f"press_depth ({self.press_depth}) must be below button_travel "
                             f"({self.button_travel}): success must be reachable before the stop")
        if not 0 < self.closed_threshold < 1:
            raise ValueError(f"closed_threshold must be in (0, 1), got {self.closed_threshold}")

    # ------------------------------------------------------------------ model
    @property
    def button_rest_z(self) -> float:
        """Height of the button centre at rest, above the table top (m)."""
        dome_top = 2 * self.base_half[2] + self.dome_radii[2]
        return dome_top + self.button_protrusion - self.button_radius

    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the slide-jointed bell and its sprung button to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"click_bell is built for robot_a, got {info.name!r}")
        z0 = info.table_height
        bell = spec.worldbody.add_body(name="bell", pos=[0.0, 0.0, z0])
        for axis, jname in (([1.0, 0.0, 0.0], "bell_x"), ([0.0, 1.0, 0.0], "bell_y")):
            bell.add_joint(name=jname, type=_SLIDE, axis=axis, damping=5.0, frictionloss=2.0,
                           armature=0.01)
        bx, by, bz = self.base_half
        bell.add_geom(
            name="bell_base", type=mujoco.mjtGeom.mjGEOM_BOX, size=[bx, by, bz], pos=[0, 0, bz],
            mass=0.3, rgba=[0.2, 0.2, 0.22, 1.0], contype=0, conaffinity=0, group=1,
        )
        bell.add_geom(
            name="bell_dome", type=mujoco.mjtGeom.mjGEOM_ELLIPSOID, size=list(self.dome_radii),
            pos=[0, 0, 2 * bz], mass=0.1, rgba=[0.85, 0.7, 0.25, 1.0], contype=0, conaffinity=0,
            group=1,
        )
        button = bell.add_body(name="bell_button", pos=[0.0, 0.0, self.button_rest_z])
        button.add_joint(
            name="bell_button", type=_SLIDE, axis=[0.0, 0.0, 1.0],
            range=[-self.button_travel, 0.0], stiffness=self.spring_stiffness,
            springref=self.spring_preload, damping=self.button_damping, armature=0.005,
            solref_limit=[_STOP_TIMECONST, 1.0],
        )
        button.add_geom(
            name="bell_button", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[self.button_radius, 0, 0],
            mass=0.01, rgba=[0.8, 0.15, 0.1, 1.0], condim=3, friction=[1.0, 0.005, 0.0001],
            contype=0, conaffinity=robots.PAD_BIT,
        )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, int]:
        m = env.mj_model
        return {
            "button_body": m.body("bell_button").id,
            "x_qadr": int(m.jnt_qposadr[m.joint("bell_x").id]),
            "y_qadr": int(m.jnt_qposadr[m.joint("bell_y").id]),
            "button_qadr": int(m.jnt_qposadr[m.joint("bell_button").id]),
        }

    def button_top(self, data: mjx.Data, env: Env) -> jax.Array:
        """World position [3] of the top of the button sphere."""
        c = data.xpos[self._ids(env)["button_body"]]
        return c + jnp.array([0.0, 0.0, self.button_radius], c.dtype)

    def button_depth(self, qpos: jax.Array, env: Env) -> jax.Array:
        """[] how far the button is pressed down (m; 0 at its upper stop)."""
        return -qpos[self._ids(env)["button_qadr"]]

    def bell_xy(self, qpos: jax.Array, env: Env) -> jax.Array:
        """Bell centre [2] (x, y) read from ``qpos`` [nq]."""
        ids = self._ids(env)
        return jnp.stack([qpos[ids["x_qadr"]], qpos[ids["y_qadr"]]])

    def placed_qpos(self, qpos: jax.Array, env: Env, xy, depth=0.0) -> jax.Array:
        """``qpos`` [nq] with the bell at ``xy`` [2] and the button pressed ``depth`` m."""
        ids = self._ids(env)
        xy = jnp.asarray(xy, qpos.dtype)
        return (qpos.at[ids["x_qadr"]].set(xy[0]).at[ids["y_qadr"]].set(xy[1])
                .at[ids["button_qadr"]].set(-jnp.asarray(depth, qpos.dtype)))

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, bell on one side, button up. Returns qpos [nq], ``{"side": []}``."""
        k_side, k_x, k_y = jax.random.split(key, 3)
        s = side_sign(k_side, self.side)
        x = jax.random.uniform(k_x, (), minval=self.bell_x_range[0], maxval=self.bell_x_range[1])
        ay = jax.random.uniform(k_y, (), minval=self.bell_y_range[0], maxval=self.bell_y_range[1])
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, jnp.stack([x, s * ay]))
        return qpos, {"side": s}

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: distances (m) and [] bool checks."""
        depth = self.button_depth(data.qpos, env)
        top = self.button_top(data, env)
        ee = data.site_xpos[env.ee_site]  # [2, 3]
        xy = jnp.linalg.norm(ee[:, :2] - top[None, :2], axis=-1)  # [2]
        closed = env.gripper_opening(data.qpos) < self.closed_threshold  # [2]
        on_button = closed & (xy < self.success_xy)
        return {
            "button_depth": depth,
            "ee_button_xy": jnp.min(xy),
            "pressed": depth >= self.press_depth,
            "gripper_on_button": jnp.any(on_button),
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["pressed"] & t["gripper_on_button"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirrored episode has its bell on the other side."""
        return {**info, "side": -info["side"]} if "side" in info else info


TASK = TaskEntry(
    name="click_bell",
    scene=ClickBell,
    robot="robot_a",
    step_limit=400,
    expert="equibim_jax.experts.click_bell:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
