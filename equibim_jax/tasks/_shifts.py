"""The distribution shifts of the real-robot tasks (robot B), shared by their scenes.

A robot-B task's scene subclasses :class:`ShiftScene`; its fields are then task options
(``make_env("drumstick_hook", side="left", asymmetric_quality=0.28)``), recorded in the
env's ``task_options`` and so in every dataset and run made with it.

Options
-------
``side`` (``"left"``, ``"right"``, ``"both"``)
    The side the object lies on (``"both"``: either, with probability 1/2). Train on one
    side and test on the other for the mirrored-configuration shift. A task whose object
    sits on the mirror plane accepts only ``"both"``.
``mirrored_orientation`` (bool)
    The object's yaw is drawn as ``s * u`` by default, ``u`` from the task's yaw range and
    ``s`` the side sign (so the default law is mirror-symmetric); with this option it is
    ``-s * u``: on the same side the object lies in the mirrored orientation.
``wide_init`` (float >= 1)
    Every initial range (position, yaw) is widened about its centre by this factor (a
    ``|y|`` range is clipped so the object stays on its side; see :func:`widen`).
``asymmetric_quality`` (float in [0, 1]) and ``asymmetric_side`` (``"left"``/``"right"``)
    That fraction of the episodes on ``asymmetric_side`` are *perturbed*: ``init`` draws a
    flag ``info["perturbed"]`` (Bernoulli, per episode), and the task's expert, reading it,
    executes a corrupted script that fails. Demo generation keeps perturbed episodes (they
    are the bad demonstrations) and records them in the dataset metadata. The initial
    state itself is unchanged.

Every option at its default gives the unshifted, mirror-symmetric distribution.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from equibim_jax.sim.env import Scene
from equibim_jax.sim.scenes import SIDES, side_sign

__all__ = ["ShiftScene", "widen", "widen_abs", "SHIFT_FIELDS"]

SHIFT_FIELDS = ("side", "mirrored_orientation", "wide_init", "asymmetric_quality", "asymmetric_side")


def widen(r: tuple[float, float], factor: float) -> tuple[float, float]:
    """``(lo, hi)`` widened about its centre by ``factor``: half-width times ``factor``."""
    c, h = 0.5 * (r[0] + r[1]), 0.5 * (r[1] - r[0])
    return (c - factor * h, c + factor * h)


def widen_abs(r: tuple[float, float], factor: float, min_low: float) -> tuple[float, float]:
    """A ``|y|`` range widened by ``factor`` (:func:`widen`), its low end kept at or above
    ``min_low`` (so the object stays wholly on its side of the mirror plane)."""
    lo, hi = widen(r, factor)
    return (max(lo, min_low), hi)


@dataclasses.dataclass(frozen=True)
class ShiftScene(Scene):
    """Base of the robot-B task scenes: the shift options (module docstring) as fields.

    Attributes:
      side: ``"left"``, ``"right"`` or ``"both"``.
      mirrored_orientation: draw the object's yaw mirrored (``-s * u`` instead of ``s * u``).
      wide_init: factor (>= 1) widening every initial range.
      asymmetric_quality: fraction of ``asymmetric_side``'s episodes whose expert is
        perturbed into failing.
      asymmetric_side: the side with the bad demonstrations.
    """

    side: str = "both"
    mirrored_orientation: bool = False
    wide_init: float = 1.0
    asymmetric_quality: float = 0.0
    asymmetric_side: str = "right"

    # Tasks whose object sits on the mirror plane set this False: ``side`` must be "both".
    sided = True

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"{self.name}: side must be one of {SIDES}, got {self.side!r}")
        if not self.sided and self.side != "both":
            raise ValueError(f"{self.name}: the object sits on the mirror plane, so side must be "
                             f"'both', got {self.side!r}")
        if not isinstance(self.mirrored_orientation, bool):
            raise ValueError(f"{self.name}: mirrored_orientation must be a bool, got "
                             f"{self.mirrored_orientation!r}")
        if not (isinstance(self.wide_init, (int, float)) and self.wide_init >= 1.0):
            raise ValueError(f"{self.name}: wide_init must be a factor >= 1, got {self.wide_init!r}")
        if not (isinstance(self.asymmetric_quality, (int, float))
                and 0.0 <= self.asymmetric_quality <= 1.0):
            raise ValueError(f"{self.name}: asymmetric_quality must be a fraction in [0, 1], got "
                             f"{self.asymmetric_quality!r}")
        if self.asymmetric_side not in ("left", "right"):
            raise ValueError(f"{self.name}: asymmetric_side must be 'left' or 'right', got "
                             f"{self.asymmetric_side!r}")
        if self.asymmetric_quality > 0 and self.sided and self.side not in ("both", self.asymmetric_side):
            raise ValueError(
                f"{self.name}: asymmetric_quality perturbs demos on the {self.asymmetric_side} "
                f"side, but side={self.side!r} never puts the object there")

    # ------------------------------------------------------------ helpers for init
    def draw_side(self, key: jax.Array) -> jax.Array:
        """The side sign ``s`` [] float32 (+1 left, -1 right) of one episode."""
        return side_sign(key, self.side).astype(jnp.float32)

    def draw_yaw(self, key: jax.Array, s: jax.Array, yaw_range: tuple[float, float]) -> jax.Array:
        """Yaw [] ``s * u`` (``-s * u`` with ``mirrored_orientation``), ``u`` uniform on
        ``yaw_range`` widened by ``wide_init``."""
        lo, hi = widen(yaw_range, self.wide_init)
        u = jax.random.uniform(key, (), minval=lo, maxval=hi)
        return (-s if self.mirrored_orientation else s) * u

    def uniform(self, key: jax.Array, r: tuple[float, float]) -> jax.Array:
        """Uniform [] on ``r`` widened by ``wide_init``."""
        lo, hi = widen(r, self.wide_init)
        return jax.random.uniform(key, (), minval=lo, maxval=hi)

    def uniform_abs(self, key: jax.Array, r: tuple[float, float], min_low: float) -> jax.Array:
        """Uniform [] on the ``|y|`` range ``r`` widened by ``wide_init`` (:func:`widen_abs`)."""
        lo, hi = widen_abs(r, self.wide_init, min_low)
        return jax.random.uniform(key, (), minval=lo, maxval=hi)

    def draw_perturbed(self, key: jax.Array, s: jax.Array) -> jax.Array:
        """Whether this episode's expert is perturbed: [] bool, True with probability
        ``asymmetric_quality`` when the episode is on ``asymmetric_side`` (for a task without
        sides: on every episode), else False."""
        on_side = s > 0 if self.asymmetric_side == "left" else s < 0
        if not self.sided:
            on_side = jnp.ones((), bool)
        return on_side & (jax.random.uniform(key, ()) < self.asymmetric_quality)

    @staticmethod
    def signed_yaw_quat(yaw: jax.Array, s: jax.Array) -> jax.Array:
        """The free joint's quaternion [4] (w, x, y, z) of a yaw about z, with sign ``s``:
        ``s (cos(yaw/2), 0, 0, sin(yaw/2))``. The mirror maps a free joint's quaternion
        ``(w, x, y, z)`` to ``(-w, x, -y, z)`` (the same rotation as the reflected one, with
        the opposite sign), so drawing the sign with the side makes the mirror image of a
        start exactly the start drawn on the other side."""
        h = 0.5 * yaw
        z = jnp.zeros_like(h)
        return s * jnp.stack([jnp.cos(h), z, z, jnp.sin(h)])

    def mirror_info(self, info: dict, env) -> dict:
        """The mirrored episode: the object on the other side and its yaw negated
        (``perturbed`` is kept)."""
        out = {**info, "side": -info["side"]} if "side" in info else dict(info)
        return {**out, "yaw": -info["yaw"]} if "yaw" in info else out
