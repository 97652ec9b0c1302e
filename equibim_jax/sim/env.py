"""Pure, batched MJX environments of a symmetric dual-arm robot.

The env object holds only static things (models, ids, config, the derived symmetry);
``reset(key) -> State`` and ``step(state, action) -> State`` are pure functions of one
environment, and :class:`VmapEnv` batches them. ``mirror_state`` applies ``S`` to the whole
simulator state, so equivariance can be tested rather than hoped for.

Observation fields (``EnvConfig.obs``):

=============  =======================  ======================================================
field          shape                    content
=============  =======================  ======================================================
qpos           [2 * (n_arm + 1)]        left arm joints, left gripper opening, right arm, right
ee             [2 * (3 + R + 1)]        per arm: ee position, rotation (R = 6 for "6d",
                                        4 for "quat"), gripper opening
image          [H, W, 3] uint8          RGB from the robot's camera on the mirror plane
wrist_image    [2, H, W, 3] uint8       RGB from the left (index 0) and right (1) wrist
                                        cameras (robots with ``wrist_cameras``, robot A)
depth          [H, W] float32           distance along each pixel's ray (``far`` for misses)
point_cloud    [N, 3] float32           world-frame points cropped to the workspace
=============  =======================  ======================================================

Under the mirror ``S``, ``image`` and ``depth`` flip left-right (one camera on the
plane); ``wrist_image`` swaps the two views and flips each (``camera_pair_op``): the
mirrored scene seen by the left wrist camera is the right camera's image flipped.

Action modes (``EnvConfig.action``): ``"joint"`` (same layout as the ``qpos`` observation:
absolute arm joint targets plus one gripper opening in [0, 1] per arm) and ``"ee"`` (same
layout as the ``ee`` observation: absolute ee pose per arm plus gripper opening, converted
to joint targets inside the step by damped-least-squares IK).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from equibim_jax._batching import chunked_vmap
from equibim_jax.sim import robots
from equibim_jax.sim._linalg import jax_cholesky
from equibim_jax.sim.ik import make_ee_fk, make_ik, mat_to_quat
from equibim_jax.sim.render import CameraConfig, PointCloudConfig, make_renderer
from equibim_jax.symmetry import (
    JointMap,
    ModelSymmetry,
    Symmetry,
    arm_swap_pose_op,
    camera_pair_op,
    derive_symmetry,
    image_op,
    point_cloud_op,
)
from equibim_jax.symmetry.mirror import matrix_to_rot6d

OBS_FIELDS = ("qpos", "ee", "image", "depth", "point_cloud", "wrist_image")
ACTION_MODES = ("joint", "ee")
ROTATIONS = ("6d", "quat")


@struct.dataclass
class State:
    """One environment's state (a pytree; batch it with :class:`VmapEnv`).

    Attributes:
      data: the ``mjx.Data``.
      obs: dict of observation fields (see the module docstring for shapes).
      reward: [] float32.
      done: [] bool, the step limit was reached.
      metrics: dict of [] scalars (e.g. ``nan_action``, ``clipped``, ``success``).
      info: dict of task/episode pytrees (``step``, ``success``, task fields).
    """

    data: mjx.Data
    obs: dict
    reward: jax.Array
    done: jax.Array
    metrics: dict
    info: dict


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static env configuration (frozen, hashable).

    Attributes:
      robot: a name from :func:`equibim_jax.sim.robot_names`.
      obs: observation fields, a subset of ``OBS_FIELDS`` (shapes in the module
        docstring). ``"wrist_image"`` needs a robot with wrist cameras
        (``RobotInfo.wrist_cameras``: robot A, not robot B).
      action: ``"joint"`` or ``"ee"``.
      rotation: rotation representation of ``ee`` fields, ``"6d"`` or ``"quat"``.
      ctrl_dt: control period (s); ``None`` takes the robot's default.
      sim_dt: physics timestep (s); ``None`` keeps the model's. ``ctrl_dt`` must be a
        whole multiple of it.
      image_size: square image side for ``image`` / ``depth`` / ``wrist_image`` (64, 96,
        128, ...); both wrist views have this size.
      n_points: points in ``point_cloud``.
      crop: ``(min [3], max [3])`` world-frame box the point cloud is cropped to, or
        ``None`` for the scene's ``point_cloud_crop`` if it sets one, else the robot's
        workspace. The box must be its own mirror image (checked), so that the cloud of a
        mirrored state is the mirrored cloud.
      episode_length: control steps before ``done``.
      camera: camera for images; ``None`` takes the robot's camera on the mirror plane.
      solver_iterations, ls_iterations: MJX solver settings (``None`` keeps the model's).
      ik_iterations: DLS iterations per control step in ``ee`` mode.
      max_contacts: keep at most this many contacts per step (per contact dimension), the
        deepest ones (MJX's ``max_contact_points``); ``None`` keeps every candidate pair's
        contacts. MJX computes constraint rows for every kept contact, touching or not, so
        this sets the size of the constraint solve. Physics is unchanged while no more than
        this many contacts touch at once; past that, the shallowest are dropped.
      cone: friction cone, ``"pyramidal"`` or ``"elliptic"`` (``None`` keeps the model's).
        Elliptic cones are invariant to rotations about the contact normal, so the
        dynamics are mirror-equivariant; pyramidal cones are not exactly (their edges
        follow a contact frame that does not mirror).
    """

    robot: str = "robot_a"
    obs: tuple[str, ...] = ("qpos",)
    action: str = "joint"
    rotation: str = "6d"
    ctrl_dt: float | None = None
    sim_dt: float | None = None
    image_size: int = 64
    n_points: int = 512
    crop: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    episode_length: int = 500
    camera: str | None = None
    solver_iterations: int | None = None
    ls_iterations: int | None = None
    ik_iterations: int = 10
    cone: str | None = None
    max_contacts: int | None = None

    def __post_init__(self):
        if self.max_contacts is not None and (not isinstance(self.max_contacts, int) or self.max_contacts < 1):
            raise ValueError(f"max_contacts must be a positive int or None, got {self.max_contacts!r}")
        if self.cone not in (None, "pyramidal", "elliptic"):
            raise ValueError(f"cone must be 'pyramidal' or 'elliptic', got {self.cone!r}")
        if self.robot not in robots.robot_names():
            raise ValueError(f"unknown robot {self.robot!r}; choose from {robots.robot_names()}")
        obs = (self.obs,) if isinstance(self.obs, str) else tuple(self.obs)
        bad = [o for o in obs if o not in OBS_FIELDS]
        if not obs or bad:
            raise ValueError(f"unknown observation field(s) {bad}; valid fields: {OBS_FIELDS}")
        if len(set(obs)) != len(obs):
            raise ValueError(f"duplicate observation fields in {obs}")
        object.__setattr__(self, "obs", obs)
        if "wrist_image" in obs and robots.robot_info(self.robot).wrist_cameras is None:
            raise ValueError(
                f"observation 'wrist_image' needs wrist cameras, but robot {self.robot!r} has none "
                f"(RobotInfo.wrist_cameras is None); robots with wrist cameras: "
                f"{[r for r in robots.robot_names() if robots.robot_info(r).wrist_cameras]}"
            )
        if self.action not in ACTION_MODES:
            raise ValueError(f"unknown action mode {self.action!r}; valid modes: {ACTION_MODES}")
        if self.rotation not in ROTATIONS:
            raise ValueError(f"unknown rotation {self.rotation!r}; valid: {ROTATIONS}")
        for name in ("ctrl_dt", "sim_dt"):
            v = getattr(self, name)
            if v is not None and not (v > 0):
                raise ValueError(f"{name} must be positive, got {v}")
        if not isinstance(self.image_size, int) or self.image_size < 8:
            raise ValueError(f"image_size must be an int >= 8, got {self.image_size!r}")
        if not isinstance(self.n_points, int) or self.n_points < 1:
            raise ValueError(f"n_points must be a positive int, got {self.n_points!r}")
        if self.crop is not None:
            try:
                lo, hi = (tuple(float(v) for v in c) for c in self.crop)
            except (TypeError, ValueError):
                lo = hi = ()
            if len(lo) != 3 or len(hi) != 3 or any(a >= b for a, b in zip(lo, hi)):
                raise ValueError(f"crop must be ((x, y, z) min, (x, y, z) max) with min < max, got {self.crop!r}")
            object.__setattr__(self, "crop", (lo, hi))
        if not isinstance(self.episode_length, int) or self.episode_length < 1:
            raise ValueError(f"episode_length must be a positive int, got {self.episode_length!r}")


class Scene:
    """What a task adds to the robot: objects, initial-state distribution, reward.

    Subclasses override the hooks; every hook is pure (``init`` and ``evaluate`` are traced).
    The default scene is the bare robot at its home posture.
    """

    name = "empty"
    point_cloud_crop: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    """World-frame ``(min, max)`` box for the point cloud (``None``: the robot's workspace)."""

    def build(self, spec: mujoco.MjSpec, info: robots.RobotInfo) -> None:
        """Add bodies, geoms, sites or cameras to the robot's spec."""

    def init(self, key: jax.Array, env: "Env") -> tuple[jax.Array, dict]:
        """Initial ``qpos`` [nq] and task ``info`` (a dict of arrays) for one episode."""
        return jnp.asarray(env.home_qpos), {}

    def evaluate(self, data: mjx.Data, info: dict, env: "Env") -> tuple[jax.Array, jax.Array, dict]:
        """``(reward [], success [] bool, task metrics)`` from the simulated state."""
        return jnp.zeros(()), jnp.zeros((), bool), {}

    def mirror_info(self, info: dict, env: "Env") -> dict:
        """The task info of the mirrored episode (e.g. the side flips)."""
        return info


class Env:
    """A pure MJX environment: a robot, a :class:`Scene`, observation and action modes.

    Args:
      config: :class:`EnvConfig`.
      scene: the task's :class:`Scene` (objects, initial states, success).
    """

    def __init__(self, config: EnvConfig = EnvConfig(), scene: Scene | None = None):
        self.config = config
        self.scene = scene or Scene()
        self.info = robots.robot_info(config.robot)
        spec = robots.robot_spec(config.robot)
        self.scene.build(spec, self.info)
        if config.max_contacts is not None:
            if any(n.name == "max_contact_points" for n in spec.numerics):
                raise ValueError("EnvConfig.max_contacts is set, but the model already has a custom numeric "
                                 "'max_contact_points'; set one of them")
            numeric = spec.add_numeric()
            numeric.name, numeric.data = "max_contact_points", [float(config.max_contacts)]
        model = spec.compile()
        if config.sim_dt is not None:
            model.opt.timestep = config.sim_dt
        if config.solver_iterations is not None:
            model.opt.iterations = config.solver_iterations
        if config.ls_iterations is not None:
            model.opt.ls_iterations = config.ls_iterations
        if config.cone is not None:
            model.opt.cone = getattr(mujoco.mjtCone, f"mjCONE_{config.cone.upper()}")
        self.ctrl_dt = config.ctrl_dt or self.info.control_dt
        n_sub = self.ctrl_dt / model.opt.timestep
        if abs(n_sub - round(n_sub)) > 1e-6 or round(n_sub) < 1:
            raise ValueError(
                f"ctrl_dt {self.ctrl_dt} is not a whole multiple of the physics timestep "
                f"{model.opt.timestep}"
            )
        self.n_substeps = int(round(n_sub))
        self.mj_model = model
        self.mirror = self.info.mirror
        self.sym: ModelSymmetry = derive_symmetry(model, self.mirror)
        if not self.sym.dynamics_exact:
            # S is exact on kinematics, but mirrored rollouts are then only approximately
            # mirror images of each other: say so once, with what differs.
            warnings.warn(
                f"model is kinematically mirror-symmetric but its dynamics or geoms are not; "
                f"physics is only approximately mirror-equivariant:\n{self.sym.dynamics.describe()}",
                stacklevel=2,
            )
        # MJX's default device is jax.devices()[0], which in a multi-process run belongs to
        # process 0; every process keeps its model on its own first device.
        self.mjx_model = mjx.put_model(model, device=jax.local_devices()[0])

        m = model
        key_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, self.info.home_key)
        self.home_qpos = np.array(m.key_qpos[key_id] if key_id >= 0 else m.qpos0, dtype=np.float32)
        self.home_ctrl = np.array(m.key_ctrl[key_id] if key_id >= 0 else np.zeros(m.nu), np.float32)
        qadr = lambda names: np.array([m.jnt_qposadr[m.joint(n).id] for n in names], np.int32)
        self.arm_qadr = np.stack([qadr(j) for j in self.info.arm_joints])  # [2, n_arm]
        self.grip_qadr = np.stack([qadr(j) for j in self.info.gripper_joints])  # [2, n_grip]
        self.arm_act = np.stack([robots.actuator_indices(m, a) for a in self.info.arm_actuators])
        self.grip_act = np.stack([robots.actuator_indices(m, a) for a in self.info.gripper_actuators])
        self.ee_site = np.array([m.site(s).id for s in self.info.ee_sites])
        self.ctrl_lo = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 0], -np.inf).astype(np.float32)
        self.ctrl_hi = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 1], np.inf).astype(np.float32)

        self.camera = config.camera or self.info.camera
        self.renderer = None
        self.crop = self._point_cloud_crop()
        if any(f in config.obs for f in ("image", "depth", "point_cloud")):
            self._check_camera_on_plane()
            outputs = tuple(
                o for f, o in (("image", "rgb"), ("depth", "depth"), ("point_cloud", "points"))
                if f in config.obs
            )
            cam_cfg = CameraConfig(
                camera=self.camera, width=config.image_size, height=config.image_size,
                outputs=outputs,
                point_cloud=PointCloudConfig(
                    n_points=config.n_points, workspace_min=self.crop[0], workspace_max=self.crop[1],
                ),
            )
            self.renderer = make_renderer(model, cam_cfg)
        self.wrist_renderers = None
        if "wrist_image" in config.obs:
            self._check_wrist_cameras()
            # Default lighting, as the head camera's: the headlight follows each camera, so
            # the two views light the scene as mirror images of each other.
            self.wrist_renderers = tuple(
                make_renderer(model, CameraConfig(camera=c, width=config.image_size,
                                                  height=config.image_size, outputs=("rgb",)))
                for c in self.info.wrist_cameras
            )
        self._ik = (
            make_ik(model, self.info, iterations=config.ik_iterations) if config.action == "ee" else None
        )
        self._fk = make_ee_fk(model, self.info)
        self.obs_symmetry, self.action_symmetry = self._build_symmetries()

    # ------------------------------------------------------------------ sizes & maps
    @property
    def rot_dim(self) -> int:
        return 6 if self.config.rotation == "6d" else 4

    def ee_rotation_mask(self) -> np.ndarray:
        """Bool ``[2 * (3 + R + 1)]``: the rotation entries of the end-effector layout
        (per arm: position 3, rotation ``R``, opening 1), used by the ``ee`` observation and
        by ``action="ee"`` actions. ``S`` maps the mask to itself."""
        from equibim_jax.training.run import ee_rotation_mask

        return ee_rotation_mask(2 * (3 + self.rot_dim + 1))

    @property
    def action_size(self) -> int:
        if self.config.action == "joint":
            return 2 * (self.info.n_arm + 1)
        return 2 * (3 + self.rot_dim + 1)

    def _joint_layout_map(self) -> JointMap:
        """The mirror of the ``[arm_L, grip_L, arm_R, grip_R]`` joint vector."""
        n = self.info.n_arm
        layout = [*self.arm_qadr[0], -1, *self.arm_qadr[1], -2]
        pos = {int(a): i for i, a in enumerate(layout) if a >= 0}
        perm, signs, offs, names = [], [], [], []
        qmap = self.sym.qpos
        for i, a in enumerate(layout):
            if a < 0:  # gripper opening: mirror-invariant, swaps sides
                perm.append(2 * n + 1 if a == -1 else n)
                signs.append(1.0)
                offs.append(0.0)
                names.append("gripper_" + ("left" if a == -1 else "right"))
                continue
            src = int(qmap.perm[a])
            if src not in pos:
                raise ValueError(f"arm joint at qpos {a} mirrors to a non-arm joint at {src}")
            perm.append(pos[src])
            signs.append(float(qmap.signs[a]))
            offs.append(float(qmap.offsets[a]))
            names.append(qmap.names[a] if qmap.names else str(a))
        return JointMap(np.array(perm), np.array(signs), np.array(offs), tuple(names))

    def _ee_local(self) -> np.ndarray:
        loc = self.sym.site_local[self.ee_site[0]]
        loc2 = self.sym.site_local[self.ee_site[1]]
        if not (np.allclose(loc, loc.T, atol=1e-6) and np.allclose(loc, loc2, atol=1e-6)):
            raise ValueError(
                "the end-effector sites' local reflections are not one symmetric matrix; "
                "ee observations/actions need mirror-consistent site frames"
            )
        return np.round(loc, 6)

    def _build_symmetries(self) -> tuple[Symmetry, Callable]:
        joint = self._joint_layout_map()
        ee = arm_swap_pose_op(self.mirror, self._ee_local(), self.config.rotation, extra=1)
        ops = {
            "qpos": joint, "ee": ee, "image": image_op("HWC"),
            "depth": lambda d: jnp.flip(d, axis=-1),
            "point_cloud": point_cloud_op(self.mirror),
            "wrist_image": camera_pair_op("HWC"),
        }
        obs_sym = Symmetry({k: ops[k] for k in self.config.obs})
        act_sym = joint if self.config.action == "joint" else ee
        self.joint_action_symmetry, self.ee_action_symmetry = joint, ee
        return obs_sym, act_sym

    def ee_action_from_joint(self, action: jax.Array) -> jax.Array:
        """The end-effector action that a joint action commands.

        Args:
          action: joint action [..., 2 * (n_arm + 1)] (per arm: joint targets, opening).
        Returns:
          [..., 2 * (3 + R + 1)]: per arm, the ee-site pose of the commanded joints
          (forward kinematics; position, then 6D rotation or quaternion as
          ``config.rotation``) and the same gripper opening; the action layout of
          ``action="ee"``. ``ee_action_symmetry`` of the result is the result for
          ``joint_action_symmetry(action)``.
        """
        action = jnp.asarray(action)
        n = self.info.n_arm
        if action.shape[-1] != 2 * (n + 1):
            raise ValueError(f"joint actions have {2 * (n + 1)} entries, got shape {action.shape}")
        per_arm = action.reshape(action.shape[:-1] + (2, n + 1))
        q0 = jnp.asarray(self.home_qpos, action.dtype)

        def one(a):  # [2, n + 1] -> [2, 3 + R + 1]
            q = q0.at[self.arm_qadr.reshape(-1)].set(a[:, :n].reshape(-1))
            pos, mat = self._fk(q)
            rot = matrix_to_rot6d(mat) if self.config.rotation == "6d" else mat_to_quat(mat)
            return jnp.concatenate([pos, rot, a[:, n:]], axis=-1)

        flat = per_arm.reshape((-1, 2, n + 1))
        out = jax.vmap(one)(flat)
        return out.reshape(action.shape[:-1] + (2 * (3 + self.rot_dim + 1),))

    def symmetry_ops(self, fields: tuple[str, ...], action_key: str = "action") -> dict:
        """``S`` in raw units as ``{field: op}`` for the observation ``fields`` and the action
        (under ``action_key``); each op acts on trailing axes."""
        missing = [f for f in fields if f not in self.obs_symmetry.ops]
        if missing:
            raise ValueError(f"the env does not observe {missing} (it observes {self.config.obs})")
        return {**{f: self.obs_symmetry.ops[f] for f in fields}, action_key: self.action_symmetry}

    def _point_cloud_crop(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The point-cloud crop box, checked to be its own mirror image."""
        crop = self.config.crop or self.scene.point_cloud_crop
        if crop is None:
            return tuple(self.info.workspace_min), tuple(self.info.workspace_max)
        lo, hi = (np.asarray(c, np.float64) for c in crop)
        corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        n = np.asarray(self.mirror.normal, np.float64)
        p0 = np.asarray(self.mirror.point, np.float64)
        mirrored = corners - 2 * ((corners - p0) @ n)[:, None] * n
        if np.any(mirrored < lo - 1e-6) or np.any(mirrored > hi + 1e-6):
            raise ValueError(
                f"point-cloud crop {crop} is not symmetric about the mirror plane (point {p0}, "
                f"normal {n}); the cloud of a mirrored state would not be the mirrored cloud"
            )
        return tuple(map(float, lo)), tuple(map(float, hi))

    def _check_camera_on_plane(self):
        m = self.mj_model
        cid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, self.camera)
        if cid < 0:
            raise ValueError(f"camera {self.camera!r} is not in the model")
        d = mujoco.MjData(m)
        d.qpos[:] = m.qpos0
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_camlight(m, d)
        x_axis = d.cam_xmat[cid].reshape(3, 3)[:, 0]
        n = np.asarray(self.mirror.normal)
        on_plane = abs(np.dot(d.cam_xpos[cid] - np.asarray(self.mirror.point), n)) < 1e-6
        if self.sym.cameras[cid] != cid or not on_plane or abs(abs(np.dot(x_axis, n)) - 1) > 1e-6:
            raise ValueError(
                f"camera {self.camera!r} is not on the mirror plane with its horizontal axis "
                f"normal to it (position {np.round(d.cam_xpos[cid], 4)}, x axis "
                f"{np.round(x_axis, 4)}, plane normal {n}); image symmetry needs such a camera"
            )

    def _check_wrist_cameras(self):
        """The wrist cameras exist and are mirror partners with a horizontal image flip, so
        that ``camera_pair_op`` (swap the views, flip each) is ``S`` on ``wrist_image``."""
        m = self.mj_model
        names = self.info.wrist_cameras
        if names is None:
            raise ValueError(f"robot {self.info.name!r} has no wrist cameras")
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, c) for c in names]
        missing = [c for c, i in zip(names, ids) if i < 0]
        if missing:
            raise ValueError(f"wrist camera(s) {missing} are not in the model")
        (a, b), flips = ids, self.sym.camera_flip
        if self.sym.cameras[a] != b or self.sym.cameras[b] != a or flips[a] != "horizontal" \
                or flips[b] != "horizontal":
            partner = lambda i: self.sym.camera_names[self.sym.cameras[i]] if self.sym.cameras[i] >= 0 else None
            raise ValueError(
                f"wrist cameras {names[0]!r} and {names[1]!r} are not mirror partners with a "
                f"horizontal image flip (mirror partner of {names[0]!r}: {partner(a)!r}, of "
                f"{names[1]!r}: {partner(b)!r}; image flips {flips[a]!r}, {flips[b]!r}); "
                f"wrist_image symmetry needs such a pair"
            )

    # ------------------------------------------------------------------ observations
    def ee_pose(self, data: mjx.Data) -> jax.Array:
        """End-effector poses [2, 3 + R] (position, then 6D rotation or quaternion)."""
        pos = data.site_xpos[self.ee_site]
        mat = data.site_xmat[self.ee_site].reshape(2, 3, 3)
        if self.config.rotation == "6d":
            rot = matrix_to_rot6d(mat)
        else:
            rot = mat_to_quat(mat)
        return jnp.concatenate([pos, rot], axis=-1)

    def gripper_opening(self, qpos: jax.Array) -> jax.Array:
        """Normalised opening [2] of each gripper from ``qpos``."""
        return self.info.gripper_opening(qpos[self.grip_qadr])

    def observe(self, data: mjx.Data) -> dict:
        """Observation dict of one environment (fields from ``config.obs``)."""
        cfg = self.config
        out = {}
        opening = self.gripper_opening(data.qpos)
        if "qpos" in cfg.obs:
            arm = data.qpos[self.arm_qadr]  # [2, n_arm]
            out["qpos"] = jnp.concatenate([arm, opening[:, None]], axis=-1).reshape(-1)
        if "ee" in cfg.obs:
            out["ee"] = jnp.concatenate([self.ee_pose(data), opening[:, None]], -1).reshape(-1)
        if self.renderer is not None:
            r = self.renderer.render(data)
            if "image" in cfg.obs:
                out["image"] = r["rgb"]
            if "depth" in cfg.obs:
                out["depth"] = r["depth"]
            if "point_cloud" in cfg.obs:
                out["point_cloud"] = r["points"]
        if self.wrist_renderers is not None:
            out["wrist_image"] = jnp.stack([w.rgb(data) for w in self.wrist_renderers])
        return out

    # ------------------------------------------------------------------ dynamics
    def action_to_ctrl(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        """Actuator targets [nu] for an action [A] (IK inside for ``ee`` mode)."""
        per_arm = action.reshape(2, -1)
        opening = jnp.clip(per_arm[:, -1], 0.0, 1.0)
        if self.config.action == "joint":
            arm_q = per_arm[:, :-1]
        else:
            q = self._ik(data.qpos, per_arm[:, :-1])
            arm_q = q[self.arm_qadr]
        ctrl = jnp.asarray(self.home_ctrl, data.ctrl.dtype)
        ctrl = ctrl.at[self.arm_act.reshape(-1)].set(arm_q.reshape(-1).astype(ctrl.dtype))
        grip = self.info.gripper_ctrl(opening[:, None])  # [2, n_gripper]
        ctrl = ctrl.at[self.grip_act.reshape(-1)].set(grip.reshape(-1).astype(ctrl.dtype))
        return ctrl

    def _physics(self, data: mjx.Data, ctrl: jax.Array) -> mjx.Data:
        data = data.replace(ctrl=ctrl)

        def sub(d, _):
            with jax_cholesky():  # no LAPACK custom call in the step (sim/_linalg.py)
                return mjx.step(self.mjx_model, d), None

        data, _ = jax.lax.scan(sub, data, None, length=self.n_substeps)
        return data

    def reset(self, key: jax.Array) -> State:
        """A new episode from ``key`` (pure; one environment): ``reset_to`` of the scene's
        draw ``scene.init(key, env)``."""
        return self.reset_to(*self.scene.init(key, self))

    def reset_to(self, qpos: jax.Array, task_info: dict) -> State:
        """A new episode from a given start: ``qpos`` [nq] and the scene's ``task_info`` (the
        pair ``scene.init`` returns; any scene of the same task and model may have drawn it).
        The arms' actuator targets are at home and the rest of the state follows from
        ``qpos`` (``mjx.forward``). Pure; one environment."""
        qpos = jnp.asarray(qpos)
        if qpos.shape != (self.mj_model.nq,):
            raise ValueError(f"qpos must have shape ({self.mj_model.nq},) (the model's nq); got {qpos.shape}")
        data = mjx.make_data(self.mjx_model)
        data = data.replace(qpos=jnp.asarray(qpos, data.qpos.dtype), ctrl=jnp.asarray(self.home_ctrl, data.ctrl.dtype))
        with jax_cholesky():
            data = mjx.forward(self.mjx_model, data)
        return self._finish(data, {"step": jnp.zeros((), jnp.int32), "success": jnp.zeros((), bool), **task_info},
                            nan=jnp.zeros((), jnp.float32), clipped=jnp.zeros((), jnp.float32))

    def step(self, state: State, action: jax.Array, observe: bool = True) -> State:
        """Advance one control step (``n_substeps`` physics steps in ``lax.scan``).

        A NaN or infinite action is refused: the previous actuator targets are held and
        ``metrics["nan_action"]`` is 1. Targets outside the actuator ranges are clipped and
        ``metrics["clipped"]`` counts the clipped entries.

        ``observe=False`` (a Python bool) skips the observation: the returned state keeps
        ``state.obs`` (stale) while physics, reward, success and metrics are computed as
        usual. Rendering is a sizeable part of a step's cost (``benchmarks/obs_cost.py``
        measures it), so a closed-loop rollout uses it for the steps whose observations its
        policy never reads.
        """
        action = jnp.asarray(action)
        if action.shape != (self.action_size,):
            raise ValueError(
                f"action must have shape ({self.action_size},) for action mode "
                f"{self.config.action!r}; got {action.shape} (use VmapEnv for batches)"
            )
        bad = ~jnp.all(jnp.isfinite(action))
        safe = jnp.where(jnp.isfinite(action), action, 0.0)
        ctrl = self.action_to_ctrl(state.data, safe)
        clipped_ctrl = jnp.clip(ctrl, self.ctrl_lo, self.ctrl_hi)
        n_clipped = jnp.sum(jnp.abs(clipped_ctrl - ctrl) > 1e-6).astype(jnp.float32)
        ctrl = jnp.where(bad, state.data.ctrl, clipped_ctrl)
        data = self._physics(state.data, ctrl)
        info = {**state.info, "step": state.info["step"] + 1}
        return self._finish(data, info, nan=bad.astype(jnp.float32), clipped=n_clipped,
                            obs=None if observe else state.obs)

    def _finish(self, data, info, nan, clipped, obs=None) -> State:
        reward, success, task_metrics = self.scene.evaluate(data, info, self)
        success = jnp.logical_or(info["success"], success)  # latched
        info = {**info, "success": success}
        done = info["step"] >= self.config.episode_length
        metrics = {"nan_action": nan, "clipped": clipped, "success": success.astype(jnp.float32),
                   **task_metrics}
        return State(data=data, obs=self.observe(data) if obs is None else obs,
                     reward=jnp.asarray(reward, jnp.float32),
                     done=done, metrics=metrics, info=info)

    # ------------------------------------------------------------------ the mirror
    def mirror_data(self, data: mjx.Data) -> mjx.Data:
        """``S`` on the simulator state: qpos, qvel, ctrl and the solver warm start."""
        d = data.replace(
            qpos=self.sym.qpos(data.qpos).astype(data.qpos.dtype),
            qvel=self.sym.qvel(data.qvel).astype(data.qvel.dtype),
            ctrl=self.sym.ctrl(data.ctrl).astype(data.ctrl.dtype),
            qacc_warmstart=self.sym.qvel(data.qacc_warmstart).astype(data.qvel.dtype),
        )
        with jax_cholesky():
            return mjx.forward(self.mjx_model, d)

    def mirror_state(self, state: State) -> State:
        """The mirror image of a whole state; observations are recomputed from it."""
        data = self.mirror_data(state.data)
        info = self.scene.mirror_info(state.info, self)
        return state.replace(data=data, obs=self.observe(data), info=info)


class VmapEnv:
    """Batches an :class:`Env`: ``reset(keys [B]) -> State [B]``, ``step(State [B], [B, A])``.

    ``chunk``: envs per vmapped sub-batch (``equibim_jax._batching``); the default is one
    ``vmap`` of the whole batch.
    """

    def __init__(self, env: Env, chunk: int | None | str = "auto"):
        self.env = env
        self.reset = chunked_vmap(env.reset, chunk)
        self.step = chunked_vmap(env.step, chunk)
        self.mirror_state = chunked_vmap(env.mirror_state, chunk)

    def __getattr__(self, name):
        return getattr(self.env, name)
