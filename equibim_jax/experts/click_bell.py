"""Scripted expert for ``click_bell``: a pure-JAX, vmappable waypoint script.

The arm on the bell's side (the left arm when the bell's y > 0) does, one phase per
segment:

    0 approach  home pose -> above the button, gripper closing and turning to point down
    1 descend   -> pad tips just above the button top
    2 press     -> pad tips ``press_travel`` below the button's rest top (pushing the
                   button down against its spring)
    3 hold      keep it pressed
    4 retreat   straight up (the spring lifts the button)
    5 rest      (to the end of the episode)

The other arm holds its home joints. The waypoints are computed once, in ``init``, from
the button's initial position; ``equibim_jax.experts._waypoints`` turns them into joint
targets by IK each step. The grasp rotation is ``R_DOWN_6D`` for both arms and every
position is the button's (a point), so the script is mirror-equivariant: from
``env.mirror_state(s0)`` it issues ``env.action_symmetry`` of its actions from ``s0``.
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
from equibim_jax.tasks.click_bell import ClickBell

__all__ = ["BellExpertConfig", "PHASES", "make_expert"]

PHASES = ("approach", "descend", "press", "hold", "retreat", "rest")


@dataclasses.dataclass(frozen=True)
class BellExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of approach, descend, press, hold, retreat.
      approach_height: pad-tip height above the button top at the end of the approach (m).
      touch_clearance: pad-tip height above the button top at the end of the descent (m).
      press_travel: how far below the button's rest top the pad tips are sent (m).
      retreat_height: pad-tip height above the button top after the retreat (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (45, 20, 25, 10, 20)
    approach_height: float = 0.06
    touch_clearance: float = 0.005
    press_travel: float = 0.012
    retreat_height: float = 0.08
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES)

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))


def make_expert(env: Env, config: BellExpertConfig = BellExpertConfig()) -> Expert:
    """The scripted expert of ``click_bell`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`ClickBell` scene and ``action="joint"``.
      config: :class:`BellExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts.Expert`: ``init(state)``, ``act(expert_state, state) ->
      (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, ClickBell):
        raise ValueError(f"make_expert needs a ClickBell scene, got {type(scene).__name__}")
    if config.press_travel >= scene.button_travel + 0.01:
        raise ValueError("press_travel would drive the pads far past the button's lower stop")
    tip = pad_tip_below_ee(env)
    r_down = jnp.asarray(R_DOWN_6D)

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [5, 10] after the start pose, and whether the left arm acts."""
        top = scene.button_top(state.data, env)  # [3]
        left = top[1] > 0.0

        def wp(dz):  # ee waypoint with the pad tips ``dz`` above the button's rest top
            p = jnp.concatenate([top[:2], top[2:] + tip + dz])
            return jnp.concatenate([p, r_down, jnp.zeros((1,), p.dtype)])  # gripper closed

        wps = jnp.stack([
            wp(config.approach_height),     # above the button
            wp(config.touch_clearance),     # just above its top
            wp(-config.press_travel),       # pressed
            wp(-config.press_travel),       # held
            wp(config.retreat_height),      # retreated
        ])
        return wps, left

    return make_waypoint_expert(env, plan, config.durations, config.ik_iterations, PHASES)
