"""A one-arm pick-and-place script as a pure-JAX, vmappable waypoint state machine.

Task experts (``place_empty_cup``, ``stamp_seal``, ``move_can_pot``) supply a *plan*: a
pure function of the initial env state that says which arm acts, where its end effector
grasps the object and where it releases it. :func:`make_pick_place_expert` turns the plan into an
:class:`~equibim_jax.experts._waypoints.Expert` that runs, one phase per segment:

    0 approach  home pose -> ``pregrasp_height`` above the grasp point, gripper opening to
                1 and turning to point down
    1 descend   -> the grasp point
    2 close     opening -> 0 (the pads squeeze the object; the grasp holds by friction only)
    3 settle    hold still while the grip force builds
    4 lift      -> carry height
    5 transfer  -> above the release point
    6 lower     -> the release point
    7 release   opening -> 1
    8 retreat   straight up by ``retreat_height``
    9 hold      (to the end of the episode)

The carry height is ``carry_lift`` above the higher of the grasp and release points, unless
the plan sets its own (``PickPlacePlan.carry_z``). The
waypoints run on the one-arm waypoint machinery of :mod:`equibim_jax.experts._waypoints`
(shared with the press-type experts): smoothstep segments, warm-started
damped-least-squares IK each control step, the other arm holding its home joints, the
phase a pure function of the step counter (``action="joint"``).

Mirror equivariance
-------------------
The grasp rotation ``R_down`` (approach -z, closing direction +y) is its own mirror image
for robot A's ee frames (``M R_down L = R_down``), the start pose is the acting arm's own
FK pose, and the IK is equivariant when its warm start is mirrored. So if the plan is
mirror-covariant (the acting arm flips and the two points are reflected when the initial
state is mirrored), the expert issues ``env.action_symmetry(a_t)`` from
``env.mirror_state(s0)`` to float32 round-off. The script is open loop after ``init``.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from equibim_jax.experts._waypoints import check_expert_config, R_DOWN_6D, Expert, make_waypoint_expert
from equibim_jax.sim.env import Env, State

__all__ = ["PHASES", "PickPlaceConfig", "PickPlacePlan", "make_pick_place_expert"]

PHASES = ("approach", "descend", "close", "settle", "lift", "transfer", "lower", "release",
          "retreat", "hold")


class PickPlacePlan(NamedTuple):
    """What a task's plan function returns for one initial state.

    Attributes:
      grasp: [3] ee (pad centre) position at which the gripper closes.
      place: [3] ee position at which it opens again.
      left: [] bool, whether the left arm acts.
      carry_z: optional [] ee height of the lift and transfer; None: ``carry_lift`` above
        the higher of ``grasp`` and ``place``.
    """

    grasp: jax.Array
    place: jax.Array
    left: jax.Array
    carry_z: jax.Array | None = None


@dataclasses.dataclass(frozen=True)
class PickPlaceConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of the segments approach, descend, close, settle, lift,
        transfer, lower, release, retreat (one per phase except "hold").
      pregrasp_height: ee height above the grasp point for the approach (m).
      carry_lift: carry height above the higher of the grasp and release points (m).
      place_clearance: gap left under the object at release (m); task plans use it.
      retreat_height: how far the gripper rises after release (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (45, 25, 15, 8, 25, 45, 25, 12, 20)
    pregrasp_height: float = 0.08
    carry_lift: float = 0.06
    place_clearance: float = 0.003
    retreat_height: float = 0.08
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES,
                            positive=("pregrasp_height", "carry_lift", "retreat_height"),
                            nonnegative=("place_clearance",))

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))

    @property
    def release_end(self) -> int:
        """Step at which the release segment ends (the gripper is fully open)."""
        return int(sum(self.durations[:8]))


def make_pick_place_expert(env: Env, plan: Callable[[State], PickPlacePlan],
                           config: PickPlaceConfig) -> Expert:
    """A one-arm pick-and-place expert for ``env`` (joint action mode).

    Args:
      env: an env with ``action="joint"`` on robot A.
      plan: ``plan(state) -> PickPlacePlan`` from one initial env state (pure, traced).
      config: :class:`PickPlaceConfig` (or a subclass).

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert` with ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [2 * (n_arm + 1)])``, pure and
      vmappable.
    """
    r_down = jnp.asarray(R_DOWN_6D)

    def waypoints(state: State) -> tuple[jax.Array, jax.Array]:
        """The 9 waypoints [9, 10] after the start pose, and whether the left arm acts."""
        pl = plan(state)
        grasp, place = pl.grasp, pl.place
        carry_z = (jnp.maximum(grasp[2], place[2]) + config.carry_lift
                   if pl.carry_z is None else pl.carry_z)
        p = lambda xy, z: jnp.concatenate([xy, jnp.reshape(z, (1,))])
        pos = jnp.stack([
            p(grasp[:2], grasp[2] + config.pregrasp_height),    # above the object
            grasp,                                              # grasp point
            grasp,                                              # closed
            grasp,                                              # settled
            p(grasp[:2], carry_z),                              # lifted
            p(place[:2], carry_z),                              # above the release point
            place,                                              # lowered
            place,                                              # released
            p(place[:2], place[2] + config.retreat_height),     # retreated
        ])
        opening = jnp.array([1, 1, 0, 0, 0, 0, 0, 1, 1], jnp.float32)
        rot = jnp.tile(r_down, (pos.shape[0], 1))
        return jnp.concatenate([pos, rot, opening[:, None]], axis=-1).astype(jnp.float32), pl.left

    return make_waypoint_expert(env, waypoints, config.durations, config.ik_iterations,
                                phase_names=PHASES)
