"""Scripted expert for ``stamp_seal``: the pick-and-place script of
:mod:`equibim_jax.experts.pick_place` with a plan for the seal.

The arm on the seal's side (the left arm when the seal's y > 0) closes its pads on the
seal's handle, ``grasp_below_top`` below the handle's top face (the pads, 5 cm long along
the approach, then end above the base), lifts the seal, carries it over the mat, lowers it
until its stamping face is ``place_clearance`` above the mat's top face, opens, and
retreats upward. The plan reads only the initial seal and mat positions (reflected by the
mirror) and the sign of the seal's y, so the expert is mirror-equivariant (see
:mod:`equibim_jax.experts.pick_place`).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from equibim_jax.experts.pick_place import PickPlaceConfig, PickPlacePlan, make_pick_place_expert
from equibim_jax.experts._waypoints import Expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.stamp_seal import StampSeal

__all__ = ["SealExpertConfig", "make_expert"]


@dataclasses.dataclass(frozen=True)
class SealExpertConfig(PickPlaceConfig):
    """:class:`PickPlaceConfig` plus where the pads grip the handle.

    Attributes:
      grasp_below_top: ee (pad centre) height below the handle's top face (m).
    """

    grasp_below_top: float = 0.02


def make_expert(env: Env, config: SealExpertConfig = SealExpertConfig()) -> Expert:
    """The scripted expert of ``stamp_seal`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`StampSeal` scene and ``action="joint"``.
      config: :class:`SealExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert`: ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, StampSeal):
        raise ValueError(f"the stamp_seal expert needs a StampSeal scene, got {type(scene).__name__}")
    if not 0.0 < config.grasp_below_top < 2 * scene.handle_half[2]:
        raise ValueError(f"grasp_below_top must lie within the handle's height "
                         f"(0, {2 * scene.handle_half[2]}), got {config.grasp_below_top}")
    base_hz = scene.base_half[2]
    mat_top_above_centre = scene.mat_half[2]

    def plan(state: State) -> PickPlacePlan:
        seal, _ = scene.seal_pose(state.data, env)
        mat = scene.mat_position(state.data, env)
        bottom = seal[2] - base_hz
        grasp_z = bottom + scene.seal_height - config.grasp_below_top
        place_z = mat[2] + mat_top_above_centre + config.place_clearance + (grasp_z - bottom)
        return PickPlacePlan(
            grasp=jnp.concatenate([seal[:2], grasp_z[None]]),
            place=jnp.concatenate([mat[:2], place_z[None]]),
            left=seal[1] > 0.0,
        )

    return make_pick_place_expert(env, plan, config)
