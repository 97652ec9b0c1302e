"""The two bimanual robot models and their static metadata.

Robots
------
``robot_a``
    Two 6-DoF ViperX/ALOHA-like arms (waist, shoulder, elbow, forearm_roll, wrist_angle,
    wrist_rotate), each with a parallel-jaw gripper made of two slide-joint fingers with
    their own position actuators. Bases at (0, +-0.3, 0), reach about 0.65 m from the
    shoulder. Head camera ``head`` on the mirror plane at (-0.2, 0, 0.75), pitched 53 deg
    down (optical axis meets the table at x = 0.36), fovy 65. Wrist cameras ``wrist_left`` /
    ``wrist_right`` in the gripper bodies at (0.02, 0, 0.06) (gripper frame: behind and
    above the fingers), looking along the gripper's +x pitched 25 deg towards its -z, image
    x axis along the gripper's -y, fovy 85: they see the fingers and what is in front of
    them, and are mirror partners with a horizontal image flip. The paper's simulated
    (RoboTwin) tasks use this robot.
``robot_b``
    Two SO-101-style 5-DoF arms (shoulder_pan, shoulder_lift, elbow_flex, wrist_flex,
    wrist_roll), each with one moving jaw closing against a fixed jaw, as on the SO-101.
    The real jaw swings on a hinge; here it slides, so the pad faces stay parallel (a
    hinged box pad squeezed a 50 g box out of the grasp with the pyramidal cone). The ee
    site is the centre of a 3 cm object pressed against the fixed jaw; an object of width
    ``w`` is held ``w / 2 - 0.015`` m from the site along the gripper's y axis (towards
    the moving jaw). Bases at (0, +-0.2, 0), both facing +x, reach about 0.37 m from the
    shoulder. Top-down camera ``top`` at (0.2, 0, 0.7), image up = +x, fovy 60. The
    paper's real-world tasks use this robot.

Frame and mirror
----------------
x forward (away from the arms' base line), y to the robot's left, z up. The table top is
the plane z = 0 for both robots (the arms stand on it). The mirror plane is y = 0 for both
robots: ``Mirror.from_axis("y")``. The ``head`` / ``top`` cameras sit on the plane with their
image x axis along -y, so the mirror acts on their images as a horizontal flip. Robot A's
wrist cameras are a mirror pair: the mirror swaps the two views and flips each.

The right arm of each robot is the exact mirror of the left: all body frames are
axis-aligned at q = 0 and every offset is an exact decimal with y negated. The body-local
reflection for every robot body (and the end-effector sites) is ``diag(1, -1, 1)``, so an
end-effector orientation ``R`` mirrors to ``M R diag(1, -1, 1)``. Hinge axes are shared
(yaw about z, pitch about y, roll about x), so under the mirror yaw and roll joints flip
sign and pitch joints keep it; finger/jaw axes are mirrored, so they keep their sign (a
normalised gripper opening is mirror invariant).

Layout
------
For both robots the robot's own joints come first in qpos (and qvel), in the order
``left arm, left gripper, right arm, right gripper``; the actuators follow the same order.
Task objects added through :func:`robot_spec` come after them. Adding bodies with joints
to the spec keeps the ``home`` keyframe valid: MuJoCo pads a shorter keyframe qpos with
the new joints' ``qpos0``.

Collision bit scheme (contype / conaffinity)
--------------------------------------------
Two geoms collide when ``(contype_a & conaffinity_b) or (contype_b & conaffinity_a)``
(and they are not on the same or parent/child bodies).

========  ===  =======  ===========  ====================================================
group     bit  contype  conaffinity  geoms
========  ===  =======  ===========  ====================================================
TABLE     1    1        6            ``table`` (a plane at z = 0)
PAD       2    2        5            finger pads / jaws (boxes, condim 4, friction 1.5)
OBJECT    4    4        15           task objects (add them with these values)
PALM      8    8        4            gripper palms (boxes, condim 4, friction 1.5)
(none)    --   0        0            arm links, bases and all visual geoms
========  ===  =======  ===========  ====================================================

So objects collide with the table, pads, palms and each other; pads collide with the
table and objects; palms collide with objects only (a palm is never nearer the table than
its pads); gripper geoms never collide with each other (same arm or across arms); arm links
collide with nothing. In the bare robot model the only candidate pairs are the four
table-pad pairs (two pads per arm). Each task object geom adds one pair with the table,
4 with the pads, 2 with the palms and one per other object geom (on another body), so
keep object geoms few. Task code should build objects
with :data:`OBJECT_CONTYPE` / :data:`OBJECT_CONAFFINITY` (``**object_collision()``), use
capsules, spheres and boxes (no cylinder touching a box: MJX has no such collision), and
``condim`` 3 or 4. A static fixture (welded to the world) that objects rest on or hang
from but the grippers pass through can use ``contype=0, conaffinity=4``; one that the pads
should also touch uses ``contype=4, conaffinity=4``. Static fixtures never collide with
the table (both belong to the world body).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
from typing import Sequence

import jax.numpy as jnp
import mujoco
import numpy as np

from equibim_jax.symmetry import Mirror

__all__ = [
    "ASSET_DIR",
    "TABLE_BIT",
    "PAD_BIT",
    "OBJECT_BIT",
    "PALM_BIT",
    "OBJECT_CONTYPE",
    "OBJECT_CONAFFINITY",
    "TABLE_CONTYPE",
    "TABLE_CONAFFINITY",
    "PAD_CONTYPE",
    "PAD_CONAFFINITY",
    "PALM_CONTYPE",
    "PALM_CONAFFINITY",
    "SIDES",
    "RobotInfo",
    "robot_names",
    "robot_info",
    "robot_spec",
    "load_robot",
    "robot_mirror",
    "robot_xml_path",
    "object_collision",
    "joint_qpos_indices",
    "joint_dof_indices",
    "actuator_indices",
]

ASSET_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "assets")

# Collision groups (bits of contype / conaffinity); see the module docstring.
TABLE_BIT = 1
PAD_BIT = 2
OBJECT_BIT = 4
PALM_BIT = 8
TABLE_CONTYPE, TABLE_CONAFFINITY = TABLE_BIT, PAD_BIT | OBJECT_BIT
PAD_CONTYPE, PAD_CONAFFINITY = PAD_BIT, TABLE_BIT | OBJECT_BIT
PALM_CONTYPE, PALM_CONAFFINITY = PALM_BIT, OBJECT_BIT
OBJECT_CONTYPE = OBJECT_BIT
OBJECT_CONAFFINITY = TABLE_BIT | PAD_BIT | OBJECT_BIT | PALM_BIT

SIDES = ("left", "right")


def object_collision() -> dict:
    """Keyword arguments for a task object's collision geom (``spec body.add_geom(**...)``)."""
    return {"contype": OBJECT_CONTYPE, "conaffinity": OBJECT_CONAFFINITY}


@dataclasses.dataclass(frozen=True)
class RobotInfo:
    """Static metadata of a bimanual robot. Hashable, so it can be a static jit argument.

    Per-side tuples are indexed by side: 0 = ``"left"``, 1 = ``"right"``
    (use :meth:`side_index` to convert a name).

    Attributes:
      name: ``"robot_a"`` or ``"robot_b"``.
      arm_joints: ((left arm joint names), (right arm joint names)), base to tip.
      gripper_joints: ((left finger/jaw joint names), (right ...)).
      arm_actuators, gripper_actuators: actuator names, same layout as the joints.
      ee_sites: (left, right) end-effector site names (grasp centre).
      ee_bodies: (left, right) bodies the end-effector sites are attached to.
      camera: the camera on the mirror plane (``head`` / ``top``).
      home_key: name of the home keyframe.
      mirror_axis: the mirror plane is ``{mirror_axis} = 0``.
      ee_local_reflection: diagonal of the end-effector frames' local reflection ``L``
        (an ee rotation ``R`` mirrors to ``M R diag(L)``).
      workspace_min, workspace_max: xyz bounds of the reachable region above the table
        (mirror symmetric), for point-cloud cropping and object sampling. ``z`` starts
        2 mm above the table top, so a crop drops the table's own points.
      table_height: z of the table top.
      control_dt: default control period in seconds.
      sim_dt: the model's physics timestep.
      gripper_closed, gripper_open: per-finger actuator targets at opening 0 and 1.
      gripper_span: distance between the pad faces at opening 1 (m).
      gripper_closed_gap: distance between the pad faces at opening 0 (m); the gap is
        linear in the opening (see :meth:`gripper_gap`).
      gripper_pads: ((left pad geom names), (right pad geom names)), the geoms that make
        the friction grasp (for contact / grasp checks).
      wrist_cameras: (left, right) names of the wrist cameras, one in each gripper body,
        mirror partners of each other whose image maps by a horizontal flip (the env's
        ``wrist_image`` observation), or ``None`` when the robot has none (robot B).
      sides: the side names, ``("left", "right")``.
    """

    name: str
    arm_joints: tuple[tuple[str, ...], tuple[str, ...]]
    gripper_joints: tuple[tuple[str, ...], tuple[str, ...]]
    arm_actuators: tuple[tuple[str, ...], tuple[str, ...]]
    gripper_actuators: tuple[tuple[str, ...], tuple[str, ...]]
    ee_sites: tuple[str, str]
    ee_bodies: tuple[str, str]
    camera: str
    home_key: str
    mirror_axis: str
    ee_local_reflection: tuple[float, float, float]
    workspace_min: tuple[float, float, float]
    workspace_max: tuple[float, float, float]
    table_height: float
    control_dt: float
    sim_dt: float
    gripper_closed: tuple[float, ...]
    gripper_open: tuple[float, ...]
    gripper_span: float
    gripper_closed_gap: float
    gripper_pads: tuple[tuple[str, ...], tuple[str, ...]]
    sides: tuple[str, str] = SIDES
    wrist_cameras: tuple[str, str] | None = None

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def side_index(side: str | int) -> int:
        """``"left"`` -> 0, ``"right"`` -> 1 (ints pass through)."""
        if isinstance(side, (int, np.integer)):
            if side not in (0, 1):
                raise ValueError(f"side index must be 0 or 1, got {side}")
            return int(side)
        if side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {side!r}")
        return SIDES.index(side)

    @property
    def n_arm(self) -> int:
        """Arm joints per side (6 for robot A, 5 for robot B)."""
        return len(self.arm_joints[0])

    @property
    def n_gripper(self) -> int:
        """Gripper joints (= gripper actuators) per side (2 for robot A, 1 for robot B)."""
        return len(self.gripper_joints[0])

    @property
    def nq_robot(self) -> int:
        """Number of robot qpos entries (they come first in qpos)."""
        return 2 * (self.n_arm + self.n_gripper)

    @property
    def nu(self) -> int:
        """Number of robot actuators (= ``model.nu`` unless task code adds actuators)."""
        return 2 * (self.n_arm + self.n_gripper)

    @property
    def mirror(self) -> Mirror:
        return Mirror.from_axis(self.mirror_axis)

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return int(round(self.control_dt / self.sim_dt))

    def joint_names(self) -> tuple[str, ...]:
        """All robot joint names in qpos order (left arm, left gripper, right arm, right gripper)."""
        return (
            self.arm_joints[0] + self.gripper_joints[0] + self.arm_joints[1] + self.gripper_joints[1]
        )

    def actuator_names(self) -> tuple[str, ...]:
        """All robot actuator names in ctrl order (same layout as :meth:`joint_names`)."""
        return (
            self.arm_actuators[0]
            + self.gripper_actuators[0]
            + self.arm_actuators[1]
            + self.gripper_actuators[1]
        )

    # ------------------------------------------------------------ gripper maps
    def gripper_ctrl(self, opening) -> jnp.ndarray:
        """Normalised opening in [0, 1] (0 closed, 1 open) -> finger actuator targets.

        ``opening``: [...] -> [..., n_gripper]. Pure jnp; values outside [0, 1] are clipped.
        The map is the same for both sides and mirror invariant.
        """
        o = jnp.clip(jnp.asarray(opening, dtype=jnp.float32), 0.0, 1.0)[..., None]
        lo = jnp.asarray(self.gripper_closed, jnp.float32)
        hi = jnp.asarray(self.gripper_open, jnp.float32)
        return lo + o * (hi - lo)

    def gripper_opening(self, gripper_q) -> jnp.ndarray:
        """Inverse of :meth:`gripper_ctrl` on joint positions: [..., n_gripper] -> [...].

        The mean over the fingers of the normalised finger positions (not clipped).
        """
        g = jnp.asarray(gripper_q)
        lo = jnp.asarray(self.gripper_closed, g.dtype)
        hi = jnp.asarray(self.gripper_open, g.dtype)
        return jnp.mean((g - lo) / (hi - lo), axis=-1)

    def gripper_gap(self, opening) -> jnp.ndarray:
        """Distance between the pad faces (m) at a normalised opening: [...] -> [...]."""
        o = jnp.asarray(opening, dtype=jnp.float32)
        return self.gripper_closed_gap + o * (self.gripper_span - self.gripper_closed_gap)

    def opening_for_gap(self, gap) -> jnp.ndarray:
        """Normalised opening at which the pad faces are ``gap`` metres apart (not clipped)."""
        g = jnp.asarray(gap, dtype=jnp.float32)
        return (g - self.gripper_closed_gap) / (self.gripper_span - self.gripper_closed_gap)

    def compose_ctrl(self, arm_q, opening) -> jnp.ndarray:
        """Robot ctrl vector from arm joint targets and gripper openings.

        ``arm_q``: [..., 2, n_arm] (left, right); ``opening``: [..., 2] -> [..., nu].
        """
        arm_q = jnp.asarray(arm_q)
        g = self.gripper_ctrl(opening).astype(arm_q.dtype)  # [..., 2, n_gripper]
        per_side = jnp.concatenate([arm_q, g], axis=-1)  # [..., 2, n_arm + n_gripper]
        return per_side.reshape(per_side.shape[:-2] + (-1,))

    def split_qpos(self, qpos) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Robot part of qpos -> (arm_q [..., 2, n_arm], gripper_q [..., 2, n_gripper])."""
        q = jnp.asarray(qpos)[..., : self.nq_robot]
        q = q.reshape(q.shape[:-1] + (2, self.n_arm + self.n_gripper))
        return q[..., : self.n_arm], q[..., self.n_arm :]


# --------------------------------------------------------------------- registry
def _arm_a(side: str) -> tuple[str, ...]:
    return tuple(
        f"{side}_{j}"
        for j in ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate")
    )


def _arm_b(side: str) -> tuple[str, ...]:
    return tuple(
        f"{side}_{j}"
        for j in ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
    )


_INFOS: dict[str, RobotInfo] = {
    "robot_a": RobotInfo(
        name="robot_a",
        arm_joints=(_arm_a("left"), _arm_a("right")),
        gripper_joints=(("left_finger_a", "left_finger_b"), ("right_finger_a", "right_finger_b")),
        arm_actuators=(_arm_a("left"), _arm_a("right")),
        gripper_actuators=(
            ("left_finger_a", "left_finger_b"),
            ("right_finger_a", "right_finger_b"),
        ),
        ee_sites=("left_ee", "right_ee"),
        ee_bodies=("left_gripper", "right_gripper"),
        camera="head",
        home_key="home",
        mirror_axis="y",
        ee_local_reflection=(1.0, -1.0, 1.0),
        workspace_min=(0.0, -0.6, 0.002),
        workspace_max=(0.65, 0.6, 0.5),
        table_height=0.0,
        control_dt=0.02,
        sim_dt=0.004,
        gripper_closed=(0.0, 0.0),
        gripper_open=(0.045, 0.045),
        gripper_span=0.094,
        gripper_closed_gap=0.004,
        gripper_pads=(("left_pad_a", "left_pad_b"), ("right_pad_a", "right_pad_b")),
        wrist_cameras=("wrist_left", "wrist_right"),
    ),
    "robot_b": RobotInfo(
        name="robot_b",
        arm_joints=(_arm_b("left"), _arm_b("right")),
        gripper_joints=(("left_gripper",), ("right_gripper",)),
        arm_actuators=(_arm_b("left"), _arm_b("right")),
        gripper_actuators=(("left_gripper",), ("right_gripper",)),
        ee_sites=("left_ee", "right_ee"),
        ee_bodies=("left_gripper", "right_gripper"),
        camera="top",
        home_key="home",
        mirror_axis="y",
        ee_local_reflection=(1.0, -1.0, 1.0),
        workspace_min=(0.0, -0.45, 0.002),
        workspace_max=(0.45, 0.45, 0.35),
        table_height=0.0,
        control_dt=0.02,
        sim_dt=0.004,
        gripper_closed=(0.0,),
        gripper_open=(0.05,),
        gripper_span=0.052,
        gripper_closed_gap=0.002,
        gripper_pads=(
            ("left_fixed_jaw", "left_moving_jaw"),
            ("right_fixed_jaw", "right_moving_jaw"),
        ),
    ),
}


def robot_names() -> list[str]:
    """The available robots: ``["robot_a", "robot_b"]``."""
    return list(_INFOS)


def _check_name(name: str) -> str:
    if name not in _INFOS:
        raise ValueError(f"unknown robot {name!r}; valid names: {robot_names()}")
    return name


def robot_xml_path(name: str) -> str:
    """Path of the robot's MJCF file."""
    return os.path.join(ASSET_DIR, f"{_check_name(name)}.xml")


def robot_info(name: str) -> RobotInfo:
    """Static metadata of robot ``name``."""
    return _INFOS[_check_name(name)]


def robot_mirror(name: str) -> Mirror:
    """The robot's mirror plane (y = 0 for both robots)."""
    return robot_info(name).mirror


def robot_spec(name: str) -> mujoco.MjSpec:
    """A fresh, uncompiled ``MjSpec`` of the robot, for task code to add objects to.

    Example::

        spec = robot_spec("robot_a")
        body = spec.worldbody.add_body(name="block", pos=[0.3, 0.1, 0.02])
        body.add_freejoint(name="block")
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02] * 3, mass=0.05,
                      condim=4, **object_collision())
        model = spec.compile()
    """
    return mujoco.MjSpec.from_file(robot_xml_path(name))


@functools.lru_cache(maxsize=None)
def _compiled(name: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(robot_xml_path(name))


def load_robot(name: str) -> tuple[mujoco.MjModel, Mirror]:
    """The compiled bare robot model (a fresh copy) and its mirror plane."""
    _check_name(name)
    return copy.copy(_compiled(name)), robot_mirror(name)


# ------------------------------------------------------------------ index helpers
def joint_qpos_indices(model: mujoco.MjModel, names: Sequence[str]) -> np.ndarray:
    """qpos addresses of 1-DoF joints (hinge/slide) ``names``, int32 [len(names)]."""
    out = []
    for n in names:
        j = model.joint(n)
        if model.jnt_type[j.id] not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            raise ValueError(f"joint {n!r} is not a hinge or slide joint")
        out.append(int(model.jnt_qposadr[j.id]))
    return np.asarray(out, dtype=np.int32)


def joint_dof_indices(model: mujoco.MjModel, names: Sequence[str]) -> np.ndarray:
    """qvel (dof) addresses of 1-DoF joints ``names``, int32 [len(names)]."""
    return np.asarray([int(model.jnt_dofadr[model.joint(n).id]) for n in names], dtype=np.int32)


def actuator_indices(model: mujoco.MjModel, names: Sequence[str]) -> np.ndarray:
    """ctrl indices of actuators ``names``, int32 [len(names)]."""
    return np.asarray([model.actuator(n).id for n in names], dtype=np.int32)
