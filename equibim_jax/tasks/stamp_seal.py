"""``stamp_seal``: pick a seal up by its handle and put it down on a mat (robot A).

Scene
-----
* **Seal**: a free body made of two boxes: a base (5 x 5 x 2.4 cm, 40 g, the stamping
  face underneath) and a handle on top of it (2.4 x 2.4 x 5 cm, 20 g) that the gripper
  squeezes. Both are their own mirror images about the body's x-z plane. The base uses
  :func:`robots.object_collision` (table, pads, palms, mat); the handle collides with the
  pads and palms only (``contype 0``, ``conaffinity PAD | PALM``): it never reaches the
  table or the mat, and dropping those pairs keeps the contact count down.
* **Mat**: a 7 x 7 x 0.6 cm plate on two slide joints (x, y) at table height, like
  ``place_empty_cup``'s coaster: its position is in ``qpos`` (randomised by ``init``,
  mirrored by ``mirror_state``), joint ``frictionloss`` stands in for table friction,
  and it collides with objects only (``contype 0, conaffinity OBJECT``).

Initial state (mirror symmetric for ``side="both"``)
----------------------------------------------------
``s = +1`` (left, y > 0) or ``-1``. Seal and mat on the same side, each at
``x ~ U(x_range)``, ``y = s U(y_range)`` (|y| in [0.05, 0.25], docs/tasks.md), with
their centres at least ``min_dist`` apart in x-y: ``n_candidates`` pairs are drawn at once
and the first pair that is far enough apart is kept (the farthest pair if none is, which
the default ranges make vanishingly rare). The rule depends on distances only, so it
commutes with the mirror. Arms at home.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
All of: seal centre within ``success_xy`` (2 cm; the original benchmark uses 1 cm) of the
mat centre in x-y; the seal's bottom face within ``success_z`` (1 cm) of the mat's top
face; the seal upright (its z axis within ``max_tilt_deg`` = 15 deg of vertical), so that
it rests on its stamping face; both grippers open (normalised opening >
``open_threshold`` = 0.5; a gripper squeezing the 2.4 cm handle reads about 0.22).
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

__all__ = ["StampSeal", "TASK"]

_BOX = mujoco.mjtGeom.mjGEOM_BOX


@dataclasses.dataclass(frozen=True)
class StampSeal(Scene):
    """The ``stamp_seal`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      side: ``"left"``, ``"right"`` or ``"both"`` (random side, mirror-symmetric).
      seal_x_range, seal_y_range: seal centre x and |y| ranges (m).
      mat_x_range, mat_y_range: mat centre x and |y| ranges (m).
      min_dist: smallest x-y distance between the seal and mat centres (m); must exceed
        the two footprints' half diagonals together so they never overlap.
      n_candidates: (seal, mat) pairs drawn per reset to find one ``min_dist`` apart.
      base_half, handle_half: half sizes of the seal's base and handle boxes (m).
      base_mass, handle_mass: their masses (kg).
      mat_half: mat half sizes (m).
      success_xy, success_z: placement tolerances (m).
      max_tilt_deg: largest seal tilt that counts as resting on its face.
      open_threshold: a gripper counts as open above this normalised opening.
    """

    side: str = "both"
    seal_x_range: tuple[float, float] = (0.22, 0.34)
    seal_y_range: tuple[float, float] = (0.05, 0.25)
    mat_x_range: tuple[float, float] = (0.22, 0.34)
    mat_y_range: tuple[float, float] = (0.05, 0.25)
    min_dist: float = 0.10
    n_candidates: int = 16
    base_half: tuple[float, float, float] = (0.025, 0.025, 0.012)
    handle_half: tuple[float, float, float] = (0.012, 0.012, 0.025)
    base_mass: float = 0.04
    handle_mass: float = 0.02
    mat_half: tuple[float, float, float] = (0.035, 0.035, 0.003)
    success_xy: float = 0.02
    success_z: float = 0.01
    max_tilt_deg: float = 15.0
    open_threshold: float = 0.5
    name = "stamp_seal"
    # The table in front of the arms' bases (see place_empty_cup); mirror-symmetric.
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.2))

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")
        for f in ("seal_x_range", "seal_y_range", "mat_x_range", "mat_y_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {r}")
        for f in ("base_half", "handle_half", "mat_half"):
            h = getattr(self, f)
            if len(h) != 3 or min(h) <= 0:
                raise ValueError(f"{f} must be three positive half sizes, got {h}")
        if self.seal_y_range[0] <= self.base_half[1] or self.mat_y_range[0] <= self.mat_half[1]:
            raise ValueError(
                "seal_y_range[0] must exceed base_half[1] and mat_y_range[0] must exceed "
                "mat_half[1]: each object must lie wholly on its side of the mirror plane"
            )
        if self.handle_half[0] > self.base_half[0] or self.handle_half[1] > self.base_half[1]:
            raise ValueError("the handle must not overhang the base (handle_half <= base_half in x, y)")
        reach = math.hypot(*self.base_half[:2]) + math.hypot(*self.mat_half[:2])
        if self.min_dist <= reach:
            raise ValueError(f"min_dist must exceed the half diagonals of the seal base and the "
                             f"mat together ({reach:.4f} m) so they never overlap; got {self.min_dist}")
        dx = max(abs(self.seal_x_range[1] - self.mat_x_range[0]), abs(self.mat_x_range[1] - self.seal_x_range[0]))
        dy = max(abs(self.seal_y_range[1] - self.mat_y_range[0]), abs(self.mat_y_range[1] - self.seal_y_range[0]))
        if math.hypot(dx, dy) < self.min_dist:
            raise ValueError(f"the ranges never put the seal and the mat min_dist = {self.min_dist} apart")
        if not isinstance(self.n_candidates, int) or self.n_candidates < 1:
            raise ValueError(f"n_candidates must be a positive int, got {self.n_candidates!r}")
        if self.base_mass <= 0 or self.handle_mass <= 0:
            raise ValueError("base_mass and handle_mass must be positive")
        if not 0.0 < self.open_threshold < 1.0:
            raise ValueError(f"open_threshold must be in (0, 1), got {self.open_threshold}")

    @property
    def seal_height(self) -> float:
        """Height of the whole seal, base plus handle (m)."""
        return 2 * (self.base_half[2] + self.handle_half[2])

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free seal (base + handle) and the slide-jointed mat to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"stamp_seal is built for robot_a, got {info.name!r}")
        z0 = info.table_height
        bx, by, bz = self.base_half
        hx, hy, hz = self.handle_half
        # The body frame is the base's centre; the handle stands on the base's top face.
        seal = spec.worldbody.add_body(name="seal", pos=[0.3, 0.0, z0 + bz])
        seal.add_freejoint(name="seal")
        seal.add_geom(
            name="seal_base", type=_BOX, size=[bx, by, bz], mass=self.base_mass,
            rgba=[0.7, 0.12, 0.1, 1.0], condim=4, friction=[1.0, 0.005, 0.0001],
            **robots.object_collision(),
        )
        seal.add_geom(
            name="seal_handle", type=_BOX, size=[hx, hy, hz], pos=[0.0, 0.0, bz + hz],
            mass=self.handle_mass, rgba=[0.45, 0.3, 0.18, 1.0], condim=4,
            friction=[1.0, 0.005, 0.0001], contype=0,
            conaffinity=robots.PAD_BIT | robots.PALM_BIT,
        )
        mx, my, mz = self.mat_half
        mat = spec.worldbody.add_body(name="mat", pos=[0.0, 0.0, z0 + mz])
        for axis, jname in (([1.0, 0.0, 0.0], "mat_x"), ([0.0, 1.0, 0.0], "mat_y")):
            mat.add_joint(
                name=jname, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis, damping=2.0,
                frictionloss=0.3, armature=0.01,
            )
        mat.add_geom(
            name="mat", type=_BOX, size=[mx, my, mz], mass=0.05, rgba=[0.2, 0.35, 0.6, 1.0],
            condim=3, friction=[1.0, 0.005, 0.0001], contype=0, conaffinity=robots.OBJECT_BIT,
        )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, int]:
        m = env.mj_model
        return {
            "seal_body": m.body("seal").id,
            "mat_body": m.body("mat").id,
            "seal_qadr": int(m.jnt_qposadr[m.joint("seal").id]),
            "mat_x_qadr": int(m.jnt_qposadr[m.joint("mat_x").id]),
            "mat_y_qadr": int(m.jnt_qposadr[m.joint("mat_y").id]),
        }

    def seal_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """Seal base centre [3] and rotation matrix [3, 3] (world frame)."""
        b = self._ids(env)["seal_body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def mat_position(self, data: mjx.Data, env: Env) -> jax.Array:
        """Mat centre [3] (world frame)."""
        return data.xpos[self._ids(env)["mat_body"]]

    def positions_from_qpos(self, qpos: jax.Array, env: Env) -> tuple[jax.Array, jax.Array]:
        """(seal base centre [3], mat centre [3]) read directly from ``qpos`` [nq]."""
        ids = self._ids(env)
        a = ids["seal_qadr"]
        mat = jnp.stack([
            qpos[ids["mat_x_qadr"]], qpos[ids["mat_y_qadr"]],
            jnp.asarray(env.info.table_height + self.mat_half[2], qpos.dtype),
        ])
        return qpos[a : a + 3], mat

    def placed_qpos(self, qpos: jax.Array, env: Env, seal_xyz, seal_quat=(1.0, 0.0, 0.0, 0.0),
                    mat_xy=None) -> jax.Array:
        """``qpos`` [nq] with the seal's free joint at ``seal_xyz`` [3], ``seal_quat`` [4], and
        the mat at ``mat_xy`` [2] if given (for building states by hand)."""
        ids = self._ids(env)
        a = ids["seal_qadr"]
        pose = jnp.concatenate([jnp.asarray(seal_xyz, qpos.dtype), jnp.asarray(seal_quat, qpos.dtype)])
        qpos = qpos.at[a : a + 7].set(pose)
        if mat_xy is not None:
            qpos = qpos.at[ids["mat_x_qadr"]].set(mat_xy[0]).at[ids["mat_y_qadr"]].set(mat_xy[1])
        return qpos

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, seal and mat sampled on one side. Returns qpos [nq], ``{"side": []}``."""
        k_side, k_sx, k_sy, k_mx, k_my = jax.random.split(key, 5)
        s = side_sign(k_side, self.side)
        n = self.n_candidates
        u = lambda k, r: jax.random.uniform(k, (n,), minval=r[0], maxval=r[1])
        sx, sy = u(k_sx, self.seal_x_range), u(k_sy, self.seal_y_range)  # [n] each
        mx, my = u(k_mx, self.mat_x_range), u(k_my, self.mat_y_range)
        dist = jnp.hypot(sx - mx, sy - my)
        ok = dist >= self.min_dist
        i = jnp.where(jnp.any(ok), jnp.argmax(ok), jnp.argmax(dist))
        z = jnp.asarray(env.info.table_height + self.base_half[2])
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, jnp.stack([sx[i], s * sy[i], z]),
                                mat_xy=(mx[i], s * my[i]))
        return qpos, {"side": s}

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: distances (m), tilt (deg) and [] bool checks."""
        seal, rot = self.seal_pose(data, env)
        mat = self.mat_position(data, env)
        xy = jnp.linalg.norm(seal[:2] - mat[:2])
        # z of the centre of the base's bottom face
        bottom = seal[2] - self.base_half[2] * rot[2, 2]
        dz = bottom - (mat[2] + self.mat_half[2])
        tilt = jnp.degrees(jnp.arccos(jnp.clip(rot[2, 2], -1.0, 1.0)))
        opening = env.gripper_opening(data.qpos)
        return {
            "seal_mat_xy": xy,
            "seal_mat_dz": dz,
            "seal_tilt_deg": tilt,
            "seal_height": bottom - env.info.table_height,
            "min_gripper_opening": jnp.min(opening),
            "on_mat": (xy < self.success_xy) & (jnp.abs(dz) < self.success_z),
            "upright": tilt < self.max_tilt_deg,
            "released": jnp.all(opening > self.open_threshold),
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["on_mat"] & t["upright"] & t["released"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirrored episode has its objects on the other side."""
        return {**info, "side": -info["side"]} if "side" in info else info


TASK = TaskEntry(
    name="stamp_seal",
    scene=StampSeal,
    robot="robot_a",
    step_limit=400,
    expert="equibim_jax.experts.stamp_seal:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
