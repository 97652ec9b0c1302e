"""Scripted expert for ``pick_dual_bottles``: both arms run the same pick-and-lift script
at the same time, each on the bottle on its side, as mirror images of each other.

Each arm (the left arm on the bottle with the larger y, the right arm on the other one),
gripper pointing straight down and closing along world y (``R_DOWN_6D``), runs one
phase per segment on the two-arm waypoint machinery
(:func:`~equibim_jax.experts._waypoints.make_bimanual_waypoint_expert`):

    0 approach  home pose -> ``pregrasp_height`` above the grasp point, opening to 1
    1 descend   -> the grasp point: pad centres ``grasp_below_top`` below the neck's top
    2 close     opening -> 0 (the pads squeeze the neck; the grasp holds by friction only)
    3 settle    hold still while the grip force builds
    4 lift      straight up, to the height that puts the body centre at the lift target's z
    5 transfer  across, until the body centre would be at its side's lift target
    6 hold      (to the end of the episode)

The plan reads the bottles' initial body centres from the state and each bottle's size
from the scene (``PickDualBottles.bottles()``; with ``robotwin_faithful=True`` the
two bottles differ), so the grasp height follows the bottle each arm picks.

Mirror equivariance
-------------------
The mirror reflects each bottle in place, so for the mirrored state the bottle with the
larger y is the mirror image of the other state's right bottle (same size): the plan
returns the reflected waypoints with the arms swapped. ``R_DOWN_6D`` is its own mirror
image for robot A, the lift targets are mirror images of each other, and both arms are
always active, so the actions from ``env.mirror_state(s0)`` are
``env.action_symmetry(a_t)`` to float32 round-off (see
:mod:`equibim_jax.experts._waypoints`).

The arms never come near each other: each arm's gripper stays on its own side of the
mirror plane (bottles and targets at ``|y| >= 0.1`` m, open pads reach about 5 cm to either
side of the grasp centre, and the arm links run from the base at ``|y| = 0.3`` m to it).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from equibim_jax.experts._waypoints import (
    check_expert_config, R_DOWN_6D, Expert, make_bimanual_waypoint_expert,
)
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.pick_dual_bottles import PickDualBottles

__all__ = ["PHASES", "DualBottlesExpertConfig", "make_expert"]

PHASES = ("approach", "descend", "close", "settle", "lift", "transfer", "hold")


@dataclasses.dataclass(frozen=True)
class DualBottlesExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of the segments approach, descend, close, settle, lift,
        transfer (one per phase except "hold").
      pregrasp_height: ee height above the grasp point for the approach (m).
      grasp_below_top: ee (pad centre) depth below the neck's top face (m). On robot A the
        palm's front face is 3.5 cm behind the pad centre and the pads reach 2.5 cm ahead
        of it, so 3 cm keeps the palm above the neck and the pad tips above the body.
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (35, 18, 12, 6, 24, 24)
    pregrasp_height: float = 0.08
    grasp_below_top: float = 0.03
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES, positive=("pregrasp_height",))

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))


def make_expert(env: Env, config: DualBottlesExpertConfig = DualBottlesExpertConfig()) -> Expert:
    """The scripted two-arm expert of ``pick_dual_bottles`` for ``env`` (joint actions).

    Args:
      env: an env built with a :class:`PickDualBottles` scene and ``action="joint"``.
      config: :class:`DualBottlesExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert`: ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, PickDualBottles):
        raise ValueError(f"the pick_dual_bottles expert needs a PickDualBottles scene, got "
                         f"{type(scene).__name__}")
    if not isinstance(config, DualBottlesExpertConfig):
        raise ValueError(f"config must be a DualBottlesExpertConfig, got {type(config).__name__}")
    for b in scene.bottles():
        if not 0.0 < config.grasp_below_top < b.neck_length:
            raise ValueError(f"grasp_below_top must lie within the neck's length (0, {b.neck_length}), "
                             f"got {config.grasp_below_top}")
    top = [b.top_above_centre for b in scene.bottles()]  # (a, b): neck top above the body centre
    ee_above = jnp.asarray([t - config.grasp_below_top for t in top], jnp.float32)  # [2]
    targets = scene.targets()  # [2, 3] (left, right) body-centre targets
    r_down = jnp.asarray(R_DOWN_6D)
    opening = jnp.array([1, 1, 0, 0, 0, 0], jnp.float32)  # after each segment

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [6, 2, 10] after the start poses (arm 0 left) and active [2] (both)."""
        pos = scene.bottle_positions(state.data, env)  # [2, 3] bottles a, b
        a_left = pos[0, 1] >= pos[1, 1]
        order = jnp.where(a_left, jnp.array([0, 1]), jnp.array([1, 0]))  # bottle of arm 0, 1
        centre = pos[order]  # [2, 3] the bottle each arm picks
        h = ee_above[order]  # [2] ee height above that bottle's body centre at the grasp
        grasp = centre + h[:, None] * jnp.array([0.0, 0.0, 1.0])
        lifted = jnp.concatenate([centre[:, :2], (targets[:, 2] + h)[:, None]], axis=-1)
        goal = targets + h[:, None] * jnp.array([0.0, 0.0, 1.0])
        above = grasp + jnp.array([0.0, 0.0, config.pregrasp_height])
        pos_wp = jnp.stack([above, grasp, grasp, grasp, lifted, goal])  # [6, 2, 3]
        rot = jnp.broadcast_to(r_down, (6, 2, 6))
        grip = jnp.broadcast_to(opening[:, None, None], (6, 2, 1))
        wps = jnp.concatenate([pos_wp, rot, grip], axis=-1).astype(jnp.float32)
        return wps, jnp.ones((2,), bool)

    return make_bimanual_waypoint_expert(env, plan, config.durations, config.ik_iterations,
                                         phase_names=PHASES)
