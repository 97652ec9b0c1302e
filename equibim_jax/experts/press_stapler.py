"""Scripted expert for ``press_stapler``: a pure-JAX, vmappable waypoint script.

The arm on the stapler's side (the left arm when the stapler's y > 0; at y = 0 exactly,
the side drawn by ``init``, ``state.info["side"]``) does, one phase per segment:

    0 approach  home pose -> above the press point of the open plate, gripper closing and
                turning to point down
    1 descend   -> pad tips just above the open plate's press point
    2 press     -> in a straight line to ``overpress`` below where the press point is
                   when the plate is shut (the chord of the press point's arc, so the
                   pads roughly follow it instead of sliding along the plate)
    3 hold      keep it shut
    4 retreat   straight up (the spring reopens the plate)
    5 rest      (to the end of the episode)

The other arm holds its home joints. The waypoints are computed once, in ``init``, from
the stapler's initial pose; ``equibim_jax.experts._waypoints`` turns them into joint
targets by IK each step. The gripper points straight down (``R_DOWN_6D``) whatever the
stapler's yaw: the closed pads' bottom faces are a square that presses the plate the
same way at any heading, and that rotation is its own mirror image. Every position is a
point on the stapler, so the script is mirror-equivariant: from ``env.mirror_state(s0)``
it issues ``env.action_symmetry`` of its actions from ``s0``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from equibim_jax.experts._waypoints import (
    check_expert_config, R_DOWN_6D, make_waypoint_expert, pad_tip_below_ee,
)
from equibim_jax.experts._waypoints import Expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.press_stapler import PressStapler

__all__ = ["StaplerExpertConfig", "PHASES", "make_expert"]

PHASES = ("approach", "descend", "press", "hold", "retreat", "rest")


@dataclasses.dataclass(frozen=True)
class StaplerExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of approach, descend, press, hold, retreat.
      approach_height: pad-tip height above the open press point after the approach (m).
      touch_clearance: pad-tip height above the open press point after the descent (m).
      overpress: how far below the shut press point the pad tips are sent (m).
      retreat_height: pad-tip height above the shut press point after the retreat (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (45, 20, 30, 10, 20)
    approach_height: float = 0.06
    touch_clearance: float = 0.005
    overpress: float = 0.003
    retreat_height: float = 0.1
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES)

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))


def make_expert(env: Env, config: StaplerExpertConfig = StaplerExpertConfig()) -> Expert:
    """The scripted expert of ``press_stapler`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`PressStapler` scene and ``action="joint"``.
      config: :class:`StaplerExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts.Expert`: ``init(state)``, ``act(expert_state, state) ->
      (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, PressStapler):
        raise ValueError(f"make_expert needs a PressStapler scene, got {type(scene).__name__}")
    tip = pad_tip_below_ee(env)
    r_down = jnp.asarray(R_DOWN_6D)

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [5, 10] after the start pose, and whether the left arm acts."""
        data = state.data
        y = scene.pose_from_qpos(data.qpos, env)[1]
        left = jnp.where(y != 0.0, y > 0.0, state.info["side"] > 0)
        p_open = scene.press_point(data, env)  # [3]
        p_shut = scene.shut_press_point(data, env)  # [3]

        def wp(p, dz):  # ee waypoint with the pad tips ``dz`` above the point ``p``
            pos = jnp.concatenate([p[:2], p[2:] + tip + dz])
            return jnp.concatenate([pos, r_down, jnp.zeros((1,), pos.dtype)])  # closed

        wps = jnp.stack([
            wp(p_open, config.approach_height),   # above the press point
            wp(p_open, config.touch_clearance),   # just above it
            wp(p_shut, -config.overpress),        # plate pushed shut
            wp(p_shut, -config.overpress),        # held
            wp(p_shut, config.retreat_height),    # retreated
        ])
        return wps, left

    return make_waypoint_expert(env, plan, config.durations, config.ik_iterations, PHASES)
