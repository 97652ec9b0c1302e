"""Scripted expert for ``chicken_hook``: a two-arm, pure-JAX, vmappable waypoint script.

Each arm takes the wing knob on its own side (the left arm the knob with the larger y).
Both arms move on one shared segment timing, one phase per segment:

    0  approach     home -> ``pregrasp`` back along the approach axis from the grasp pose,
                    opening
    1  descend      -> the grasp pose (the knob between the open jaws, ``clearance`` from
                    the fixed jaw's face)
    2  close        both close (friction grasp of the vertical knobs)
    3  settle       hold while the grip force builds
    4  lift         carry the toy up, its centre onto the mirror plane, with the loop's
                    centre ``thread_drop`` below the peg's tip (the loop is still behind it)
    5  thread       forward along +x until the toy's centre is ``hang_back`` in front of
                    the post: the peg passes through the loop
    6  lower        down until the loop's top corner rests on the peg (``preload`` lower)
    7  release      both open
    8  sidestep     move each gripper's fixed jaw ``sidestep`` away from its knob
    9  retreat      back ``retreat`` along the approach axis (up and towards the robot)
    10 hold         (to the end of the episode)

The toy is carried without turning it: the two knobs are translated by the same vector, so
its initial yaw is kept (the loop's hole still faces the peg for the yaws drawn).

Grasp pose
----------
Robot B's 5-DoF arm lies in the vertical plane through its shoulder pan axis, so its
gripper points along ``a = (cos(p) r, -sin(p))`` with ``r`` the horizontal direction of that
plane and ``p`` = ``pitch_deg`` below horizontal; with zero wrist roll the jaws close along
``y = z x r`` (horizontal). The ee site is ``ee_offset`` off the plane along ``y`` (on the
left arm, ``-ee_offset`` on the right), so ``r`` is solved from the target position
(:func:`aim`) and every waypoint is a pose the arm reaches exactly. The knobs are vertical
capsules, so the jaws (vertical planes) squeeze them whatever ``r``.

Perturbed episodes
------------------
When ``info["perturbed"]`` is True (``asymmetric_quality``), the script stops the thread
``short`` in front of the peg's tip (chosen with ``jnp.where``): the loop never goes onto
the peg and the toy drops onto the table when released.

The plan reads only the toy's initial pose (reflected by the mirror, with the knobs assigned
to arms by their y) and ``perturbed`` (kept by the mirror), and :func:`aim` is covariant
(``R -> M R diag(1, -1, 1)`` with the arms swapped), so with the mirror-equivariant
machinery of :mod:`equibim_jax.experts._waypoints` the expert is mirror-equivariant. It is
open loop after ``init``.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax.experts._waypoints import check_expert_config, Expert, make_bimanual_waypoint_expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.chicken_hook import ChickenHook

__all__ = ["ChickenHookExpertConfig", "PHASES", "aim", "make_expert"]

PHASES = ("approach", "descend", "close", "settle", "lift", "thread", "lower", "release",
          "sidestep", "retreat", "hold")


@dataclasses.dataclass(frozen=True)
class ChickenHookExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of each phase but the final hold (see :data:`PHASES`).
      pitch_deg: the grippers' approach axis, degrees below horizontal.
      pregrasp: distance back along the approach axis before the descent (m).
      clearance: gap between a knob and the fixed jaw's face at the grasp pose (m).
      thread_drop: the loop's centre below the peg's axis at its tip while threading (m).
      hang_back: the toy's centre this far in front of the post's axis at the hang (m).
      preload: how much lower than the resting hang the toy is lowered before release (m).
      sidestep: how far the fixed jaws move away from the knobs after the release (m).
      retreat: how far back along the approach axis the grippers retreat (m).
      short: perturbed episodes stop the toy's centre this far in front of the peg's tip (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (40, 20, 12, 8, 40, 45, 25, 12, 10, 25)
    pitch_deg: float = 50.0
    pregrasp: float = 0.05
    clearance: float = 0.003
    thread_drop: float = 0.003
    hang_back: float = 0.06
    preload: float = 0.004
    sidestep: float = 0.012
    retreat: float = 0.06
    short: float = 0.05
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES,
                            positive=("pregrasp", "hang_back", "sidestep", "retreat", "short"),
                            nonnegative=("clearance", "preload"))
        if not 0.0 < self.pitch_deg <= 90.0:
            raise ValueError(f"pitch_deg must be in (0, 90], got {self.pitch_deg}")

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))

    @property
    def release_end(self) -> int:
        """Step at which the release segment ends (both grippers open)."""
        return int(sum(self.durations[: PHASES.index("release") + 1]))


def aim(target: jax.Array, base_xy: jax.Array, sign: jax.Array, ee_offset: float,
        pitch: float) -> jax.Array:
    """Reachable gripper rotation for an ee ``target`` of a robot-B arm.

    Args:
      target: ee position [3].
      base_xy: the arm's shoulder pan axis (x, y) [2].
      sign: [] +1 for the left arm, -1 for the right (the ee site sits ``sign * ee_offset``
        off the arm's plane along the closing axis).
      ee_offset: |y| of the ee site in the gripper frame (m).
      pitch: approach angle below horizontal (rad).

    Returns:
      6D rotation [6]: the approach axis (gripper x) then the closing axis (gripper y).
    """
    d = target[:2] - base_xy
    rho = jnp.sqrt(jnp.maximum(jnp.sum(d * d) - ee_offset**2, 1e-8))
    psi = jnp.arctan2(d[1], d[0]) - jnp.arctan2(sign * ee_offset, rho)
    c, s = jnp.cos(psi), jnp.sin(psi)
    approach = jnp.stack([math.cos(pitch) * c, math.cos(pitch) * s, -math.sin(pitch) * jnp.ones_like(c)])
    closing = jnp.stack([-s, c, jnp.zeros_like(c)])
    return jnp.concatenate([approach, closing])


def make_expert(env: Env, config: ChickenHookExpertConfig = ChickenHookExpertConfig()) -> Expert:
    """The scripted expert of ``chicken_hook`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`ChickenHook` scene and ``action="joint"``.
      config: :class:`ChickenHookExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert`: ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [12])``, pure and vmappable.

    Raises:
      ValueError: not a ``ChickenHook`` scene, or a clearance that does not fit the knob in
        the open jaws.
    """
    scene = env.scene
    if not isinstance(scene, ChickenHook):
        raise ValueError(f"the chicken_hook expert needs a ChickenHook scene, got {type(scene).__name__}")
    m = env.mj_model
    info = env.info
    # the arms' pan axes, the ee site's offset off the arm plane and the fixed jaw's face
    base_xy = np.stack([m.body(f"{side}_shoulder").pos[:2] + m.body(f"{side}_base").pos[:2]
                        for side in info.sides]).astype(np.float32)  # [2, 2]
    ee_offset = float(abs(m.site(info.ee_sites[0]).pos[1]))
    fixed = m.geom(info.gripper_pads[0][0])
    fixed_face = float(abs(fixed.pos[1]) - fixed.size[1])  # |y| of the fixed jaw's face
    # the knob's centre sits ``knob_radius + clearance`` from the face, towards the site
    ee_shift = ee_offset + fixed_face - scene.knob_radius - config.clearance
    if config.clearance + 2 * scene.knob_radius > info.gripper_span - 0.005:
        raise ValueError(f"clearance {config.clearance} leaves no room for the {2 * scene.knob_radius} m "
                         f"knob in the {info.gripper_span} m open jaws")
    pitch = math.radians(config.pitch_deg)
    signs = jnp.asarray([1.0, -1.0], jnp.float32)
    c = config

    tip = scene.peg_tip
    z_thread = float(scene.peg_axis_height(tip[0]) - c.thread_drop - scene.ring_centre_z)
    x_hang = scene.hook_x - c.hang_back
    z_hang = float(scene.peg_axis_height(x_hang) - scene.loop_hang_drop - scene.ring_centre_z - c.preload)
    x_short = float(tip[0] - c.short)
    z0 = info.table_height

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [10, 2, 10] (row 0 of axis 1 the left arm) and active [2] (both)."""
        pos, _ = scene.toy_pose(state.data, env)
        knobs = scene.knob_positions(state.data, env)  # [2, 3], body +y knob first
        swap = knobs[0, 1] < knobs[1, 1]
        knobs = jnp.where(swap, knobs[::-1], knobs)  # the left arm's knob first
        x_end = jnp.where(state.info["perturbed"], x_short, x_hang)
        one = jnp.ones((), pos.dtype)
        centre = lambda x, z: jnp.stack([x * one, 0.0 * one, z0 + z * one])
        toy = jnp.stack([
            pos, pos, pos, pos,                       # approach .. settle
            centre(pos[0], z_thread),                 # lift
            centre(x_end, z_thread),                  # thread
            centre(x_end, z_hang),                    # lower
            centre(x_end, z_hang),                    # release
            centre(x_end, z_hang),                    # sidestep
            centre(x_end, z_hang),                    # retreat
        ])  # [10, 3]
        opening = jnp.asarray([1, 1, 0, 0, 0, 0, 0, 1, 1, 1], pos.dtype)
        n = toy.shape[0]

        def arm(k):
            sgn, base = signs[k], jnp.asarray(base_xy[k])
            knob = knobs[k][None] + (toy - pos[None])  # [10, 3]
            rot0 = jax.vmap(lambda p: aim(p, base, sgn, ee_offset, pitch))(knob)
            ee = knob + sgn * ee_shift * rot0[:, 3:6]
            rot = jax.vmap(lambda p: aim(p, base, sgn, ee_offset, pitch))(ee)
            app, close = rot[:, :3], rot[:, 3:6]
            back = jnp.zeros((n,), pos.dtype).at[0].set(c.pregrasp).at[9].set(c.retreat)
            side = jnp.zeros((n,), pos.dtype).at[8].set(c.sidestep).at[9].set(c.sidestep)
            ee = ee - back[:, None] * app - (sgn * side)[:, None] * close
            return jnp.concatenate([ee, rot, opening[:, None]], axis=-1)  # [10, 10]

        wps = jnp.stack([arm(0), arm(1)], axis=1)
        return wps.astype(jnp.float32), jnp.ones((2,), bool)

    return make_bimanual_waypoint_expert(env, plan, c.durations, c.ik_iterations, PHASES)
