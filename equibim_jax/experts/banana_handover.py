"""Scripted expert for ``banana_handover``: a two-arm, pure-JAX, vmappable waypoint script.

The *giver* is the arm on the banana's side (the left arm when the banana's y > 0), the
*receiver* the other one. Both arms move on one shared segment timing:

    0  approach     giver: home -> ``pregrasp_height`` above its grasp pose, opening and
                    turning to point down; receiver: home -> its waiting pose (``standoff``
                    back along its approach and ``rise`` above its grasp pose), opening
    1  descend      giver -> its grasp pose on the banana's middle
    2  close        giver closes (friction grasp)
    3  settle       hold while the grip force builds
    4  lift         giver lifts the banana straight up to the handover height
    5  transfer     giver carries it to the handover pose, turning it
    6  lower        receiver -> ``standoff`` back along its approach at the grasp height
    7  insert       receiver moves in: one jaw under the banana, one over it
    8  close2       receiver closes (both arms now hold the banana)
    9  settle2      hold
    10 give         giver opens
    11 back_off     giver moves its fixed jaw ``back_off`` away from the banana
    12 withdraw     giver rises ``withdraw_height``
    13 retreat      giver moves towards its own side and up
    14 hold         (to the end of the episode)

Grasps
------
The giver grips from above (ee x = -z, a pose the 5-DoF arms reach anywhere in their
workspace) across the banana's middle capsule, at ``giver_offset`` from its centre (0 by
default: at the centre of mass, so the banana does not turn in the grip while carried):
ee y = ``sigma R e_x`` with ``R`` the banana's rotation, ``e_x`` its body x axis (across the
middle capsule, towards the side its ends curve to) and ``sigma`` the arm's own side sign
(+1 left, -1 right), so the moving jaw is on the banana's +x side. The ee sits
``giver_above`` above the capsule's axis (the jaws' lower ends stay above the table) and,
before closing, ``giver_clearance`` towards the fixed jaw from where the pressed capsule
ends up; closing presses the capsule against the fixed jaw.

The receiver grips with a horizontal approach ``a`` at ``receiver_pan`` from the world x
axis (turned towards the mirror plane), which the 5-DoF arm reaches because ``a`` points
away from its base, and closing vertically (ee y = ``sigma z``: the moving jaw on top, the
fixed jaw under the banana). Its grasp point is ``receiver_reach`` from its base along
``a``, at height ``handover_z``. The giver brings the banana there turned so that ``a`` is
the banana's body x axis (across it) and the receiver's grasp point is ``receiver_offset``
from the banana's centre towards the receiver's side. A grasp across the banana between
horizontal jaws holds the banana's weight off its centre with the jaws' normal forces
(a top-down grasp off the centre would hold it by friction about the jaws' normal, where
MuJoCo's soft contacts let it creep).

Everything the plan computes is mirror-covariant: positions reflect as points, the
banana's rotation maps to ``M R M`` (its body reflection is ``diag(1, -1, 1)``), sides swap
and ``sigma R e_x`` / ``sigma z`` map to the other arm's ``M (.) L``. So with
:mod:`equibim_jax.experts._waypoints` the expert is mirror-equivariant. It reads the
banana's initial pose from ``qpos`` and ``info["perturbed"]``, and is open loop after
``init``.

Perturbed episodes (``info["perturbed"]``, see :mod:`equibim_jax.tasks._shifts`): the
giver opens during the transfer instead of after the receiver has closed, so the banana
drops to the table and the episode fails (chosen with ``jnp.where``).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from equibim_jax.experts._waypoints import check_expert_config, Expert, make_bimanual_waypoint_expert
from equibim_jax.sim.env import Env, State
from equibim_jax.tasks.banana_handover import BananaHandover

__all__ = ["BananaExpertConfig", "PHASES", "make_expert"]

PHASES = ("approach", "descend", "close", "settle", "lift", "transfer", "lower", "insert",
          "close2", "settle2", "give", "back_off", "withdraw", "retreat", "hold")


@dataclasses.dataclass(frozen=True)
class BananaExpertConfig:
    """Static parameters of the script (frozen, hashable).

    Attributes:
      durations: control steps of each phase but the final hold (see :data:`PHASES`).
      giver_offset: distance of the giver's grasp point from the middle capsule's centre,
        along it towards the giver's side (m); 0 grips the banana at its centre of mass.
      receiver_offset: distance of the receiver's grasp point from the centre, along the
        banana towards the receiver's side (m).
      giver_above: giver ee height above the capsule's axis (m).
      giver_clearance, receiver_clearance: gap between the fixed jaw and the capsule
        before a grasp closes (m).
      pregrasp_height: giver ee height above its grasp pose for the approach (m).
      receiver_pan: horizontal angle (rad) between the receiver's approach and the world
        x axis, turned towards the mirror plane.
      receiver_reach: horizontal distance from the receiver's base to its grasp point (m).
      handover_z: height of the banana's axis at the handover (m).
      standoff: how far back along its approach the receiver waits before moving in (m).
      rise: how much higher than its grasp pose the receiver waits during the transfer (m).
      back_off: how far the giver moves its fixed jaw away from the banana after opening (m).
      withdraw_height: how far the giver then rises (m).
      retreat: the giver's last move, towards its own side and up (m).
      ik_iterations: DLS iterations per control step (warm-started).
    """

    durations: tuple[int, ...] = (50, 25, 15, 10, 25, 50, 20, 25, 15, 10, 12, 8, 15, 25)
    giver_offset: float = 0.0
    receiver_offset: float = 0.034
    giver_above: float = 0.016
    giver_clearance: float = 0.007
    receiver_clearance: float = 0.003
    pregrasp_height: float = 0.05
    receiver_pan: float = 1.0471975511965976  # 60 degrees
    receiver_reach: float = 0.24
    handover_z: float = 0.07
    standoff: float = 0.05
    rise: float = 0.05
    back_off: float = 0.008
    withdraw_height: float = 0.025
    retreat: tuple[float, float] = (0.07, 0.02)
    ik_iterations: int = 10

    def __post_init__(self):
        check_expert_config(self, PHASES,
                            positive=("pregrasp_height", "receiver_reach", "handover_z", "standoff", "rise",
                                      "back_off", "withdraw_height"),
                            nonnegative=("giver_clearance", "receiver_clearance"))

    @property
    def horizon(self) -> int:
        """Steps of the scripted part (sum of ``durations``)."""
        return int(sum(self.durations))

    def phase_end(self, name: str) -> int:
        """Control step at which phase ``name`` ends."""
        return int(sum(self.durations[: PHASES.index(name) + 1]))


def make_expert(env: Env, config: BananaExpertConfig = BananaExpertConfig()) -> Expert:
    """The scripted expert of ``banana_handover`` for ``env`` (joint action mode).

    Args:
      env: an env built with a :class:`BananaHandover` scene and ``action="joint"``.
      config: :class:`BananaExpertConfig`.

    Returns:
      :class:`~equibim_jax.experts._waypoints.Expert`: ``init(state)`` and
      ``act(expert_state, state) -> (expert_state, action [12])``, pure and vmappable.

    Raises:
      ValueError: not a ``BananaHandover`` scene, grasp points off the middle capsule or
        so close that the two grippers' jaws overlap, or a grasp whose jaws would not
        straddle the banana or would reach the table.
    """
    scene = env.scene
    if not isinstance(scene, BananaHandover):
        raise ValueError(f"the banana_handover expert needs a BananaHandover scene, got "
                         f"{type(scene).__name__}")
    c = config
    m = env.mj_model
    # jaw half sizes: along the approach (ee x), across (ee y), along ee z
    jaw_len, _, jaw_w = (float(v) for v in m.geom_size[m.geom(env.info.gripper_pads[0][0]).id])
    reach = scene.mid_half + 1e-9
    if (abs(c.giver_offset) + jaw_w > reach or abs(c.receiver_offset) + jaw_w > reach
            or c.giver_offset + c.receiver_offset < 2 * jaw_w + 0.002):
        raise ValueError(
            f"giver_offset={c.giver_offset} and receiver_offset={c.receiver_offset} must keep both "
            f"grippers' jaws ({2 * jaw_w:.3f} m wide along the banana) on the middle capsule "
            f"(within {scene.mid_half} m of its centre) and at least 2 mm apart")
    if not 0.0 <= c.giver_above < jaw_len - scene.radius / 2:
        raise ValueError(f"giver_above must keep the capsule's axis between the jaws (0 <= "
                         f"giver_above < {jaw_len - scene.radius / 2:.4f}), got {c.giver_above}")
    if jaw_len - c.giver_above > scene.radius:
        raise ValueError(f"giver_above={c.giver_above} puts the jaws' lower ends "
                         f"{jaw_len - c.giver_above:.3f} m below the capsule's axis at the pick: "
                         f"into the table (at most the radius, {scene.radius})")
    gap = float(env.info.gripper_span)
    for f in ("giver_clearance", "receiver_clearance"):
        if not 2 * scene.radius + getattr(c, f) < gap:
            raise ValueError(f"{f}={getattr(c, f)} leaves no room for the {2 * scene.radius} m "
                             f"thick banana between the open jaws ({gap} m apart)")
    # The ee site's distance from the fixed jaw's face (gripper frame y, left arm).
    fixed = m.geom(env.info.gripper_pads[0][0]).id
    fixed_face = float(m.site_pos[env.ee_site[0]][1] - (m.geom_pos[fixed][1] + m.geom_size[fixed][1]))
    # ee offset from the capsule's axis along the moving jaw's direction once a grasp
    # holds (the capsule pressed on the fixed jaw) and before it closes
    hold = -(scene.radius - fixed_face)
    g_pre, r_pre = hold - c.giver_clearance, hold - c.receiver_clearance
    # |y| of the arms' bases (the parent body of the first arm joint's body)
    pan_body = m.jnt_bodyid[m.joint(env.info.arm_joints[0][0]).id]
    base_y = abs(float(m.body_pos[m.body_parentid[pan_body]][1]))
    cp, sp = math.cos(c.receiver_pan), math.sin(c.receiver_pan)
    dtype = jnp.float32

    def plan(state: State) -> tuple[jax.Array, jax.Array]:
        """Waypoints [14, 2, 10] (row 0 of axis 1 the left arm) and active [2] (both)."""
        p0, quat = scene.pose_from_qpos(state.data.qpos, env)
        p0 = p0.astype(dtype)
        yaw = 2.0 * jnp.arctan2(quat[3], quat[0]).astype(dtype)  # the banana lies flat
        s = jnp.where(p0[1] > 0.0, 1.0, -1.0).astype(dtype)  # the giver's side
        ex = jnp.stack([jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw)])  # body x (world)
        ey = jnp.stack([-jnp.sin(yaw), jnp.cos(yaw), jnp.zeros_like(yaw)])  # body y (world)
        one = jnp.ones((), dtype)
        zero = jnp.zeros((), dtype)
        up = jnp.asarray([0.0, 0.0, 1.0], dtype)
        down = -up
        n = len(c.durations)

        # ---- the handover: the receiver's horizontal approach, its grasp point, and the
        # banana's pose, turned so that the approach is across the banana (its body x)
        app = jnp.stack([cp * one, s * sp, zero])  # receiver's approach = banana body x
        hy = jnp.stack([-s * sp, cp * one, zero])  # banana body y at the handover
        r_axis = jnp.stack([zero, -s * base_y, c.handover_z * one]) + c.receiver_reach * app
        centre = r_axis + s * c.receiver_offset * hy  # banana centre (on its axis)

        # ---- giver: grasp on the table, lift, carry to the handover, let go, leave
        grasp = p0 + s * c.giver_offset * ey + g_pre * ex + c.giver_above * up
        held = grasp.at[2].set(c.handover_z + c.giver_above)  # lifted straight up
        g_hand = centre + s * c.giver_offset * hy + hold * app + c.giver_above * up
        g_back = g_hand - c.back_off * app
        g_up = g_back + c.withdraw_height * up
        g_away = g_up + s * c.retreat[0] * jnp.asarray([0.0, 1.0, 0.0], dtype) + c.retreat[1] * up
        g_pos = jnp.stack([
            grasp + c.pregrasp_height * up,  # 0 approach
            grasp, grasp, grasp,             # 1 descend, 2 close, 3 settle
            held,                            # 4 lift
            g_hand, g_hand, g_hand,          # 5 transfer, 6 lower, 7 insert
            g_hand, g_hand,                  # 8 close2, 9 settle2
            g_hand,                          # 10 give
            g_back,                          # 11 back_off
            g_up,                            # 12 withdraw
            g_away,                          # 13 retreat
        ])
        # pointing down, closing across the banana: ee y = own side sign * banana body x
        g_rot = jnp.stack([jnp.concatenate([down, s * (ex if k < 5 else app)]) for k in range(n)])
        g_open_ok = jnp.asarray([1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1], dtype)
        g_open_bad = jnp.asarray([1, 1, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1], dtype)  # drops it
        perturbed = jnp.asarray(state.info.get("perturbed", False), bool)
        g_open = jnp.where(perturbed, g_open_bad, g_open_ok)

        # ---- receiver: horizontal approach across the banana, closing vertically: ee y =
        # its own side sign (-s) * up, so the moving jaw is on top, the fixed jaw under it
        r_grasp = r_axis + r_pre * up
        r_low = r_grasp - c.standoff * app
        r_high = r_low + c.rise * up
        r_pos = jnp.stack([r_high] * 6 + [r_low] + [r_grasp] * (n - 7))
        r_rot = jnp.tile(jnp.concatenate([app, -s * up])[None], (n, 1))
        r_open = jnp.asarray([1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0], dtype)

        giver = jnp.concatenate([g_pos, g_rot, g_open[:, None]], axis=-1)  # [14, 10]
        recv = jnp.concatenate([r_pos, r_rot, r_open[:, None]], axis=-1)
        wps = jnp.where(s > 0, jnp.stack([giver, recv], axis=1), jnp.stack([recv, giver], axis=1))
        return wps.astype(jnp.float32), jnp.ones((2,), bool)

    return make_bimanual_waypoint_expert(env, plan, c.durations, c.ik_iterations, PHASES)
