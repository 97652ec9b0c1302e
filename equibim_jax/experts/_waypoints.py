"""One-arm waypoint scripts: the machinery shared by the press-type experts
(``click_bell``, ``press_stapler``).

A task's expert supplies ``plan(state) -> (waypoints [K - 1, 10], left [] bool)``: the
active arm's end-effector waypoints (position 3, 6D rotation 6, normalised gripper
opening 1) after its start pose, and whether the left arm acts. This module prepends the
active arm's own start pose (from forward kinematics of the initial ``qpos``) and turns
the waypoints into a pure, vmappable :class:`~equibim_jax.experts.Expert`:

* segment ``k`` moves from waypoint ``k`` to ``k + 1`` in ``durations[k]`` control steps
  along a smoothstep (zero velocity at both ends); after the last segment the target
  holds the last waypoint;
* each control step, damped-least-squares IK (warm-started from the previous step's
  solution) turns the active arm's target into joint targets; the idle arm holds the pose
  of its home joints and its home gripper opening;
* the phase is a pure function of the step counter, so nothing branches on traced values,
  and the script is open loop after ``init``.

Mirror equivariance follows as for ``place_empty_cup`` (see
``equibim_jax/experts/place_empty_cup.py``): if ``plan`` is mirror-covariant (positions
mirror as points, the arm flips with the side, rotations ``R`` map to ``M R L``), the
actions from ``env.mirror_state(s0)`` are ``env.action_symmetry`` of the actions from
``s0``, to float32 round-off.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from equibim_jax.experts.place_empty_cup import Expert
from equibim_jax.sim.env import Env, State
from equibim_jax.sim.ik import make_ee_fk, make_ik, mat_to_rot6d

__all__ = ["R_DOWN_6D", "WaypointState", "make_waypoint_expert", "pad_tip_below_ee"]

R_DOWN_6D = np.array([0.0, 0.0, -1.0, 0.0, 1.0, 0.0], np.float32)
"""Gripper pointing straight down (ee x = -z), closing along world y (ee y = +y). For robot
A's ee frames ``M R L = R`` for this rotation, so it is the same for both arms and its own
mirror image."""


@struct.dataclass
class WaypointState:
    """Expert state of one environment (a pytree).

    Attributes:
      t: [] int32 control step.
      q: [nq] last IK solution (the warm start of the next solve).
      waypoints: [K, 10] active-arm waypoints: ee position (3), 6D rotation (6), opening (1);
        row 0 is the start pose.
      left: [] bool, whether the left arm is the active one.
      rest_opening: [] float32, the idle arm's gripper opening (its home opening).
    """

    t: jax.Array
    q: jax.Array
    waypoints: jax.Array
    left: jax.Array
    rest_opening: jax.Array


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


def make_waypoint_expert(
    env: Env,
    plan: Callable[[State], tuple[jax.Array, jax.Array]],
    durations: tuple[int, ...],
    ik_iterations: int = 10,
    phase_names: tuple[str, ...] | None = None,
) -> Expert:
    """A one-arm waypoint expert for ``env`` (joint action mode).

    Args:
      env: the environment (``action="joint"``).
      plan: ``plan(state) -> (waypoints [K - 1, 10], left [] bool)``, pure and traceable;
        the waypoints after the start pose, ``K - 1 == len(durations)``.
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
        wps, left = plan(state)
        if wps.shape != (n_seg, 10):
            raise ValueError(f"plan must return waypoints [{n_seg}, 10], got {wps.shape}")
        pos, mat = fk(q)  # [2, 3], [2, 3, 3]
        start_l = jnp.concatenate([pos[0], mat_to_rot6d(mat[0]), home_open[0:1]])
        start_r = jnp.concatenate([pos[1], mat_to_rot6d(mat[1]), home_open[1:2]])
        start = jnp.where(left, start_l, start_r)
        waypoints = jnp.concatenate([start[None], wps]).astype(jnp.float32)
        return WaypointState(
            t=jnp.zeros((), jnp.int32), q=q, waypoints=waypoints, left=left,
            rest_opening=jnp.where(left, home_open[1], home_open[0]).astype(jnp.float32),
        )

    def phase(es: WaypointState) -> jax.Array:
        """[] int32 index of the segment the next step is in (``len(durations)``: hold)."""
        return jnp.searchsorted(jnp.asarray(times[1:]), es.t + 1, side="left").astype(jnp.int32)

    def target(es: WaypointState) -> jax.Array:
        """Active-arm target [10] for step ``t``: reached at the end of the step."""
        s = es.t + 1
        seg = jnp.clip(jnp.searchsorted(jnp.asarray(times), s, side="right") - 1, 0, n_seg - 1)
        u = jnp.clip((s - jnp.asarray(times)[seg]).astype(jnp.float32) / jnp.asarray(durs)[seg],
                     0.0, 1.0)
        a, b = es.waypoints[seg], es.waypoints[seg + 1]
        return a + _smoothstep(u) * (b - a)

    def act(es: WaypointState, state: State) -> tuple[WaypointState, jax.Array]:
        """One control step: (next expert state, joint action [2 * (n_arm + 1)])."""
        del state  # open loop after init
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

    return Expert(init=init, act=act, horizon=int(times[-1]), phase=phase)
