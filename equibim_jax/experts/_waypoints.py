"""Waypoint scripts: the machinery every scripted expert runs on.

A task's expert supplies a *plan*: a pure function of the initial env state that returns
end-effector waypoints. This module turns the plan into a pure, vmappable
:class:`Expert`:

* row 0 of each arm's waypoints is the arm's own start pose (forward kinematics of the
  initial ``qpos``) with its home gripper opening;
* segment ``k`` moves every arm from waypoint ``k`` to ``k + 1`` in ``durations[k]``
  control steps along a smoothstep (zero velocity at both ends); after the last segment
  the targets hold the last waypoints;
* each control step, damped-least-squares IK (warm-started from the previous step's
  solution) turns the active arms' targets into joint targets; an inactive arm holds its
  initial joints and its home gripper opening;
* the phase is a pure function of the step counter, so nothing branches on traced values,
  and the script is open loop after ``init``.

Two entry points: :func:`make_bimanual_waypoint_expert` (plans give both arms' waypoints,
``[K - 1, 2, 10]``, and which arms act) and :func:`make_waypoint_expert` (one arm acts,
plans give its waypoints ``[K - 1, 10]`` and whether it is the left arm).

A waypoint row is [10]: ee position (3), 6D rotation (6, the first two columns of the
rotation matrix, :func:`~equibim_jax.sim.ik.mat_to_rot6d`), normalised gripper opening
(1; 1 open, 0 closed). Arm 0 is the left arm (y > 0), arm 1 the right.

Mirror equivariance
-------------------
Linear interpolation of 6D rotations followed by Gram-Schmidt commutes with
``R -> M R L``, the start poses are the arms' own FK poses, and the IK is equivariant when
its warm start is mirrored. So if the plan is mirror-covariant (for the mirrored state it
returns the mirrored waypoints, positions reflected as points and rotations mapped by
``R -> M R L``, with the two arms swapped, and ``active`` swapped), the actions from
``env.mirror_state(s0)`` are ``env.action_symmetry`` of the actions from ``s0``, to
float32 round-off, however the two simulations drift apart through contacts.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from equibim_jax.sim.env import Env, State
from equibim_jax.sim.ik import make_ee_fk, make_ik, mat_to_rot6d

__all__ = ["R_DOWN_6D", "Expert", "WaypointState", "check_expert_config", "make_bimanual_waypoint_expert",
           "make_waypoint_expert", "pad_tip_below_ee"]

R_DOWN_6D = np.array([0.0, 0.0, -1.0, 0.0, 1.0, 0.0], np.float32)
"""Gripper pointing straight down (ee x = -z), closing along world y (ee y = +y). For robot
A's ee frames ``M R L = R`` for this rotation, so it is the same for both arms and its own
mirror image."""


class Expert(NamedTuple):
    """A scripted expert as pure functions (``jit``/``vmap`` them freely).

    Attributes:
      init: ``init(env_state) -> expert_state`` for one environment.
      act: ``act(expert_state, env_state) -> (expert_state, action [A])``; ``A`` is the
        env's joint action size (14 for robot A).
      horizon: control steps the script needs before its final hold begins.
      phase: ``phase(expert_state) -> [] int32``, the index of the segment the next step
        is in (``len(durations)``: the final hold).
    """

    init: Callable[[State], Any]
    act: Callable[[Any, State], tuple[Any, jax.Array]]
    horizon: int
    phase: Callable[[Any], jax.Array]


@struct.dataclass
class WaypointState:
    """Expert state of one environment (a pytree).

    Attributes:
      t: [] int32 control step.
      q: [nq] last IK solution (the warm start of the next solve).
      waypoints: [K, 2, 10] per-arm waypoints; row 0 is the start pose.
      active: [2] bool, which arms follow their waypoints.
    """

    t: jax.Array
    q: jax.Array
    waypoints: jax.Array
    active: jax.Array


def check_expert_config(config: Any, phases: tuple[str, ...], positive: tuple[str, ...] = (),
                        nonnegative: tuple[str, ...] = ()) -> None:
    """Check a phased expert config: ``config.durations`` holds one positive step count per
    phase but the last of ``phases``, the fields named in ``positive`` are > 0 and those in
    ``nonnegative`` are >= 0. Raises ``ValueError`` naming the first field that is not."""
    d = tuple(config.durations)
    if len(d) != len(phases) - 1 or min(d, default=0) < 1:
        raise ValueError(f"durations needs {len(phases) - 1} positive step counts (one per "
                         f"phase {tuple(phases[:-1])}), got {config.durations}")
    for f in positive:
        if not getattr(config, f) > 0:
            raise ValueError(f"{f} must be positive, got {getattr(config, f)}")
    for f in nonnegative:
        if not getattr(config, f) >= 0:
            raise ValueError(f"{f} must be >= 0, got {getattr(config, f)}")


def _smoothstep(u):
    return u * u * (3.0 - 2.0 * u)


def pad_tip_below_ee(env: Env) -> float:
    """Distance (m) from the ee site to the finger-pad tips along the approach axis (ee x).

    Read from the model at the reference posture: with the gripper pointing down, the
    closed pads' bottom faces are this far below the ee site.
    """
    m = env.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    site = env.ee_site[0]
    rot = d.site_xmat[site].reshape(3, 3)
    tips = []
    for pad in env.info.gripper_pads[0]:
        g = m.geom(pad).id
        grot = d.geom_xmat[g].reshape(3, 3)
        # the pad box's farthest extent along the site's x axis
        ext = np.abs(grot.T @ rot[:, 0]) @ m.geom_size[g]
        tips.append(float(rot[:, 0] @ (d.geom_xpos[g] - d.site_xpos[site]) + ext))
    return max(tips)


def make_bimanual_waypoint_expert(
    env: Env,
    plan: Callable[[State], tuple[jax.Array, jax.Array]],
    durations: tuple[int, ...],
    ik_iterations: int = 10,
    phase_names: tuple[str, ...] | None = None,
) -> Expert:
    """A waypoint expert that drives both arms on a shared segment timing (joint actions).

    Args:
      env: the environment (``action="joint"``).
      plan: ``plan(state) -> (waypoints [K - 1, 2, 10], active [2] bool)``, pure and
        traceable: each arm's waypoints after its start pose (``K - 1 == len(durations)``)
        and which arms act. An inactive arm's rows are ignored.
      durations: control steps of each segment (positive ints).
      ik_iterations: DLS iterations per control step (warm-started).
      phase_names: optional names of the segments plus the final hold (for messages).

    Returns:
      :class:`Expert` with ``init(state) -> WaypointState`` and
      ``act(expert_state, state) -> (expert_state, action [2 * (n_arm + 1)])``.
    """
    if env.config.action != "joint":
        raise ValueError(f"the {env.scene.name} expert emits joint actions; env action is "
                         f"{env.config.action!r} (build the env with action='joint')")
    durations = tuple(int(d) for d in durations)
    if not durations or min(durations) < 1:
        raise ValueError(f"durations must be positive step counts, got {durations}")
    if phase_names is not None and len(phase_names) != len(durations) + 1:
        raise ValueError(f"phase_names needs {len(durations) + 1} names, got {phase_names}")
    ik = make_ik(env.mj_model, env.info, iterations=ik_iterations)
    fk = make_ee_fk(env.mj_model, env.info)
    arm_qadr = jnp.asarray(env.arm_qadr)  # [2, n_arm]
    home_open = env.info.gripper_opening(jnp.asarray(env.home_qpos)[env.grip_qadr])  # [2]
    times = np.concatenate([[0], np.cumsum(durations)]).astype(np.int32)  # [K]
    durs = np.asarray(durations, np.float32)
    n_seg = len(durations)

    def init(state: State) -> WaypointState:
        """Plan the waypoints of one episode from its initial ``state``."""
        q = state.data.qpos
        wps, active = plan(state)
        if wps.shape != (n_seg, 2, 10):
            raise ValueError(f"plan must return waypoints [{n_seg}, 2, 10], got {wps.shape}")
        pos, mat = fk(q)  # [2, 3], [2, 3, 3]
        rot6 = jax.vmap(mat_to_rot6d)(mat)  # [2, 6]
        start = jnp.concatenate([pos, rot6, home_open[:, None]], axis=-1)  # [2, 10]
        waypoints = jnp.concatenate([start[None], wps.astype(start.dtype)]).astype(jnp.float32)
        return WaypointState(t=jnp.zeros((), jnp.int32), q=q, waypoints=waypoints,
                             active=jnp.asarray(active, bool).reshape(2))

    def phase(es: WaypointState) -> jax.Array:
        """[] int32 index of the segment the next step is in (``len(durations)``: hold)."""
        return jnp.searchsorted(jnp.asarray(times[1:]), es.t + 1, side="left").astype(jnp.int32)

    def target(es: WaypointState) -> jax.Array:
        """Both arms' targets [2, 10] for step ``t``: reached at the end of the step."""
        s = es.t + 1
        seg = jnp.clip(jnp.searchsorted(jnp.asarray(times), s, side="right") - 1, 0, n_seg - 1)
        u = jnp.clip((s - jnp.asarray(times)[seg]).astype(jnp.float32) / jnp.asarray(durs)[seg],
                     0.0, 1.0)
        a, b = es.waypoints[seg], es.waypoints[seg + 1]
        return a + _smoothstep(u) * (b - a)

    def act(es: WaypointState, state: State) -> tuple[WaypointState, jax.Array]:
        """One control step: (next expert state, joint action [2 * (n_arm + 1)])."""
        del state  # open loop after init
        tgt = target(es)  # [2, 10]
        q = ik(es.q, tgt[:, :9], active=es.active)
        opening = jnp.where(es.active, tgt[:, 9], home_open)  # [2]
        action = jnp.concatenate([q[arm_qadr], opening[:, None]], axis=-1).reshape(-1)
        return es.replace(t=es.t + 1, q=q), action

    return Expert(init=init, act=act, horizon=int(times[-1]), phase=phase)


def make_waypoint_expert(
    env: Env,
    plan: Callable[[State], tuple[jax.Array, jax.Array]],
    durations: tuple[int, ...],
    ik_iterations: int = 10,
    phase_names: tuple[str, ...] | None = None,
) -> Expert:
    """A one-arm waypoint expert for ``env`` (joint action mode); the other arm holds still.

    Args:
      env: the environment (``action="joint"``).
      plan: ``plan(state) -> (waypoints [K - 1, 10], left [] bool)``, pure and traceable:
        the acting arm's waypoints after its start pose (``K - 1 == len(durations)``) and
        whether the left arm acts.
      durations, ik_iterations, phase_names: as for :func:`make_bimanual_waypoint_expert`.

    Returns:
      :class:`Expert`, as :func:`make_bimanual_waypoint_expert`.
    """
    n_seg = len(durations)

    def plan2(state: State) -> tuple[jax.Array, jax.Array]:
        wps, left = plan(state)
        if wps.shape != (n_seg, 10):
            raise ValueError(f"plan must return waypoints [{n_seg}, 10], got {wps.shape}")
        left = jnp.asarray(left, bool)
        both = jnp.stack([wps, wps], axis=1)  # the idle arm's rows are ignored
        return both, jnp.stack([left, ~left])

    return make_bimanual_waypoint_expert(env, plan2, durations, ik_iterations, phase_names)
