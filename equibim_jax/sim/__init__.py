"""Symmetric dual-arm robots, the MJX environment, the ray-cast renderer and the IK."""

from equibim_jax.sim.robots import (
    RobotInfo,
    load_robot,
    object_collision,
    robot_info,
    robot_names,
    robot_spec,
)

__all__ = [
    "RobotInfo", "load_robot", "object_collision", "robot_info", "robot_names", "robot_spec",
    "Env", "EnvConfig", "Scene", "State", "VmapEnv", "BoxScene", "make_ik", "make_renderer",
    "CameraConfig", "PointCloudConfig",
]


def __getattr__(name):
    # The env, renderer and IK import mujoco.mjx (slow); load them on first use.
    if name in ("Env", "EnvConfig", "Scene", "State", "VmapEnv"):
        from equibim_jax.sim import env

        return getattr(env, name)
    if name == "BoxScene":
        from equibim_jax.sim.scenes import BoxScene

        return BoxScene
    if name == "make_ik":
        from equibim_jax.sim.ik import make_ik

        return make_ik
    if name in ("make_renderer", "CameraConfig", "PointCloudConfig"):
        from equibim_jax.sim import render

        return getattr(render, name)
    raise AttributeError(f"module 'equibim_jax.sim' has no attribute {name!r}")
