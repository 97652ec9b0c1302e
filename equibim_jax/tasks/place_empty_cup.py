"""``place_empty_cup``: pick an empty cup up and put it down on a coaster (robot A).

Scene
-----
* **Cup**: a free body, a 5 x 5 x 8 cm box of 50 g (one collision geom, so 4 contacts with
  the table, 4 with each of the six gripper geoms and 4 with the coaster) with a thin dark
  visual plate on its top face that marks the opening. A box rather than a ring of wall
  geoms because contacts dominate MJX's cost on the CPU; the flat faces also give
  the pads a face-to-face friction grasp. It uses :func:`robots.object_collision`.
* **Coaster**: a 9 x 9 x 0.8 cm plate on two slide joints (x, y) at table height, so its
  position is part of ``qpos`` (randomised by ``init`` and mirrored by ``mirror_state``)
  while its height and orientation are held by the joints instead of by table contacts.
  Table friction is stood in for by joint ``frictionloss``. It collides with objects only
  (``contype 0, conaffinity OBJECT``): the grippers never need to touch it, and dropping
  its 6 gripper pairs and its table pair keeps the contact count down.

Initial state (mirror symmetric for ``side="both"``)
----------------------------------------------------
``s = +1`` (left, y > 0) or ``-1``. Cup at ``x ~ U(cup_x_range)``, ``y = s U(cup_y_range)``
(|y| in [0.15, 0.30], docs/tasks.md). Coaster on the same side, nearer the centre:
``x ~ U(coaster_x_range)``, ``|y| ~ U(coaster_y_min, |y_cup| - min_gap)``, so the two are
at least ``min_gap`` apart in y and never overlap. Arms at home.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
All of: cup centre within ``success_xy`` (3.5 cm) of the coaster centre in xy; the cup's
bottom face within ``success_z`` (1.5 cm) of the coaster's top face; the cup upright (its
z axis within ``max_tilt_deg`` = 15 deg of vertical); both grippers open (normalised
opening > ``open_threshold``). The threshold is 0.65, not 0.5: a gripper squeezing the
5 cm cup reads opening 0.51, so 0.5 would count a held cup as released; at 0.65 the pads
are at least 6 mm clear of the cup's sides.
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

__all__ = ["PlaceEmptyCup", "held_opening", "TASK"]

_BOX = mujoco.mjtGeom.mjGEOM_BOX


@dataclasses.dataclass(frozen=True)
class PlaceEmptyCup(Scene):
    """The ``place_empty_cup`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      side: ``"left"``, ``"right"`` or ``"both"`` (random side, mirror-symmetric).
      cup_x_range, cup_y_range: cup centre x and |y| ranges (m).
      coaster_x_range: coaster centre x range (m).
      coaster_y_min: smallest coaster |y| (m).
      min_gap: smallest ``|y_cup| - |y_coaster|`` (m); must exceed the half widths of cup
        and coaster together so they never overlap.
      cup_half: cup box half sizes (m); cup_mass in kg.
      coaster_half: coaster half sizes (m).
      success_xy, success_z: placement tolerances (m).
      max_tilt_deg: largest cup tilt that counts as upright.
      open_threshold: a gripper counts as open above this normalised opening.
    """

    side: str = "both"
    cup_x_range: tuple[float, float] = (0.22, 0.34)
    cup_y_range: tuple[float, float] = (0.15, 0.30)
    coaster_x_range: tuple[float, float] = (0.22, 0.34)
    coaster_y_min: float = 0.03
    min_gap: float = 0.10
    cup_half: tuple[float, float, float] = (0.025, 0.025, 0.04)
    cup_mass: float = 0.05
    coaster_half: tuple[float, float, float] = (0.045, 0.045, 0.004)
    success_xy: float = 0.035
    success_z: float = 0.015
    max_tilt_deg: float = 15.0
    open_threshold: float = 0.65
    name = "place_empty_cup"
    # The point cloud sees the table in front of the arms' bases (cup, coaster and a gripper
    # that reaches down), not the arms at rest: with 64 points on 2 CPU cores, cropping to
    # the workspace of the task is what gives the policy a usable view of the objects, as
    # DP3 crops each task's cloud to its workspace.
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.2))

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")
        for f in ("cup_x_range", "cup_y_range", "coaster_x_range"):
            lo, hi = getattr(self, f)
            if not lo <= hi:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {(lo, hi)}")
        if self.cup_y_range[0] - self.min_gap < self.coaster_y_min:
            raise ValueError(
                f"cup_y_range[0] - min_gap = {self.cup_y_range[0] - self.min_gap:.3f} is below "
                f"coaster_y_min = {self.coaster_y_min}: no room for the coaster"
            )
        if self.min_gap <= self.cup_half[1] + self.coaster_half[1]:
            raise ValueError("min_gap must exceed cup_half[1] + coaster_half[1] (no overlap)")
        if self.coaster_y_min < 0:
            raise ValueError(f"coaster_y_min must be >= 0, got {self.coaster_y_min}")

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free cup and the slide-jointed coaster to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"place_empty_cup is built for robot_a, got {info.name!r}")
        z0 = info.table_height
        hx, hy, hz = self.cup_half
        cup = spec.worldbody.add_body(name="cup", pos=[0.3, 0.0, z0 + hz])
        cup.add_freejoint(name="cup")
        cup.add_geom(
            name="cup", type=_BOX, size=[hx, hy, hz], mass=self.cup_mass,
            rgba=[0.92, 0.92, 0.95, 1.0], condim=4, friction=[1.0, 0.005, 0.0001],
            **robots.object_collision(),
        )
        # The opening: a dark plate just above the top face (visual only, massless).
        cup.add_geom(
            name="cup_opening", type=_BOX, size=[hx - 0.004, hy - 0.004, 0.0005],
            pos=[0.0, 0.0, hz + 0.0005], rgba=[0.25, 0.2, 0.15, 1.0], contype=0,
            conaffinity=0, density=0.0, group=1,
        )
        cx, cy, cz = self.coaster_half
        coaster = spec.worldbody.add_body(name="coaster", pos=[0.0, 0.0, z0 + cz])
        for axis, jname in (([1.0, 0.0, 0.0], "coaster_x"), ([0.0, 1.0, 0.0], "coaster_y")):
            coaster.add_joint(
                name=jname, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis, damping=2.0,
                frictionloss=0.3, armature=0.01,
            )
        coaster.add_geom(
            name="coaster", type=_BOX, size=[cx, cy, cz], mass=0.05,
            rgba=[0.55, 0.32, 0.18, 1.0], condim=3, friction=[1.0, 0.005, 0.0001],
            contype=0, conaffinity=robots.OBJECT_BIT,
        )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, int]:
        m = env.mj_model
        return {
            "cup_body": m.body("cup").id,
            "coaster_body": m.body("coaster").id,
            "cup_qadr": int(m.jnt_qposadr[m.joint("cup").id]),
            "coaster_qadr": int(m.jnt_qposadr[m.joint("coaster_x").id]),
            "coaster_y_qadr": int(m.jnt_qposadr[m.joint("coaster_y").id]),
        }

    def cup_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """Cup centre [3] and rotation matrix [3, 3] (world frame)."""
        b = self._ids(env)["cup_body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def coaster_position(self, data: mjx.Data, env: Env) -> jax.Array:
        """Coaster centre [3] (world frame)."""
        return data.xpos[self._ids(env)["coaster_body"]]

    def positions_from_qpos(self, qpos: jax.Array, env: Env) -> tuple[jax.Array, jax.Array]:
        """(cup centre [3], coaster centre [3]) read directly from ``qpos`` [nq]."""
        ids = self._ids(env)
        a = ids["cup_qadr"]
        cup = qpos[a : a + 3]
        coaster = jnp.stack([
            qpos[ids["coaster_qadr"]], qpos[ids["coaster_y_qadr"]],
            jnp.asarray(env.info.table_height + self.coaster_half[2], qpos.dtype),
        ])
        return cup, coaster

    def placed_qpos(self, qpos: jax.Array, env: Env, cup_xyz, cup_quat=(1.0, 0.0, 0.0, 0.0)) -> jax.Array:
        """``qpos`` [nq] with the cup's free joint set to ``cup_xyz`` [3] and ``cup_quat`` [4].

        For building states by hand (tests, resets from data)."""
        a = self._ids(env)["cup_qadr"]
        pose = jnp.concatenate([jnp.asarray(cup_xyz, qpos.dtype), jnp.asarray(cup_quat, qpos.dtype)])
        return qpos.at[a : a + 7].set(pose)

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, cup and coaster sampled on one side. Returns qpos [nq], ``{"side": []}``."""
        k_side, k_cx, k_cy, k_kx, k_ky = jax.random.split(key, 5)
        s = side_sign(k_side, self.side)
        u = lambda k, lo, hi: jax.random.uniform(k, (), minval=lo, maxval=hi)
        cup_x = u(k_cx, *self.cup_x_range)
        cup_ay = u(k_cy, *self.cup_y_range)
        co_x = u(k_kx, *self.coaster_x_range)
        co_ay = u(k_ky, self.coaster_y_min, cup_ay - self.min_gap)
        ids = self._ids(env)
        qpos = jnp.asarray(env.home_qpos)
        qpos = self.placed_qpos(qpos, env, jnp.stack([
            cup_x, s * cup_ay, jnp.asarray(env.info.table_height + self.cup_half[2])]))
        qpos = qpos.at[ids["coaster_qadr"]].set(co_x).at[ids["coaster_y_qadr"]].set(s * co_ay)
        return qpos, {"side": s}

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: distances (m), tilt (deg) and [] bool checks."""
        cup, rot = self.cup_pose(data, env)
        coaster = self.coaster_position(data, env)
        xy = jnp.linalg.norm(cup[:2] - coaster[:2])
        cup_bottom = cup[2] - self.cup_half[2]
        coaster_top = coaster[2] + self.coaster_half[2]
        dz = cup_bottom - coaster_top
        tilt = jnp.degrees(jnp.arccos(jnp.clip(rot[2, 2], -1.0, 1.0)))
        opening = env.gripper_opening(data.qpos)
        return {
            "cup_coaster_xy": xy,
            "cup_coaster_dz": dz,
            "cup_tilt_deg": tilt,
            "cup_height": cup_bottom - env.info.table_height,
            "min_gripper_opening": jnp.min(opening),
            "on_coaster": (xy < self.success_xy) & (jnp.abs(dz) < self.success_z),
            "upright": tilt < self.max_tilt_deg,
            "released": jnp.all(opening > self.open_threshold),
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["on_coaster"] & t["upright"] & t["released"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirrored episode has its objects on the other side."""
        return {**info, "side": -info["side"]} if "side" in info else info


def held_opening(info: robots.RobotInfo, cup_width: float) -> float:
    """Normalised opening at which robot A's pads touch a box of width ``cup_width`` (m)."""
    closed_span = info.gripper_span - 2 * (info.gripper_open[0] - info.gripper_closed[0])
    return (cup_width - closed_span) / (info.gripper_span - closed_span)


TASK = TaskEntry(
    name="place_empty_cup",
    scene=PlaceEmptyCup,
    robot="robot_a",
    step_limit=500,
    expert="equibim_jax.experts.place_empty_cup:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
