"""``pick_dual_bottles``: both arms at once each pick up the bottle on their side and lift
it to a lift target (robot A).

Scene
-----
* **Two bottles**, free bodies ``bottle_a`` and ``bottle_b``. Each is a body box (5 x 5 x
  10 cm, 80 g by default) with a narrower neck standing on its top face: a vertical
  capsule (radius 1.4 cm, 7 cm long, 20 g) that the gripper squeezes. Primitives only: MJX
  has no box-cylinder collision (the pads are boxes), and a capsule-box pair makes 2
  contact points where a box-box pair makes 4. Every geom is its own mirror image about
  the body's x-z plane. The body frame is the centre of the body box.
  To keep the contact count low, the body collides with the table, pads and palms but not
  with the other bottle (``contype OBJECT``, ``conaffinity TABLE | PAD | PALM``; the
  bottles stand on opposite sides of the mirror plane and are lifted to targets 0.3 m
  apart), and the neck collides with the pads and palms only (``contype 0``,
  ``conaffinity PAD | PALM``): it never reaches the table.
* With ``robotwin_faithful=True`` the right bottle (``bottle_b``) is a different bottle
  (the ``right_*`` options: a 6 x 6 x 8 cm, 120 g body with an 8 cm long, 1.2 cm radius,
  30 g neck by default), as in the original benchmark, which uses two different bottles.
  That variant is **not** mirror-symmetric, on purpose: the mirror image of a start puts
  the left bottle on the right, where this variant never places it.

Initial state (mirror symmetric by default)
-------------------------------------------
One bottle on each side: the left one (y > 0) at ``x ~ U(x_range)``, ``y ~ U(y_range)``,
the right one at an independent ``x ~ U(x_range)``, ``y ~ -U(y_range)``, both upright on
the table. By default the two bottles are identical and a fair coin ``a_side``
(``info["a_side"]``, +1 or -1) says which side ``bottle_a`` stands on, so the mirror image
of a start (``env.mirror_state``, which reflects each free bottle in place) is a start
with the same density. With ``robotwin_faithful=True``, ``bottle_a`` is always on the left
(``a_side = +1``). Arms at home.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
The lift targets are the fixed points ``(x_t, +y_t, z_t)`` (left) and
``(x_t, -y_t, z_t)`` (right), ``lift_target = (x_t, y_t, z_t)``, for a bottle's body
centre. The left bottle is the one with the larger y now. Success: each bottle's body
centre is at least ``min_lift`` (10 cm) above its height resting on the table and within
``success_dist`` (0.1 m) of the lift target on its side. The predicate reads bottle
positions only, and ``y_t > success_dist`` makes it a function of the set of the two
bottle positions (a bottle on the wrong side is far from the other target).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from equibim_jax.sim import robots
from equibim_jax.sim.env import Env, Scene
from equibim_jax.tasks import TaskEntry

__all__ = ["Bottle", "PickDualBottles", "TASK"]

_BOX = mujoco.mjtGeom.mjGEOM_BOX
_CAPSULE = mujoco.mjtGeom.mjGEOM_CAPSULE
_NAMES = ("bottle_a", "bottle_b")


class Bottle(NamedTuple):
    """One bottle's shape and masses (static).

    Attributes:
      body_half: half sizes of the body box (m).
      neck_radius, neck_length: radius and full length (caps included) of the vertical
        capsule neck standing on the body's top face (m).
      body_mass, neck_mass: masses (kg).
    """

    body_half: tuple[float, float, float]
    neck_radius: float
    neck_length: float
    body_mass: float
    neck_mass: float

    @property
    def top_above_centre(self) -> float:
        """Height of the neck's top above the body centre (m)."""
        return self.body_half[2] + self.neck_length


@dataclasses.dataclass(frozen=True)
class PickDualBottles(Scene):
    """The ``pick_dual_bottles`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      x_range: bottle body-centre x range (m), both sides.
      y_range: bottle body-centre |y| range (m), both sides.
      body_half: half sizes of a bottle's body box (m).
      neck_radius, neck_length: its capsule neck's radius and full length (m).
      body_mass, neck_mass: their masses (kg).
      lift_target: ``(x_t, y_t, z_t)``: the left bottle's target is ``(x_t, y_t, z_t)``, the
        right one's ``(x_t, -y_t, z_t)`` (body centre, world frame, m).
      min_lift: smallest rise of each body centre above its resting height (m).
      success_dist: largest distance of each body centre from its lift target (m).
      robotwin_faithful: the right bottle is a different bottle (the ``right_*`` fields)
        and always the right one, as in the original benchmark; the task is then not
        mirror-symmetric, on purpose.
      right_body_half, right_neck_radius, right_neck_length, right_body_mass,
        right_neck_mass: the right bottle with ``robotwin_faithful=True`` (ignored
        otherwise).
    """

    x_range: tuple[float, float] = (0.22, 0.34)
    y_range: tuple[float, float] = (0.10, 0.25)
    body_half: tuple[float, float, float] = (0.025, 0.025, 0.05)
    neck_radius: float = 0.014
    neck_length: float = 0.07
    body_mass: float = 0.08
    neck_mass: float = 0.02
    lift_target: tuple[float, float, float] = (0.30, 0.15, 0.20)
    min_lift: float = 0.10
    success_dist: float = 0.10
    robotwin_faithful: bool = False
    right_body_half: tuple[float, float, float] = (0.03, 0.03, 0.04)
    right_neck_radius: float = 0.012
    right_neck_length: float = 0.08
    right_body_mass: float = 0.12
    right_neck_mass: float = 0.03
    name = "pick_dual_bottles"
    # The table in front of the arms' bases (see place_empty_cup), mirror-symmetric, and
    # tall enough to hold the bottles at their lift targets.
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.35))

    def __post_init__(self):
        if not isinstance(self.robotwin_faithful, bool):
            raise ValueError(f"robotwin_faithful must be a bool, got {self.robotwin_faithful!r}")
        for f in ("x_range", "y_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {r}")
        for f in ("body_half", "right_body_half"):
            h = getattr(self, f)
            if len(h) != 3 or min(h) <= 0:
                raise ValueError(f"{f} must be three positive half sizes, got {h}")
        for f in ("neck_radius", "neck_length", "body_mass", "neck_mass", "right_neck_radius",
                  "right_neck_length", "right_body_mass", "right_neck_mass", "min_lift",
                  "success_dist"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        for b in self.bottles():
            if b.neck_radius > min(b.body_half[:2]):
                raise ValueError(f"a bottle's neck must not overhang its body: neck radius "
                                 f"{b.neck_radius} > body half width {min(b.body_half[:2])}")
            if b.neck_length < 2 * b.neck_radius:
                raise ValueError(f"a neck's length ({b.neck_length}) must be at least its "
                                 f"diameter ({2 * b.neck_radius}): it is a capsule")
            reach = math.hypot(b.body_half[0], b.body_half[1])
            if self.y_range[0] <= reach:
                raise ValueError(
                    f"y_range[0] = {self.y_range[0]} must exceed a bottle body's half diagonal "
                    f"({reach:.4f} m): each bottle must lie wholly on its side of the mirror plane")
        if len(self.lift_target) != 3:
            raise ValueError(f"lift_target must be (x_t, y_t, z_t), got {self.lift_target}")
        if not self.lift_target[1] > self.success_dist:
            raise ValueError(
                f"lift_target y_t = {self.lift_target[1]} must exceed success_dist = "
                f"{self.success_dist}: each target's tolerance ball must lie on its own side")
        for b in self.bottles():
            if self.lift_target[2] - b.body_half[2] < self.min_lift:
                raise ValueError(
                    f"lift_target z_t = {self.lift_target[2]} must be at least min_lift = "
                    f"{self.min_lift} above a resting bottle's body centre ({b.body_half[2]} m)")

    def bottles(self) -> tuple[Bottle, Bottle]:
        """(``bottle_a``, ``bottle_b``) as built: identical unless ``robotwin_faithful``."""
        a = Bottle(tuple(self.body_half), self.neck_radius, self.neck_length, self.body_mass,
                   self.neck_mass)
        if not self.robotwin_faithful:
            return (a, a)
        return (a, Bottle(tuple(self.right_body_half), self.right_neck_radius,
                          self.right_neck_length, self.right_body_mass, self.right_neck_mass))

    def rest_height(self, env: Env) -> tuple[float, float]:
        """Body-centre z of each bottle resting upright on the table (m): (a, b)."""
        return tuple(env.info.table_height + b.body_half[2] for b in self.bottles())

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the two free bottles (body box + capsule neck each) to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"pick_dual_bottles is built for robot_a, got {info.name!r}")
        z0 = info.table_height
        colors = ([0.2, 0.55, 0.3, 1.0], [0.85, 0.85, 0.8, 1.0])  # green body, white neck
        faithful_colors = ([0.7, 0.45, 0.15, 1.0], [0.3, 0.3, 0.3, 1.0])  # the other bottle
        for k, (name, b) in enumerate(zip(_NAMES, self.bottles())):
            rgba = faithful_colors if (self.robotwin_faithful and k == 1) else colors
            hz = b.body_half[2]
            # Mirror-image reference positions (qpos0), so the model's reference posture is
            # mirror-symmetric; init moves both bottles.
            body = spec.worldbody.add_body(name=name, pos=[0.3, 0.15 * (1 - 2 * k), z0 + hz])
            body.add_freejoint(name=name)
            # The body touches the table and the grippers, not the other bottle (contype
            # OBJECT, conaffinity without OBJECT); condim 3 is enough on the table (the pads
            # bring condim 4 to their own contacts).
            body.add_geom(
                name=f"{name}_body", type=_BOX, size=list(b.body_half), mass=b.body_mass,
                rgba=rgba[0], condim=3, friction=[1.0, 0.005, 0.0001], contype=robots.OBJECT_BIT,
                conaffinity=robots.TABLE_BIT | robots.PAD_BIT | robots.PALM_BIT,
            )
            # The neck: a vertical capsule (capsule-box contacts are 2 points in MJX, box-box
            # 4), touching the grippers only.
            body.add_geom(
                name=f"{name}_neck", type=_CAPSULE,
                size=[b.neck_radius, b.neck_length / 2 - b.neck_radius, 0.0],
                pos=[0.0, 0.0, hz + b.neck_length / 2], mass=b.neck_mass, rgba=rgba[1], condim=4,
                friction=[1.0, 0.005, 0.0001], contype=0,
                conaffinity=robots.PAD_BIT | robots.PALM_BIT,
            )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, tuple[int, int]]:
        m = env.mj_model
        return {
            "body": tuple(m.body(n).id for n in _NAMES),
            "qadr": tuple(int(m.jnt_qposadr[m.joint(n).id]) for n in _NAMES),
        }

    def bottle_positions(self, data: mjx.Data, env: Env) -> jax.Array:
        """Body centres [2, 3] of (``bottle_a``, ``bottle_b``) (world frame)."""
        return data.xpos[jnp.asarray(self._ids(env)["body"])]

    def bottle_up(self, data: mjx.Data, env: Env) -> jax.Array:
        """z components [2] of the bottles' own z axes (1 when upright)."""
        return data.xmat[jnp.asarray(self._ids(env)["body"])].reshape(2, 3, 3)[:, 2, 2]

    def positions_from_qpos(self, qpos: jax.Array, env: Env) -> jax.Array:
        """Body centres [2, 3] of (``bottle_a``, ``bottle_b``) read directly from ``qpos``."""
        return jnp.stack([qpos[a : a + 3] for a in self._ids(env)["qadr"]])

    def placed_qpos(self, qpos: jax.Array, env: Env, a_xyz, b_xyz, a_quat=(1.0, 0.0, 0.0, 0.0),
                    b_quat=(1.0, 0.0, 0.0, 0.0)) -> jax.Array:
        """``qpos`` [nq] with ``bottle_a`` at ``a_xyz`` [3], ``a_quat`` [4] and ``bottle_b`` at
        ``b_xyz``, ``b_quat`` (body centres; for building states by hand)."""
        for adr, xyz, quat in zip(self._ids(env)["qadr"], (a_xyz, b_xyz), (a_quat, b_quat)):
            pose = jnp.concatenate([jnp.asarray(xyz, qpos.dtype), jnp.asarray(quat, qpos.dtype)])
            qpos = qpos.at[adr : adr + 7].set(pose)
        return qpos

    def layout(self, env: Env, a_side, left_xy, right_xy) -> jax.Array:
        """Start ``qpos`` [nq]: arms at home, the left bottle's centre at ``left_xy`` [2] (y > 0),
        the right one's at ``right_xy`` [2]; ``bottle_a`` on the left iff ``a_side`` > 0.

        ``init`` draws its arguments; the mirror of ``layout(s, l, r)`` is
        ``layout(-s, M r, M l)`` (``M`` negates y)."""
        za, zb = self.rest_height(env)
        left_xy, right_xy = jnp.asarray(left_xy), jnp.asarray(right_xy)
        on_left = a_side > 0
        a_xy = jnp.where(on_left, left_xy, right_xy)
        b_xy = jnp.where(on_left, right_xy, left_xy)
        a = jnp.concatenate([a_xy, jnp.full((1,), za, a_xy.dtype)])
        b = jnp.concatenate([b_xy, jnp.full((1,), zb, b_xy.dtype)])
        return self.placed_qpos(jnp.asarray(env.home_qpos), env, a, b)

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, one bottle on each side. Returns qpos [nq], ``{"a_side": []}``."""
        k_side, k_l, k_r = jax.random.split(key, 3)
        if self.robotwin_faithful:
            a_side = jnp.ones(())
        else:
            a_side = jnp.where(jax.random.bernoulli(k_side), 1.0, -1.0)
        lo = jnp.asarray([self.x_range[0], self.y_range[0]])
        hi = jnp.asarray([self.x_range[1], self.y_range[1]])
        left = jax.random.uniform(k_l, (2,), minval=lo, maxval=hi)
        right = jax.random.uniform(k_r, (2,), minval=lo, maxval=hi) * jnp.asarray([1.0, -1.0])
        return self.layout(env, a_side, left, right), {"a_side": a_side}

    def targets(self) -> jax.Array:
        """Lift targets [2, 3]: (left, right) body-centre targets (world frame)."""
        x, y, z = self.lift_target
        return jnp.asarray([[x, y, z], [x, -y, z]], jnp.float32)

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: rises and distances (m), [] bool checks.

        ``left_*`` is the bottle with the larger y now, ``right_*`` the other one."""
        pos = self.bottle_positions(data, env)  # [2, 3]
        rest = jnp.asarray(self.rest_height(env), pos.dtype)  # [2]
        lift = pos[:, 2] - rest  # [2] per bottle a, b
        a_left = pos[0, 1] >= pos[1, 1]
        order = jnp.where(a_left, jnp.array([0, 1]), jnp.array([1, 0]))  # (left, right) bottle ids
        lift_lr = lift[order]
        dist_lr = jnp.linalg.norm(pos[order] - self.targets().astype(pos.dtype), axis=-1)
        lifted = lift_lr >= self.min_lift
        near = dist_lr < self.success_dist
        return {
            "left_lift": lift_lr[0],
            "right_lift": lift_lr[1],
            "left_target_dist": dist_lr[0],
            "right_target_dist": dist_lr[1],
            "min_upright": jnp.min(self.bottle_up(data, env)),
            "left_done": lifted[0] & near[0],
            "right_done": lifted[1] & near[1],
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["left_done"] & t["right_done"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirror reflects each bottle in place, so ``bottle_a`` changes side."""
        return {**info, "a_side": -info["a_side"]} if "a_side" in info else info


TASK = TaskEntry(
    name="pick_dual_bottles",
    scene=PickDualBottles,
    robot="robot_a",
    step_limit=400,
    expert="equibim_jax.experts.pick_dual_bottles:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
