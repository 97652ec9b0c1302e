"""Scripted expert for ``move_can_pot``: the pick-and-place script of
:mod:`equibim_jax.experts.pick_place` with a plan for the can.

The arm on the can's side (the left arm when the can's y > 0, ``s = +1``) grips the can
``grasp_below_top`` below its top face, lifts it, carries it to the release point beside
the pot and stands it down with its bottom ``place_clearance`` above the table, opens and
retreats upward. The release point is at the pot's x, and at
``pot_y + s (r(yaw) + can_half_y + place_gap)`` in y, where ``r(yaw)`` is the half extent
in y of the pot's yawed footprint: the can's side face ends ``place_gap`` clear of the
pot. The plan reads the initial can and pot poses (reflected by the mirror; ``r`` is
even in the yaw) and the sign of the can's y, so the expert is mirror-equivariant (see
:mod:`equibim_jax.experts.pick_place`).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from equibim_jax.experts.pick_place import PickPlaceConfig, PickPlacePlan, make_pick_place_expert
from equibim_jax.experts._waypoints import Expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.move_can_pot import MoveCanPot

__all__ = ["CanExpertConfig", "make_expert"]


@dataclasses.dataclass(frozen=True)
class CanExpertConfig(PickPlaceConfig):
    """:class:`PickPlaceConfig` plus the grasp height and the release point.

    Attributes:
      grasp_below_top: ee (pad centre) height below the can's top face (m).
      place_gap: gap between the pot's footprint and the can's near side face (m).
    """

    grasp_below_top: float = 0.03
    place_gap: float = 0.02


def make_expert(env: Env, config: CanExpertConfig = CanExpertConfig()) -> Expert:
    """The scripted expert of ``move_can_pot`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`MoveCanPot` scene and ``action="joint"``.
      config: :class:`CanExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert`: ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, MoveCanPot):
        raise ValueError(f"the move_can_pot expert needs a MoveCanPot scene, got {type(scene).__name__}")
    if not 0.0 < config.grasp_below_top < 2 * scene.can_half[2]:
        raise ValueError(f"grasp_below_top must lie within the can's height "
                         f"(0, {2 * scene.can_half[2]}), got {config.grasp_below_top}")
    reach = scene.pot_reach_y(scene.pot_max_yaw) + scene.can_half[1]
    if not 0.0 < config.place_gap < scene.beside_max_dy - reach:
        raise ValueError(f"place_gap must be in (0, {scene.beside_max_dy - reach:.4f}) so that the "
                         f"can lands beside the pot within beside_max_dy; got {config.place_gap}")
    can_hy, can_hz = scene.can_half[1], scene.can_half[2]
    table = env.info.table_height

    def plan(state: State) -> PickPlacePlan:
        can, _ = scene.can_pose(state.data, env)
        pot, pot_rot = scene.pot_pose(state.data, env)
        left = can[1] > 0.0
        s = jnp.where(left, 1.0, -1.0)
        yaw_reach = scene.pot_half[0] * jnp.abs(pot_rot[1, 0]) + scene.pot_half[1] * jnp.abs(pot_rot[1, 1])
        place_y = pot[1] + s * (yaw_reach + can_hy + config.place_gap)
        grasp_z = can[2] + can_hz - config.grasp_below_top
        bottom_below_ee = grasp_z - (can[2] - can_hz)
        place_z = table + config.place_clearance + bottom_below_ee
        return PickPlacePlan(
            grasp=jnp.concatenate([can[:2], grasp_z[None]]),
            place=jnp.stack([pot[0], place_y, place_z]),
            left=left,
        )

    return make_pick_place_expert(env, plan, config)
