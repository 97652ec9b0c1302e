"""Reusable scene building blocks: free objects on the table with a mirror-symmetric
initial distribution. Tasks build on these."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from equibim_jax.sim import robots
from equibim_jax.sim.env import Env, Scene

SIDES = ("left", "right", "both")


def side_sign(key: jax.Array, side: str) -> jax.Array:
    """+1 (left, y > 0) or -1 (right); ``"both"`` draws either with probability 1/2."""
    if side == "left":
        return jnp.ones(())
    if side == "right":
        return -jnp.ones(())
    if side == "both":
        return jnp.where(jax.random.bernoulli(key), 1.0, -1.0)
    raise ValueError(f"side must be one of {SIDES}, got {side!r}")


def add_free_box(spec: mujoco.MjSpec, name: str, half_size, mass: float, rgba, pos=(0.3, 0.0, 0.1),
                 friction=(1.0, 0.005, 0.0001)) -> None:
    """A free box body ``name`` whose geom collides with the table, grippers and objects."""
    body = spec.worldbody.add_body(name=name, pos=list(pos))
    body.add_freejoint(name=name)
    body.add_geom(
        name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half_size), mass=mass, rgba=list(rgba),
        condim=4, friction=list(friction), **robots.object_collision(),
    )


@dataclasses.dataclass(frozen=True)
class BoxScene(Scene):
    """One box on the table at ``x`` in ``x_range`` and ``|y|`` in ``y_range`` on ``side``.

    Used by the simulator benchmark and the dynamics-equivariance tests.
    """

    half_size: tuple[float, float, float] = (0.02, 0.02, 0.02)
    mass: float = 0.05
    x_range: tuple[float, float] = (0.25, 0.35)
    y_range: tuple[float, float] = (0.1, 0.3)
    side: str = "both"
    name = "box"

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side must be one of {SIDES}, got {self.side!r}")

    def build(self, spec, info):
        add_free_box(spec, "box", self.half_size, self.mass, (0.9, 0.2, 0.2, 1.0),
                     pos=(0.3, 0.0, info.table_height + self.half_size[2]))

    def init(self, key, env: Env):
        k_side, k_x, k_y = jax.random.split(key, 3)
        sign = side_sign(k_side, self.side)
        x = jax.random.uniform(k_x, (), minval=self.x_range[0], maxval=self.x_range[1])
        y = sign * jax.random.uniform(k_y, (), minval=self.y_range[0], maxval=self.y_range[1])
        z = env.info.table_height + self.half_size[2]
        adr = int(env.mj_model.jnt_qposadr[env.mj_model.joint("box").id])
        home = jnp.asarray(env.home_qpos)
        qpos = home.at[adr : adr + 3].set(jnp.stack([x, y, z]).astype(home.dtype))
        return qpos, {"side": sign}

    def mirror_info(self, info, env):
        return {**info, "side": -info["side"]} if "side" in info else info
