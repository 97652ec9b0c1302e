"""Scripted expert for ``handover_block``: a two-arm, pure-JAX, vmappable waypoint script.

The *giver* is the arm on the block's side (the left arm when the block's y > 0), the
*receiver* the other one. Both arms move on one shared segment timing, one phase per
segment:

    0  approach     giver: home -> ``pregrasp_height`` above the grasp point, opening and
                    turning to point down; receiver: home -> its standby pose beside the
                    handover point, opening, turning to its side grasp
    1  descend      giver -> grasp point (pads on the block's upper part)
    2  close        giver closes (friction grasp)
    3  settle       hold while the grip force builds
    4  lift         giver lifts the block straight up to handover height
    5  transfer     giver carries it over the handover point (on the mirror plane)
    6  insert       receiver moves in along its approach; its open pads straddle the
                    block's lower part
    7  close2       receiver closes (both arms now hold the block)
    8  settle2      hold
    9  give         giver opens
    10 withdraw     giver rises straight up, clear of the block
    11 carry        receiver carries the block above the target pad
    12 lower        -> the block's bottom ``place_clearance`` above the pad
    13 release      receiver opens
    14 retreat      receiver backs out along its approach and up
    15 hold         (to the end of the episode)

Grasps
------
The giver grips from above with ``R_DOWN_6D`` (approach -z, closing along y): its pads
squeeze the block's +-y faces with the ee (pad centre) ``grasp_below_top`` below the
block's top, so the 5 cm pads cover about its top 5 cm. The receiver grips with a
horizontal approach pointing from its own side towards the mirror plane, ``(0, s, 0)``
with ``s`` the block's side sign, closing along x
(ee y = ``(s, 0, 0)``, ee z = -z): its pads squeeze the block's +-x faces at
``receiver_grip_height`` above the block's bottom, well below the giver's pads. Both
rotations are mirror-covariant: ``R_DOWN`` is its own mirror image and the receiver's
maps to the other side's under ``R -> M R L``. The handover point is on the mirror plane
(y = 0) at x = ``handover_x``, with the block's bottom at ``handover_bottom``.

The plan reads only the block's and the pad's initial positions (reflected by the mirror)
and the sign of the block's y, so, with the mirror-equivariant machinery of
:mod:`equibim_jax.experts._waypoints`, the expert is mirror-equivariant: from
``env.mirror_state(s0)`` it issues ``env.action_symmetry`` of its actions from ``s0``. It
is open loop after ``init``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from equibim_jax.experts._waypoints import (
    check_expert_config, R_DOWN_6D, Expert, make_bimanual_waypoint_expert,
)
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.handover_block import HandoverBlock

__all__ = ["HandoverExpertConfig", "PHASES", "make_expert"]

PHASES = ("approach", "descend", "close", "settle", "lift", "transfer", "insert", "close2",
          "settle2", "give", "withdraw", "carry", "lower", "release", "retreat", "hold")


@dataclasses.dataclass(frozen=True)
class HandoverExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of each phase but the final hold (see :data:`PHASES`).
      grasp_below_top: giver ee (pad centre) depth below the block's top face (m).
      pregrasp_height: giver ee height above its grasp point for the approach (m).
      handover_x: x of the handover point (its y is 0) (m).
      handover_bottom: height of the block's bottom above the table at the handover (m).
      receiver_grip_height: receiver ee (pad centre) height above the block's bottom (m).
      standoff: receiver's distance back along its approach before it moves in (m).
      withdraw_height: how far the giver rises after letting go (m).
      carry_lift: height of the block's bottom above its release height while carried
        over the pad (m).
      place_clearance: gap under the block at release (m).
      retreat_back, retreat_up: the receiver's retreat along -approach and up (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (45, 20, 15, 8, 25, 45, 25, 15, 8, 12, 15, 50, 20, 12, 15)
    grasp_below_top: float = 0.022
    pregrasp_height: float = 0.08
    handover_x: float = 0.30
    handover_bottom: float = 0.10
    receiver_grip_height: float = 0.035
    standoff: float = 0.10
    withdraw_height: float = 0.08
    carry_lift: float = 0.04
    place_clearance: float = 0.003
    retreat_back: float = 0.08
    retreat_up: float = 0.03
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES,
                            positive=("pregrasp_height", "handover_bottom", "receiver_grip_height",
                                      "standoff", "withdraw_height", "carry_lift", "retreat_back"),
                            nonnegative=("place_clearance", "retreat_up"))

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))

    @property
    def release_end(self) -> int:
        """Step at which the receiver's release segment ends (its gripper is open)."""
        return int(sum(self.durations[: PHASES.index("release") + 1]))


def make_expert(env: Env, config: HandoverExpertConfig = HandoverExpertConfig()) -> Expert:
    """The scripted expert of ``handover_block`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`HandoverBlock` scene and ``action="joint"``.
      config: :class:`HandoverExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert`: ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [14])``, pure and vmappable.

    Raises:
      ValueError: not a ``HandoverBlock`` scene, or grasp heights that would put the two
        grippers' pads on the same part of the block or outside it.
    """
    scene = env.scene
    if not isinstance(scene, HandoverBlock):
        raise ValueError(f"the handover_block expert needs a HandoverBlock scene, got "
                         f"{type(scene).__name__}")
    height = 2 * scene.block_half[2]
    # finger pad half sizes: along the approach (ee x) and across it (ee z)
    pad_half_len, _, pad_half_w = (float(v) for v in env.mj_model.geom(env.info.gripper_pads[0][0]).size)
    if not 0.0 < config.grasp_below_top < height:
        raise ValueError(f"grasp_below_top must lie within the block's height (0, {height}), "
                         f"got {config.grasp_below_top}")
    if not pad_half_w < config.receiver_grip_height < height:
        raise ValueError(f"receiver_grip_height must put the receiver's pads on the block "
                         f"({pad_half_w}, {height}), got {config.receiver_grip_height}")
    gap = (height - config.grasp_below_top - pad_half_len) - (config.receiver_grip_height + pad_half_w)
    if gap < 0.01:
        raise ValueError(
            f"the giver's pads (from {config.grasp_below_top + pad_half_len:.3f} m below the top) "
            f"and the receiver's (up to {config.receiver_grip_height + pad_half_w:.3f} m above the "
            f"bottom) must leave at least 1 cm of the block's {height} m between them; got "
            f"{gap:.4f} m (lower receiver_grip_height or grasp_below_top, or use a taller block)")
    bz = scene.block_half[2]
    pad_top_above_centre = scene.pad_half[2]
    r_down = jnp.asarray(R_DOWN_6D)
    c = config

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [15, 2, 10] (row 0 of axis 1 the left arm) and active [2] (both)."""
        qpos = state.data.qpos
        block, pad = scene.positions_from_qpos(qpos, env)
        s = jnp.where(block[1] > 0.0, 1.0, -1.0).astype(block.dtype)  # the giver's side
        z0 = block[2] - bz  # block bottom on the table
        one = jnp.ones((), block.dtype)
        zero = jnp.zeros((), block.dtype)
        p = lambda x, y, z: jnp.stack([x * one, y * one, z * one])

        # ---- giver: R_DOWN, pads on the block's top part
        g_grasp_z = z0 + 2 * bz - c.grasp_below_top
        g_hand_z = c.handover_bottom + 2 * bz - c.grasp_below_top
        g_pos = jnp.stack([
            p(block[0], block[1], g_grasp_z + c.pregrasp_height),   # 0 approach
            p(block[0], block[1], g_grasp_z),                       # 1 descend
            p(block[0], block[1], g_grasp_z),                       # 2 close
            p(block[0], block[1], g_grasp_z),                       # 3 settle
            p(block[0], block[1], g_hand_z),                        # 4 lift
            p(c.handover_x, zero, g_hand_z),                        # 5 transfer
            p(c.handover_x, zero, g_hand_z),                        # 6 insert
            p(c.handover_x, zero, g_hand_z),                        # 7 close2
            p(c.handover_x, zero, g_hand_z),                        # 8 settle2
            p(c.handover_x, zero, g_hand_z),                        # 9 give
            p(c.handover_x, zero, g_hand_z + c.withdraw_height),    # 10 withdraw
        ])
        g_pos = jnp.concatenate([g_pos, jnp.tile(g_pos[-1:], (4, 1))])  # 11-14 hold
        g_open = jnp.asarray([1, 1, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1], block.dtype)
        g_rot = jnp.tile(r_down.astype(block.dtype), (15, 1))

        # ---- receiver: horizontal approach (0, s, 0), closing along x, on the lower part
        app = p(zero, s, zero)
        r_hand = p(c.handover_x, zero, c.handover_bottom + c.receiver_grip_height)
        r_stand = r_hand - c.standoff * app
        place_z = pad[2] + pad_top_above_centre + c.place_clearance + c.receiver_grip_height
        r_place = p(pad[0], pad[1], place_z)
        r_above = r_place + p(zero, zero, c.carry_lift)
        r_back = r_place - c.retreat_back * app + p(zero, zero, c.retreat_up)
        r_pos = jnp.stack([
            r_stand, r_stand, r_stand, r_stand, r_stand, r_stand,   # 0-5 standby
            r_hand, r_hand, r_hand, r_hand, r_hand,                 # 6 insert, 7-10 hold
            r_above, r_place, r_place, r_back,                      # 11-14
        ])
        r_open = jnp.asarray([1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 1, 1], block.dtype)
        r_rot6 = jnp.concatenate([app, p(s, zero, zero)])
        r_rot = jnp.tile(r_rot6, (15, 1))

        giver = jnp.concatenate([g_pos, g_rot, g_open[:, None]], axis=-1)  # [15, 10]
        recv = jnp.concatenate([r_pos, r_rot, r_open[:, None]], axis=-1)
        left_gives = s > 0
        wps = jnp.where(left_gives, jnp.stack([giver, recv], axis=1), jnp.stack([recv, giver], axis=1))
        return wps.astype(jnp.float32), jnp.ones((2,), bool)

    return make_bimanual_waypoint_expert(env, plan, c.durations, c.ik_iterations, PHASES)
