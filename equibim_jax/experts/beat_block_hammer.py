"""Scripted expert for ``beat_block_hammer``: a pure-JAX, vmappable waypoint script.

The arm on the block's side (the left arm when the block's y > 0) does, one phase per
segment:

    0 approach  home pose -> ``pregrasp_height`` above the grasp point on the handle,
                gripper opening and turning to point down (closing along y)
    1 descend   -> the grasp point: ``grasp_from_head`` behind the head's centre along
                the handle, ``grasp_above_axis`` above the handle's axis
    2 close     opening -> 0 (the grasp holds by friction only)
    3 settle    hold still while the grip force builds
    4 lift      -> carry height: the striking face ``carry_clearance`` above the block's top
    5 transfer  -> the striking face above the block's top centre
    6 aim       -> the striking face ``aim_height`` above the block's top
    7 strike    -> the striking face ``overstrike`` below the block's top (the block stops
                   it: the head lands on the block)
    8 hold      keep it there
    9 raise     straight up by ``raise_height``
   10 rest      (to the end of the episode)

The gripper keeps the same downward rotation (``R_DOWN_6D``) throughout, so the hammer,
held level along x, is only translated: the ee is sent to the block's top centre minus
the striking face's offset from the ee at the grasp (both read from the initial state).
The other arm holds its home joints. The waypoints are computed once, in ``init``;
``equibim_jax.experts._waypoints`` turns them into joint targets by IK each step.

Mirror equivariance: every position is a point of the hammer or the block (reflected by
the mirror), ``R_DOWN_6D`` is its own mirror image for robot A, and the arm is chosen by
the sign of the block's y (never 0: ``block_y_range`` starts above 0), so from
``env.mirror_state(s0)`` the script issues ``env.action_symmetry`` of its actions from
``s0`` (see :mod:`equibim_jax.experts._waypoints`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from equibim_jax.experts._waypoints import check_expert_config, R_DOWN_6D, make_waypoint_expert
from equibim_jax.experts.place_empty_cup import Expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.beat_block_hammer import BeatBlockHammer

__all__ = ["HammerExpertConfig", "PHASES", "make_expert"]

PHASES = ("approach", "descend", "close", "settle", "lift", "transfer", "aim", "strike", "hold",
          "raise", "rest")


@dataclasses.dataclass(frozen=True)
class HammerExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of the segments approach, descend, close, settle, lift,
        transfer, aim, strike, hold, raise (one per phase except "rest").
      grasp_from_head: distance along the handle from the head's centre back to the grasp
        point (m).
      grasp_above_axis: ee height above the handle's axis at the grasp (m); the pads reach
        0.025 m below the ee, so this keeps their tips off the table.
      pregrasp_height: ee height above the grasp point for the approach (m).
      carry_clearance: striking-face height above the block's top while carried (m).
      aim_height: striking-face height above the block's top before the strike (m).
      overstrike: how far below the block's top the striking face is sent (m).
      raise_height: how far the ee rises after the strike (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (45, 25, 15, 8, 25, 45, 20, 10, 8, 20)
    grasp_from_head: float = 0.035
    grasp_above_axis: float = 0.01
    pregrasp_height: float = 0.08
    carry_clearance: float = 0.05
    aim_height: float = 0.03
    overstrike: float = 0.003
    raise_height: float = 0.06
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES,
                            positive=("pregrasp_height", "carry_clearance", "aim_height", "raise_height"),
                            nonnegative=("overstrike", "grasp_above_axis"))

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))

    @property
    def strike_end(self) -> int:
        """Step at which the strike segment ends."""
        return int(sum(self.durations[:8]))


def make_expert(env: Env, config: HammerExpertConfig = HammerExpertConfig()) -> Expert:
    """The scripted expert of ``beat_block_hammer`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`BeatBlockHammer` scene and ``action="joint"``.
      config: :class:`HammerExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts.Expert`: ``init(state)``, ``act(expert_state, state) ->
      (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, BeatBlockHammer):
        raise ValueError(f"the beat_block_hammer expert needs a BeatBlockHammer scene, got "
                         f"{type(scene).__name__}")
    hx = scene.handle_half[0]
    head_cx = scene.head_local[0]
    grasp_x = head_cx - config.grasp_from_head  # in the hammer's body frame
    # The pads' half width along the handle (the pad boxes' z half size: the ee's z axis
    # lies along the handle when the gripper points down); the pads must squeeze the
    # handle only, between the foot and the head.
    pad_w = float(env.mj_model.geom(env.info.gripper_pads[0][0]).size[2])
    lo, hi = scene.head_half[0] + pad_w, head_cx + hx - 2 * scene.foot_radius - pad_w
    if not lo <= config.grasp_from_head <= hi:
        raise ValueError(f"grasp_from_head must put the pads on the handle between the foot and "
                         f"the head: within [{lo:.3f}, {hi:.3f}] m, got {config.grasp_from_head}")
    grasp_local = (grasp_x, 0.0, config.grasp_above_axis)
    r_down = jnp.asarray(R_DOWN_6D)

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [10, 10] after the start pose, and whether the left arm acts."""
        data = state.data
        grasp = scene.hammer_point(data, env, grasp_local)  # [3] ee at the grasp
        face_off = scene.face_centre(data, env) - grasp  # [3] striking face relative to the ee
        top = scene.block_top(data, env)  # [3]
        left = scene.block_from_qpos(data.qpos, env)[1] > 0.0
        strike_ee = top - face_off  # ee position with the face on the block's top centre
        up = lambda p, dz: p + jnp.asarray([0.0, 0.0, 1.0], p.dtype) * dz
        carry_z = strike_ee[2] + config.carry_clearance  # [], also above the grasp point
        above_grasp = jnp.concatenate([grasp[:2], carry_z[None]])
        above_block = jnp.concatenate([strike_ee[:2], carry_z[None]])
        pos = jnp.stack([
            up(grasp, config.pregrasp_height),      # approach
            grasp,                                  # descend
            grasp,                                  # close
            grasp,                                  # settle
            above_grasp,                            # lift
            above_block,                            # transfer
            up(strike_ee, config.aim_height),       # aim
            up(strike_ee, -config.overstrike),      # strike
            up(strike_ee, -config.overstrike),      # hold
            up(strike_ee, config.raise_height),     # raise
        ])
        opening = jnp.array([1, 1, 0, 0, 0, 0, 0, 0, 0, 0], jnp.float32)
        rot = jnp.tile(r_down, (pos.shape[0], 1))
        wps = jnp.concatenate([pos, rot, opening[:, None]], axis=-1).astype(jnp.float32)
        return wps, left

    return make_waypoint_expert(env, plan, config.durations, config.ik_iterations, PHASES)
