"""``handover_block``: one arm picks a tall block up and hands it to the other arm, which
puts it down on a target pad on its own side (robot A).

Scene
-----
* **Block**: a free box of 4 x 4 x 12 cm and 60 g (:func:`robots.object_collision`:
  table, finger pads, palms, target pad). It is tall so that two grippers hold it at once
  without their pads overlapping: the giver squeezes its upper part from above, the
  receiver its lower part from the side. It is its own mirror image about its x-z plane.
* **Target pad**: a 9 x 9 x 0.6 cm plate on two slide joints (x, y) at table height, like
  ``stamp_seal``'s mat: its position is in ``qpos`` (randomised by ``init``, mirrored by
  ``mirror_state``), joint ``frictionloss`` stands in for table friction, and it collides
  with objects only (``contype 0, conaffinity OBJECT``): the grippers pass through it.

Initial state
-------------
``s = +1`` (block on the left, y > 0) or ``-1``. Block at ``x ~ U(block_x_range)``,
``y = s U(block_y_range)`` (|y| in [0.05, 0.25]); target pad on the OTHER side at
``x ~ U(pad_x_range)``, ``y = -s U(pad_y_range)`` (|y| in [0.1, 0.25]). Block and pad
are on opposite sides of the mirror plane, so they never overlap. Arms at home.

* ``side="both"`` (default): ``s`` is +1 or -1 with probability 1/2; the law is
  mirror-symmetric (the same key gives exact mirror images for ``"left"`` and ``"right"``).
* ``robotwin_faithful=True``: the original benchmark's distribution, block always on the
  left and pad always on the right. This variant is asymmetric on purpose. With it,
  ``side`` may be ``"left"`` or ``"both"`` (both are resolved to ``"left"`` when the scene is
  built, so ``scene.side`` and the recorded options say what is drawn); ``"right"`` is a
  ValueError.

Success (from the simulated state, every control step, latched by the env)
-------------------------------------------------------------------------
All of: the block's centre within ``success_xy`` (3 cm) of the target pad's centre in
x-y; the block's lowest point within ``success_z`` (1 cm) of the pad's top face; the
receiving gripper open (normalised opening > ``open_threshold`` = 0.6; a gripper squeezing
the 4 cm block reads about 0.40). The receiving gripper is the arm on the pad's side (the
right arm when the pad's y < 0), read from the pad's position in the state.
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

__all__ = ["HandoverBlock", "TASK"]

_BOX = mujoco.mjtGeom.mjGEOM_BOX


@dataclasses.dataclass(frozen=True)
class HandoverBlock(Scene):
    """The ``handover_block`` task as an env :class:`~equibim_jax.sim.env.Scene` (robot A).

    Attributes:
      side: the block's side: ``"left"``, ``"right"`` or ``"both"`` (random side,
        mirror-symmetric). With ``robotwin_faithful`` it is resolved to ``"left"``.
      robotwin_faithful: draw the original benchmark's asymmetric distribution (block
        always on the left, pad on the right); ``side="right"`` is then an error.
      block_x_range, block_y_range: block centre x and |y| ranges (m).
      pad_x_range, pad_y_range: target pad centre x and |y| ranges (m).
      block_half, block_mass: block half sizes (m) and mass (kg).
      pad_half: target pad half sizes (m).
      success_xy, success_z: placement tolerances (m).
      open_threshold: the receiving gripper counts as open above this normalised opening.
    """

    side: str = "both"
    robotwin_faithful: bool = False
    block_x_range: tuple[float, float] = (0.22, 0.34)
    block_y_range: tuple[float, float] = (0.05, 0.25)
    pad_x_range: tuple[float, float] = (0.22, 0.34)
    pad_y_range: tuple[float, float] = (0.10, 0.25)
    block_half: tuple[float, float, float] = (0.02, 0.02, 0.06)
    block_mass: float = 0.06
    pad_half: tuple[float, float, float] = (0.045, 0.045, 0.003)
    success_xy: float = 0.03
    success_z: float = 0.01
    open_threshold: float = 0.6
    name = "handover_block"
    # The table in front of the arms' bases, tall enough for the block held at the
    # handover (its top reaches about 0.23 m); mirror-symmetric.
    point_cloud_crop = ((0.12, -0.4, 0.002), (0.55, 0.4, 0.3))

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")
        if not isinstance(self.robotwin_faithful, bool):
            raise ValueError(f"robotwin_faithful must be a bool, got {self.robotwin_faithful!r}")
        if self.robotwin_faithful:
            if self.side == "right":
                raise ValueError(
                    "robotwin_faithful=True always starts the block on the left (the original "
                    "benchmark's asymmetric distribution); side='right' contradicts it (use "
                    "side='left' or 'both', or robotwin_faithful=False)")
            object.__setattr__(self, "side", "left")
        for f in ("block_x_range", "block_y_range", "pad_x_range", "pad_y_range"):
            r = getattr(self, f)
            if len(r) != 2 or not r[0] <= r[1]:
                raise ValueError(f"{f} must be (low, high) with low <= high, got {r}")
        for f in ("block_half", "pad_half"):
            h = getattr(self, f)
            if len(h) != 3 or min(h) <= 0:
                raise ValueError(f"{f} must be three positive half sizes, got {h}")
        if self.block_y_range[0] <= self.block_half[1] or self.pad_y_range[0] <= self.pad_half[1]:
            raise ValueError(
                "block_y_range[0] must exceed block_half[1] and pad_y_range[0] must exceed "
                "pad_half[1]: each object must lie wholly on its side of the mirror plane")
        for f in ("block_mass", "success_xy", "success_z"):
            if not getattr(self, f) > 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        if not 0.0 < self.open_threshold < 1.0:
            raise ValueError(f"open_threshold must be in (0, 1), got {self.open_threshold}")

    # ------------------------------------------------------------------ model
    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add the free block and the slide-jointed target pad to robot A's spec."""
        if info.name != "robot_a":
            raise ValueError(f"handover_block is built for robot_a, got {info.name!r}")
        z0 = info.table_height
        bx, by, bz = self.block_half
        block = spec.worldbody.add_body(name="block", pos=[0.3, 0.0, z0 + bz])
        block.add_freejoint(name="block")
        block.add_geom(
            name="block", type=_BOX, size=[bx, by, bz], mass=self.block_mass,
            rgba=[0.85, 0.55, 0.1, 1.0], condim=4, friction=[1.0, 0.005, 0.0001],
            **robots.object_collision(),
        )
        px, py, pz = self.pad_half
        pad = spec.worldbody.add_body(name="target", pos=[0.0, 0.0, z0 + pz])
        for axis, jname in (([1.0, 0.0, 0.0], "target_x"), ([0.0, 1.0, 0.0], "target_y")):
            pad.add_joint(
                name=jname, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis, damping=2.0,
                frictionloss=0.3, armature=0.01,
            )
        pad.add_geom(
            name="target", type=_BOX, size=[px, py, pz], mass=0.05, rgba=[0.15, 0.55, 0.3, 1.0],
            condim=3, friction=[1.0, 0.005, 0.0001], contype=0, conaffinity=robots.OBJECT_BIT,
        )

    # ------------------------------------------------------------------ ids
    @staticmethod
    def _ids(env: Env) -> dict[str, int]:
        m = env.mj_model
        return {
            "block_body": m.body("block").id,
            "pad_body": m.body("target").id,
            "block_qadr": int(m.jnt_qposadr[m.joint("block").id]),
            "pad_x_qadr": int(m.jnt_qposadr[m.joint("target_x").id]),
            "pad_y_qadr": int(m.jnt_qposadr[m.joint("target_y").id]),
        }

    def block_pose(self, data: mjx.Data, env: Env) -> tuple[jax.Array, jax.Array]:
        """Block centre [3] and rotation matrix [3, 3] (world frame)."""
        b = self._ids(env)["block_body"]
        return data.xpos[b], data.xmat[b].reshape(3, 3)

    def pad_position(self, data: mjx.Data, env: Env) -> jax.Array:
        """Target pad centre [3] (world frame)."""
        return data.xpos[self._ids(env)["pad_body"]]

    def positions_from_qpos(self, qpos: jax.Array, env: Env) -> tuple[jax.Array, jax.Array]:
        """(block centre [3], target pad centre [3]) read directly from ``qpos`` [nq]."""
        ids = self._ids(env)
        a = ids["block_qadr"]
        pad = jnp.stack([
            qpos[ids["pad_x_qadr"]], qpos[ids["pad_y_qadr"]],
            jnp.asarray(env.info.table_height + self.pad_half[2], qpos.dtype),
        ])
        return qpos[a : a + 3], pad

    def placed_qpos(self, qpos: jax.Array, env: Env, block_xyz, block_quat=(1.0, 0.0, 0.0, 0.0),
                    pad_xy=None) -> jax.Array:
        """``qpos`` [nq] with the block's free joint at ``block_xyz`` [3], ``block_quat`` [4],
        and the target pad at ``pad_xy`` [2] if given (for building states by hand)."""
        ids = self._ids(env)
        a = ids["block_qadr"]
        pose = jnp.concatenate([jnp.asarray(block_xyz, qpos.dtype), jnp.asarray(block_quat, qpos.dtype)])
        qpos = qpos.at[a : a + 7].set(pose)
        if pad_xy is not None:
            qpos = qpos.at[ids["pad_x_qadr"]].set(pad_xy[0]).at[ids["pad_y_qadr"]].set(pad_xy[1])
        return qpos

    # ------------------------------------------------------------------ episode
    def init(self, key: jax.Array, env: Env) -> tuple[jax.Array, dict]:
        """Home arms, block on side ``s``, target pad on side ``-s``.

        Returns qpos [nq] and ``{"side": []}`` (``s``, the block's side: +1 left, -1 right).
        """
        k_side, k_bx, k_by, k_px, k_py = jax.random.split(key, 5)
        # a strongly typed float32 sign for every ``side`` (side_sign gives a weakly typed one
        # for "both"), so that starts of all variants share one pytree type under jit
        s = side_sign(k_side, self.side).astype(jnp.float32)
        u = lambda k, r: jax.random.uniform(k, (), minval=r[0], maxval=r[1])
        bx, by = u(k_bx, self.block_x_range), u(k_by, self.block_y_range)
        px, py = u(k_px, self.pad_x_range), u(k_py, self.pad_y_range)
        z = jnp.asarray(env.info.table_height + self.block_half[2])
        qpos = self.placed_qpos(jnp.asarray(env.home_qpos), env, jnp.stack([bx, s * by, z]),
                                pad_xy=(px, -s * py))
        return qpos, {"side": s}

    def terms(self, data: mjx.Data, env: Env) -> dict[str, jax.Array]:
        """Named success terms of one state: distances (m), tilt (deg), openings and [] bool
        checks."""
        block, rot = self.block_pose(data, env)
        pad = self.pad_position(data, env)
        xy = jnp.linalg.norm(block[:2] - pad[:2])
        # the block's lowest point: its centre minus the half sizes projected on world z
        bottom = block[2] - jnp.sum(jnp.abs(rot[2, :]) * jnp.asarray(self.block_half, rot.dtype))
        dz = bottom - (pad[2] + self.pad_half[2])
        tilt = jnp.degrees(jnp.arccos(jnp.clip(rot[2, 2], -1.0, 1.0)))
        opening = env.gripper_opening(data.qpos)  # [2] (left, right)
        receiver_open = jnp.where(pad[1] > 0.0, opening[0], opening[1])  # the pad's side
        return {
            "block_pad_xy": xy,
            "block_pad_dz": dz,
            "block_height": bottom - env.info.table_height,
            "block_tilt_deg": tilt,
            "receiver_opening": receiver_open,
            "on_pad": (xy < self.success_xy) & (jnp.abs(dz) < self.success_z),
            "released": receiver_open > self.open_threshold,
        }

    def evaluate(self, data: mjx.Data, info: dict, env: Env) -> tuple[jax.Array, jax.Array, dict]:
        """Sparse reward (1 on success), success [] bool, and the named terms as metrics."""
        t = self.terms(data, env)
        success = t["on_pad"] & t["released"]
        metrics = {k: v.astype(jnp.float32) for k, v in t.items()}
        return success.astype(jnp.float32), success, metrics

    def mirror_info(self, info: dict, env: Env) -> dict:
        """The mirrored episode has its block (and pad) on the other side."""
        return {**info, "side": -info["side"]} if "side" in info else info


TASK = TaskEntry(
    name="handover_block",
    scene=HandoverBlock,
    robot="robot_a",
    step_limit=800,
    expert="equibim_jax.experts.handover_block:make_expert",
    env_defaults={"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64},
)
