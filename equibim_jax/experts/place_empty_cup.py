"""Scripted expert for ``place_empty_cup``: the pick-and-place script of
:mod:`equibim_jax.experts.pick_place` with a plan for the cup.

The arm on the cup's side (the left arm when the cup's y > 0) approaches the cup from
above with the gripper pointing down, closes its pads ``grasp_below_top`` below the cup's
top face (the grasp holds by friction only), lifts the cup by ``carry_lift``, carries it
over the coaster, lowers it until its bottom is ``place_clearance`` above the coaster's
top, opens, and retreats upward. The other arm holds its home joints. The phases are
:data:`~equibim_jax.experts.pick_place.PHASES`.

The plan reads only the initial cup and coaster positions (reflected by the mirror) and
the sign of the cup's y, so the expert is mirror-equivariant: from
``env.mirror_state(s0)`` it issues ``env.action_symmetry(a_t)`` to float32 round-off (see
:mod:`equibim_jax.experts._waypoints`).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from equibim_jax.experts._waypoints import Expert, WaypointState
from equibim_jax.experts.pick_place import PHASES, PickPlaceConfig, PickPlacePlan, make_pick_place_expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.place_empty_cup import PlaceEmptyCup

__all__ = ["CupExpertConfig", "CupExpertState", "Expert", "PHASES", "make_expert"]

CupExpertState = WaypointState
"""The expert's state (the shared waypoint state)."""


@dataclasses.dataclass(frozen=True)
class CupExpertConfig(PickPlaceConfig):
    """:class:`PickPlaceConfig` plus where the pads grip the cup.

    Attributes:
      grasp_below_top: ee (pad centre) height below the cup's top face (m).

    Here ``carry_lift`` is measured from the grasp height (the cup is lifted by it).
    """

    grasp_below_top: float = 0.025


def make_expert(env: Env, config: CupExpertConfig = CupExpertConfig()) -> Expert:
    """The scripted expert of ``place_empty_cup`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`PlaceEmptyCup` scene and ``action="joint"``.
      config: :class:`CupExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert`: ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, PlaceEmptyCup):
        raise ValueError(f"make_expert needs a PlaceEmptyCup scene, got {type(scene).__name__}")
    top_above_centre = scene.cup_half[2]
    coaster_top_above_centre = scene.coaster_half[2]

    def plan(state: State) -> PickPlacePlan:
        cup, _ = scene.cup_pose(state.data, env)
        coaster = scene.coaster_position(state.data, env)
        grasp_z = cup[2] + top_above_centre - config.grasp_below_top
        # the ee-to-cup-bottom offset the grasp fixes, used to place the bottom
        bottom_below_ee = grasp_z - (cup[2] - top_above_centre)
        place_z = coaster[2] + coaster_top_above_centre + config.place_clearance + bottom_below_ee
        return PickPlacePlan(
            grasp=jnp.concatenate([cup[:2], grasp_z[None]]),
            place=jnp.concatenate([coaster[:2], place_z[None]]),
            left=cup[1] > 0.0,
            carry_z=grasp_z + config.carry_lift,
        )

    return make_pick_place_expert(env, plan, config)
