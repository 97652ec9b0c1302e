"""Scripted expert for ``drumstick_hook``: a pure-JAX, vmappable waypoint script.

The arm on the stick's side (the left arm when the stick's y > 0) does, one phase per
segment:

    0 approach  home pose -> ``pregrasp_height`` above the grasp point, gripper opening and
                turning to point down with its jaws across the stick
    1 descend   -> the grasp point: the stick's centre of mass held between the pads'
                lower ends (``grasp_depth`` beyond the ee along the approach axis)
    2 close     opening -> 0 (the grasp holds by friction only)
    3 settle    hold still while the grip force builds
    4 lift      -> the stick's centre ``lift_height`` above the table, the gripper pitched
                up to ``pitch`` from straight down (the stick turns about its own axis)
    5 transfer  -> the stick's centre ``hover`` above its hanging pose on the rack
    6 lower     -> the stick's centre ``release_clearance`` above its resting height on
                the pegs
    7 release   opening -> 1 (the stick drops onto the pegs)
    8 retreat   back along the approach axis by ``retreat`` and up by ``retreat_up``
    9 hold      (to the end of the episode)

Orientations a 5-DoF arm reaches exactly: with the gripper pointing down any yaw of the
jaws is reachable (the wrist roll turns it), so the grasp rotation puts the gripper's z
axis along the stick. From the lift on, the gripper's approach axis lies in the arm's
vertical plane through the stick's centre, pitched ``pitch`` from straight down, and its
z axis (the stick) is horizontal and normal to that plane. At the rack the stick lies
across both pegs with its centre of mass between them.

Perturbed episodes (``info["perturbed"]``, drawn by the scene's ``asymmetric_quality``):
the same script with the hanging pose moved ``short`` back along the arm's plane towards
the robot, so the stick is lowered and released short of the rack and falls to the table
(a failed demonstration). The choice is a ``jnp.where`` on the flag.

Mirror equivariance: the plan computes the left arm's waypoints from the stick's pose
mirrored into the left half (when it lies on the right), then mirrors positions
(``M p``) and rotations (``M R L``) back; the arm is chosen by the sign of the stick's y
(never 0). So from ``env.mirror_state(s0)`` the script issues ``env.action_symmetry`` of
its actions from ``s0`` (see :mod:`equibim_jax.experts._waypoints`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from equibim_jax.experts._waypoints import check_expert_config, Expert, make_waypoint_expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.drumstick_hook import DrumstickHook

__all__ = ["DrumstickExpertConfig", "PHASES", "make_expert", "hang_rotation", "grasp_rotation"]

PHASES = ("approach", "descend", "close", "settle", "lift", "transfer", "lower", "release",
          "retreat", "hold")

_M = np.diag([1.0, -1.0, 1.0]).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class DrumstickExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of the segments approach, descend, close, settle, lift,
        transfer, lower, release, retreat (one per phase except "hold").
      grasp_depth: distance (m) along the approach axis from the ee to the stick's axis
        at the grasp (the pads reach 0.025 m beyond the ee, so this keeps their tips off
        the table).
      pregrasp_height: ee height above the grasp point for the approach (m).
      lift_height: height of the stick's centre after the lift (m).
      pitch: angle (rad) of the approach axis from straight down, from the lift on.
      hover: height of the stick's centre above its release point at the end of the
        transfer (m).
      release_clearance: height of the stick's axis above its resting height on the pegs
        at the release (m).
      retreat, retreat_up: the ee moves back along the approach axis by ``retreat`` and up
        by ``retreat_up`` after the release (m).
      short: how far short of the rack (back along the arm's plane, m) a perturbed
        episode releases the stick.
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (40, 20, 12, 8, 50, 50, 25, 12, 25)
    grasp_depth: float = 0.018
    pregrasp_height: float = 0.05
    lift_height: float = 0.18
    pitch: float = math.radians(100.0)
    hover: float = 0.05
    release_clearance: float = 0.003
    retreat: float = 0.06
    retreat_up: float = 0.03
    short: float = 0.16
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES,
                            positive=("pregrasp_height", "lift_height", "hover", "retreat", "short"),
                            nonnegative=("release_clearance", "retreat_up", "grasp_depth"))
        if not 0.0 <= self.pitch < math.pi:
            raise ValueError(f"pitch must be in [0, pi) rad, got {self.pitch}")

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))

    @property
    def release_end(self) -> int:
        """Step at which the release segment ends (the gripper is fully open)."""
        return int(sum(self.durations[:8]))


def _frame(x, z):
    """Rotation matrix [3, 3] with columns x, z cross x, z (x, z orthonormal [3])."""
    return jnp.stack([x, jnp.cross(z, x), z], axis=-1)


def grasp_rotation(axis: jax.Array) -> jax.Array:
    """Left-arm gripper rotation [3, 3] pointing straight down with its z axis along the
    horizontal part of the stick ``axis`` [3] (its jaws then close across the stick)."""
    d = axis * jnp.asarray([1.0, 1.0, 0.0], axis.dtype)
    d = d / jnp.linalg.norm(d)
    return _frame(jnp.asarray([0.0, 0.0, -1.0], axis.dtype), d)


def hang_rotation(direction: jax.Array, pitch) -> jax.Array:
    """Left-arm gripper rotation [3, 3] whose approach axis lies in the vertical plane of
    the horizontal unit ``direction`` [3] (from the arm's pan axis), ``pitch`` rad from
    straight down, and whose z axis is horizontal, normal to that plane (the left arm's
    pan direction turned +90 deg about z): the pose reached with the wrist roll at -90 deg."""
    p = direction
    up = jnp.asarray([0.0, 0.0, 1.0], p.dtype)
    x = jnp.sin(pitch) * p - jnp.cos(pitch) * up
    z = jnp.stack([-p[1], p[0], jnp.zeros_like(p[0])])
    return _frame(x, z)


def make_expert(env: Env, config: DrumstickExpertConfig = DrumstickExpertConfig()) -> Expert:
    """The scripted expert of ``drumstick_hook`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`DrumstickHook` scene and ``action="joint"``.
      config: :class:`DrumstickExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts.Expert`: ``init(state)``, ``act(expert_state, state) ->
      (expert_state, action [12])``, pure and vmappable.
    """
    scene = env.scene
    if not isinstance(scene, DrumstickHook):
        raise ValueError(f"the drumstick_hook expert needs a DrumstickHook scene, got "
                         f"{type(scene).__name__}")
    m = env.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    # the left arm's pan axis (x, y); the arm's vertical plane passes through it
    base_xy = np.asarray(d.xpos[m.body(f"{env.info.sides[0]}_shoulder").id][:2], np.float32)
    # The stick's axis in the left gripper's frame at the grasp: grasp_depth along the
    # approach (x), and pressed against the fixed jaw: an object of width w is held
    # w / 2 - 0.015 m from the ee site along the gripper's y (robots module docstring).
    off_local = np.asarray([config.grasp_depth, scene.stick_radius - 0.015, 0.0], np.float32)
    hang_c = np.asarray([scene.hook_x, 0.0, env.info.table_height + scene.hang_height
                         + config.release_clearance], np.float32)
    z_lift = env.info.table_height + config.lift_height
    M = jnp.asarray(_M)

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [9, 10] after the start pose, and whether the left arm acts."""
        origin, axis = scene.stick_from_qpos(state.data.qpos, env)
        left = origin[1] > 0.0
        # the stick mirrored into the left half: the script is planned for the left arm
        o = jnp.where(left, origin, M @ origin)
        ax = jnp.where(left, axis, M @ axis)
        com = o + scene.com_offset * ax
        base = jnp.asarray(base_xy, o.dtype)
        flat = lambda v: jnp.concatenate([v, jnp.zeros((1,), v.dtype)])
        unit = lambda v: v / jnp.linalg.norm(v)

        r_grasp = grasp_rotation(ax)
        c_lift = jnp.stack([com[0], com[1], jnp.asarray(z_lift, o.dtype)])
        r_lift = hang_rotation(flat(unit(c_lift[:2] - base)), config.pitch)
        c_hang = jnp.asarray(hang_c, o.dtype)
        p_hang = flat(unit(c_hang[:2] - base))
        c_hang = c_hang - jnp.where(state.info["perturbed"], config.short, 0.0) * p_hang
        r_hang = hang_rotation(p_hang, config.pitch)
        off = jnp.asarray(off_local, o.dtype)
        ee = lambda c, r: c - r @ off  # ee site holding the stick's centre of mass at c
        up = jnp.asarray([0.0, 0.0, 1.0], o.dtype)

        grasp = ee(com, r_grasp)
        hang = ee(c_hang, r_hang)
        pos = jnp.stack([
            grasp + config.pregrasp_height * up,                      # approach
            grasp,                                                    # descend
            grasp,                                                    # close
            grasp,                                                    # settle
            ee(c_lift, r_lift),                                       # lift
            hang + config.hover * up,                                 # transfer
            hang,                                                     # lower
            hang,                                                     # release
            hang - config.retreat * r_hang[:, 0] + config.retreat_up * up,  # retreat
        ])
        rots = jnp.stack([r_grasp] * 4 + [r_lift] + [r_hang] * 4)
        # back to the stick's side: positions reflect, rotations map R -> M R L (L = M)
        pos = jnp.where(left, pos, pos @ M)
        rots = jnp.where(left, rots, M @ rots @ M)
        rot6 = jnp.concatenate([rots[:, :, 0], rots[:, :, 1]], axis=-1)
        opening = jnp.array([1, 1, 0, 0, 0, 0, 0, 1, 1], jnp.float32)
        wps = jnp.concatenate([pos, rot6, opening[:, None].astype(pos.dtype)], axis=-1)
        return wps.astype(jnp.float32), left

    return make_waypoint_expert(env, plan, config.durations, config.ik_iterations, PHASES)
