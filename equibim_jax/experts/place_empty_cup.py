"""Scripted expert for ``place_empty_cup``: a pure-JAX, vmappable waypoint state machine.

The arm on the cup's side (the left arm when the cup's y > 0) does, one phase per segment:

    0 approach  home pose -> above the cup, gripper opening to 1, gripper turning to point down
    1 descend   -> grasp height (pads around the cup's upper part)
    2 close     opening -> 0 (the pads squeeze the cup; the grasp holds by friction only)
    3 settle    hold still while the grip force builds
    4 lift      -> carry height
    5 transfer  -> above the coaster
    6 lower     -> the cup's bottom ``place_clearance`` above the coaster top
    7 release   opening -> 1
    8 retreat   straight up
    9 hold      (to the end of the episode)

The other arm holds its home joints. Waypoints (ee position, gripper rotation, opening) are
computed once in ``init`` from the initial cup and coaster positions; between waypoints
the target moves along a smoothstep (zero velocity at both ends), and each control step
the ee target is turned into JOINT targets by damped-least-squares IK warm-started from
the previous step's solution, so the demos carry joint actions (``action="joint"``).
Phase changes are by time: the phase is a pure function of the step counter (no Python
branching on traced values).

Mirror equivariance
-------------------
Everything is computed from mirror-covariant quantities: the active arm is chosen by the
sign of the cup's y, positions are the objects' (mirrored as points), the start pose is
the active arm's own FK pose, and the grasp rotation ``R_down`` (approach -z, closing
direction y) satisfies ``M R_down L = R_down`` for robot A's ee frames (``L = diag(1,-1,1)``),
so it is the same for both arms. Linear interpolation of 6D rotations followed by
Gram-Schmidt commutes with ``R -> M R L``, and the IK is equivariant when its initial
guess is mirrored. So from ``env.mirror_state(s0)`` the expert issues
``env.action_symmetry(a_t)`` (to float32 round-off: about 1e-5 rad, see the tests).
The script is open loop after ``init`` (``act`` reads nothing but the step counter and
its own IK warm start), so the actions stay equivariant however the two simulations
drift apart through contacts.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from equibim_jax.sim.env import Env, State
from equibim_jax.sim.ik import make_ee_fk, make_ik, mat_to_rot6d
from equibim_jax.tasks.place_empty_cup import PlaceEmptyCup

__all__ = ["CupExpertConfig", "CupExpertState", "Expert", "PHASES", "make_expert"]

PHASES = ("approach", "descend", "close", "settle", "lift", "transfer", "lower", "release",
          "retreat", "hold")

# Gripper pointing straight down (ee x = -z), closing along world y (ee y = +y).
_R_DOWN_6D = np.array([0.0, 0.0, -1.0, 0.0, 1.0, 0.0], np.float32)


class Expert(NamedTuple):
    """A scripted expert as pure functions (``jit``/``vmap`` them freely).

    Attributes:
      init: ``init(env_state) -> expert_state`` for one environment.
      act: ``act(expert_state, env_state) -> (expert_state, action [A])``; ``A`` is the
        env's joint action size (14 for robot A).
      horizon: control steps the script needs before its last phase ("hold") begins.
      phase: ``phase(expert_state) -> [] int32`` index into :data:`PHASES`.
    """

    init: Callable[[State], "CupExpertState"]
    act: Callable[["CupExpertState", State], tuple["CupExpertState", jax.Array]]
    horizon: int
    phase: Callable[["CupExpertState"], jax.Array]


@struct.dataclass
class CupExpertState:
    """Expert state of one environment (a pytree).

    Attributes:
      t: [] int32 control step.
      q: [nq] last IK solution (the warm start of the next solve).
      waypoints: [K, 10] active-arm waypoints: ee position (3), 6D rotation (6), opening (1).
      left: [] bool, whether the left arm is the active one.
      rest_opening: [] float32, the idle arm's gripper opening (its home opening).
    """

    t: jax.Array
    q: jax.Array
    waypoints: jax.Array
    left: jax.Array
    rest_opening: jax.Array


@dataclasses.dataclass(frozen=True)
class CupExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of the segments approach, descend, close, settle, lift,
        transfer, lower, release, retreat (one per phase except "hold").
      grasp_below_top: ee (pad centre) height below the cup's top face (m).
      pregrasp_height: ee height above the grasp height for the approach (m).
      carry_lift: how far the cup is lifted for the transfer (m).
      place_clearance: height of the cup's bottom over the coaster top at release (m).
      retreat_height: how far the gripper rises after release (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (45, 25, 15, 8, 25, 45, 25, 12, 20)
    grasp_below_top: float = 0.025
    pregrasp_height: float = 0.08
    carry_lift: float = 0.06
    place_clearance: float = 0.003
    retreat_height: float = 0.08
    ik_iterations: int = 10

    def __post_init__(self):
        if len(self.durations) != len(PHASES) - 1 or min(self.durations) < 1:
            raise ValueError(
                f"durations needs {len(PHASES) - 1} positive step counts (one per phase "
                f"{PHASES[:-1]}), got {self.durations}"
            )

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))


def _smoothstep(u):
    return u * u * (3.0 - 2.0 * u)


def make_expert(env: Env, config: CupExpertConfig = CupExpertConfig()) -> Expert:
    """The scripted expert of ``place_empty_cup`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`PlaceEmptyCup` scene and ``action="joint"``.
      config: :class:`CupExpertConfig`.

    Returns:
      :class:`Expert` with ``init(state) -> expert_state`` and
      ``act(expert_state, state) -> (expert_state, action [14])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, PlaceEmptyCup):
        raise ValueError(f"make_expert needs a PlaceEmptyCup scene, got {type(scene).__name__}")
    if env.config.action != "joint":
        raise ValueError(f"the place_empty_cup expert emits joint actions; env action is "
                         f"{env.config.action!r} (build the env with action='joint')")
    ik = make_ik(env.mj_model, env.info, iterations=config.ik_iterations)
    fk = make_ee_fk(env.mj_model, env.info)
    arm_qadr = jnp.asarray(env.arm_qadr)  # [2, n_arm]
    home_open = env.info.gripper_opening(jnp.asarray(env.home_qpos)[env.grip_qadr])  # [2]
    times = np.concatenate([[0], np.cumsum(config.durations)]).astype(np.int32)  # [K]
    durs = np.asarray(config.durations, np.float32)
    r_down = jnp.asarray(_R_DOWN_6D)
    top_above_centre = scene.cup_half[2]
    coaster_top_above_centre = scene.coaster_half[2]

    def init(state: State) -> CupExpertState:
        """Plan the waypoints from the initial cup/coaster positions of ``state``."""
        data = state.data
        q = data.qpos
        cup, _ = scene.cup_pose(data, env)
        coaster = scene.coaster_position(data, env)
        left = cup[1] > 0.0
        pos, mat = fk(q)  # [2, 3], [2, 3, 3]
        start = jnp.where(left, jnp.concatenate([pos[0], mat_to_rot6d(mat[0])]),
                          jnp.concatenate([pos[1], mat_to_rot6d(mat[1])]))
        grasp_z = cup[2] + top_above_centre - config.grasp_below_top
        # the ee-to-cup-bottom offset the grasp fixes, used to place the bottom
        bottom_below_ee = grasp_z - (cup[2] - top_above_centre)
        place_z = coaster[2] + coaster_top_above_centre + config.place_clearance + bottom_below_ee
        carry_z = grasp_z + config.carry_lift
        p = lambda xy, z: jnp.concatenate([xy, z[None]])
        wp_pos = jnp.stack([
            start[:3],                                            # home
            p(cup[:2], grasp_z + config.pregrasp_height),         # above the cup
            p(cup[:2], grasp_z),                                  # grasp height
            p(cup[:2], grasp_z),                                  # closed
            p(cup[:2], grasp_z),                                  # settled
            p(cup[:2], carry_z),                                  # lifted
            p(coaster[:2], carry_z),                              # above the coaster
            p(coaster[:2], place_z),                              # lowered
            p(coaster[:2], place_z),                              # released
            p(coaster[:2], place_z + config.retreat_height),      # retreated
        ])
        n = wp_pos.shape[0]
        wp_rot = jnp.concatenate([start[None, 3:], jnp.tile(r_down, (n - 1, 1))])
        op = jnp.array([0, 1, 1, 0, 0, 0, 0, 0, 1, 1], jnp.float32)
        op = op.at[0].set(jnp.where(left, home_open[0], home_open[1]))
        wps = jnp.concatenate([wp_pos, wp_rot, op[:, None]], axis=-1).astype(jnp.float32)
        return CupExpertState(
            t=jnp.zeros((), jnp.int32), q=q, waypoints=wps, left=left,
            rest_opening=jnp.where(left, home_open[1], home_open[0]).astype(jnp.float32),
        )

    def phase(es: CupExpertState) -> jax.Array:
        """[] int32 phase index of the step the expert is about to take."""
        return jnp.searchsorted(jnp.asarray(times[1:]), es.t + 1, side="left").astype(jnp.int32)

    def target(es: CupExpertState) -> jax.Array:
        """Active-arm target [10] for step ``t``: reached at the end of the step."""
        s = es.t + 1
        seg = jnp.clip(jnp.searchsorted(jnp.asarray(times), s, side="right") - 1, 0, len(durs) - 1)
        u = jnp.clip((s - jnp.asarray(times)[seg]).astype(jnp.float32) / jnp.asarray(durs)[seg],
                     0.0, 1.0)
        w = _smoothstep(u)
        a, b = es.waypoints[seg], es.waypoints[seg + 1]
        return a + w * (b - a)

    def act(es: CupExpertState, state: State) -> tuple[CupExpertState, jax.Array]:
        """One control step: (next expert state, joint action [2 * (n_arm + 1)])."""
        del state  # open loop after init (see the module docstring)
        tgt = target(es)
        pos, mat = fk(es.q)
        idle = jnp.where(es.left, jnp.concatenate([pos[1], mat_to_rot6d(mat[1])]),
                         jnp.concatenate([pos[0], mat_to_rot6d(mat[0])]))
        targets = jnp.where(es.left, jnp.stack([tgt[:9], idle]), jnp.stack([idle, tgt[:9]]))
        active = jnp.stack([es.left, ~es.left])
        q = ik(es.q, targets, active=active)
        opening = jnp.where(es.left, jnp.stack([tgt[9], es.rest_opening]),
                            jnp.stack([es.rest_opening, tgt[9]]))
        action = jnp.concatenate([q[arm_qadr], opening[:, None]], axis=-1).reshape(-1)
        return es.replace(t=es.t + 1, q=q), action

    return Expert(init=init, act=act, horizon=config.horizon, phase=phase)
