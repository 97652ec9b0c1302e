"""Structured symmetry operators: joint maps and named per-field symmetries.

``JointMap`` is ``x' = P D x + b`` on a flat vector (signed permutation plus offsets).
``Symmetry`` is a named structure of operators, one per field of a dict observation or
action, applied to a whole batch pytree. Both are pure and involutions when built from a
symmetric model (``derive_symmetry`` checks this).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Mapping

import jax.numpy as jnp
import numpy as np

from equibim_jax.symmetry import mirror as _m

Array = jnp.ndarray
Op = Callable[[Array], Array]


@dataclasses.dataclass(frozen=True, eq=False)
class JointMap:
    """``x'[..., i] = signs[i] * x[..., perm[i]] + offsets[i]`` over the last axis.

    Attributes:
      perm: int [n], source index of each output entry.
      signs: float [n], +1 or -1.
      offsets: float [n].
      names: optional names of the n entries (for printing and error messages).
    """

    perm: np.ndarray
    signs: np.ndarray
    offsets: np.ndarray
    names: tuple[str, ...] | None = None

    def __post_init__(self):
        perm = np.asarray(self.perm, dtype=np.int32).reshape(-1)
        signs = np.asarray(self.signs, dtype=np.float64).reshape(-1)
        offsets = np.asarray(self.offsets, dtype=np.float64).reshape(-1)
        n = perm.shape[0]
        if signs.shape != (n,) or offsets.shape != (n,):
            raise ValueError(
                f"JointMap perm, signs, offsets must have the same length; got "
                f"{perm.shape}, {signs.shape}, {offsets.shape}"
            )
        if sorted(perm.tolist()) != list(range(n)):
            raise ValueError(f"JointMap perm is not a permutation of 0..{n - 1}: {perm}")
        if not np.all(np.isin(signs, (-1.0, 1.0))):
            raise ValueError(f"JointMap signs must be +1 or -1, got {signs}")
        if self.names is not None and len(self.names) != n:
            raise ValueError(f"JointMap names has {len(self.names)} entries, expected {n}")
        object.__setattr__(self, "perm", perm)
        object.__setattr__(self, "signs", signs)
        object.__setattr__(self, "offsets", offsets)

    @classmethod
    def identity(cls, n: int, names=None) -> "JointMap":
        return cls(np.arange(n), np.ones(n), np.zeros(n), names)

    @property
    def size(self) -> int:
        return int(self.perm.shape[0])

    def __call__(self, x: Array) -> Array:
        """Apply to ``x`` [..., n] -> [..., n]."""
        x = jnp.asarray(x)
        if x.shape[-1] != self.size:
            raise ValueError(f"JointMap of size {self.size} applied to shape {x.shape}")
        if not jnp.issubdtype(x.dtype, jnp.floating):
            x = x.astype(jnp.float32)
        s = jnp.asarray(self.signs, x.dtype)
        b = jnp.asarray(self.offsets, x.dtype)
        return x[..., self.perm] * s + b

    def linear(self) -> "JointMap":
        """The same map without offsets (its action on differences and velocities)."""
        return JointMap(self.perm, self.signs, np.zeros_like(self.offsets), self.names)

    def as_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """``(A, b)`` with ``x' = A x + b``: A [n, n], b [n]."""
        a = np.zeros((self.size, self.size))
        a[np.arange(self.size), self.perm] = self.signs
        return a, self.offsets.copy()

    def is_involution(self, atol: float = 1e-9) -> bool:
        a, b = self.as_matrix()
        return bool(
            np.allclose(a @ a, np.eye(self.size), atol=atol) and np.allclose(a @ b + b, 0, atol=atol)
        )

    def concat(self, other: "JointMap") -> "JointMap":
        """Block-diagonal combination: this map on the first entries, ``other`` on the rest."""
        names = None
        if self.names is not None and other.names is not None:
            names = self.names + other.names
        return JointMap(
            np.concatenate([self.perm, other.perm + self.size]),
            np.concatenate([self.signs, other.signs]),
            np.concatenate([self.offsets, other.offsets]),
            names,
        )

    def select(self, idx) -> "JointMap":
        """Restrict to a subset of entries that the map sends to each other.

        ``idx``: int [k] indices into the full vector; must be closed under ``perm``.
        """
        idx = np.asarray(idx, dtype=np.int64)
        pos = {int(j): k for k, j in enumerate(idx)}
        try:
            perm = [pos[int(self.perm[i])] for i in idx]
        except KeyError as e:
            raise ValueError(
                f"JointMap.select: the chosen entries are not closed under the map (entry {e} "
                "maps outside the selection)"
            ) from None
        names = tuple(self.names[i] for i in idx) if self.names is not None else None
        return JointMap(perm, self.signs[idx], self.offsets[idx], names)

    def describe(self) -> str:
        """A readable table: one line per entry, ``name <- sign * source + offset``."""
        names = self.names or tuple(str(i) for i in range(self.size))
        lines = []
        for i in range(self.size):
            sign = "+" if self.signs[i] > 0 else "-"
            off = f" {self.offsets[i]:+.4f}" if abs(self.offsets[i]) > 0 else ""
            lines.append(f"{names[i]:>24s} <- {sign}{names[self.perm[i]]}{off}")
        return "\n".join(lines)


def identity_op(x: Array) -> Array:
    """The identity operator (fields that do not change under the mirror, e.g. time)."""
    return x


def image_op(layout: str = "NHWC") -> Op:
    """Operator that flips images with the given trailing layout."""
    _m.flip_image(jnp.zeros((1, 1, 1)), layout)  # validate eagerly
    return lambda x: _m.flip_image(x, layout)


def camera_pair_op(layout: str = "HWC") -> Op:
    """Operator on the images of a mirror pair of cameras (e.g. left and right wrist):
    swap the two views, then flip each image left-right.

    ``layout`` names each image's trailing axes as in :func:`image_op`: ``"HWC"`` /
    ``"NHWC"`` -> the pair is [..., 2, H, W, C] (swap axis -4, flip axis -2);
    ``"CHW"`` / ``"NCHW"`` -> [..., 2, C, H, W] (swap axis -4, flip axis -1). Index 0 of
    the pair axis is one camera (the left one), index 1 its mirror partner; same shape
    and dtype out.

    This is ``S`` when the two cameras are mirror partners whose image maps by a
    horizontal flip (``ModelSymmetry.cameras`` pairs them and ``camera_flip`` is
    ``"horizontal"``): the mirrored scene seen by camera 0 is camera 1's image flipped,
    and vice versa. A flip alone (``image_op``) would be wrong for such a pair: it is
    ``S`` only for a single camera on the mirror plane.
    """
    if layout in ("NHWC", "HWC"):
        flip_axis = -2
    elif layout in ("NCHW", "CHW"):
        flip_axis = -1
    else:
        raise ValueError(f"layout must be NHWC, HWC, NCHW or CHW, got {layout!r}")

    def op(x: Array) -> Array:
        x = jnp.asarray(x)
        if x.ndim < 4 or x.shape[-4] != 2:
            raise ValueError(
                f"camera_pair_op expects a camera pair [..., 2, H, W, C] or [..., 2, C, H, W], "
                f"got shape {x.shape}"
            )
        return jnp.flip(jnp.flip(x, axis=-4), axis=flip_axis)

    return op


def point_cloud_op(mirror: _m.Mirror) -> Op:
    """Operator that reflects world-frame point clouds [..., N, 3+]."""
    return lambda x: _m.reflect_point_cloud(mirror, x)


def arm_swap_pose_op(
    mirror: _m.Mirror, local=None, rotation: str = "6d", extra: int = 1
) -> Op:
    """End-effector action/observation of two arms: mirror each pose and swap the arms.

    The vector is ``[pose_A, extra_A, pose_B, extra_B]`` with pose = position (3) plus
    rotation (``"quat"``: 4, ``"6d"``: 6) and ``extra`` mirror-invariant entries per arm
    (e.g. the gripper opening). The mirrored pose of arm A becomes arm B's. [..., D].
    """
    if rotation == "quat":
        rdim, reflect = 4, _m.reflect_pose_quat
    elif rotation == "6d":
        rdim, reflect = 6, _m.reflect_pose_6d
    else:
        raise ValueError(f"rotation must be 'quat' or '6d', got {rotation!r}")
    per_arm = 3 + rdim + extra

    def op(x: Array) -> Array:
        x = jnp.asarray(x)
        if x.shape[-1] != 2 * per_arm:
            raise ValueError(
                f"arm_swap_pose_op expects last dim {2 * per_arm} (2 x (3 + {rdim} + {extra})), "
                f"got {x.shape}"
            )
        a, b = x[..., :per_arm], x[..., per_arm:]

        def mirror_arm(v):
            pose = reflect(mirror, v[..., : 3 + rdim], local)
            return jnp.concatenate([pose, v[..., 3 + rdim :].astype(pose.dtype)], axis=-1)

        return jnp.concatenate([mirror_arm(b), mirror_arm(a)], axis=-1)

    return op


@dataclasses.dataclass(frozen=True, eq=False)
class Symmetry:
    """A named structure of operators, one per field: ``S`` on a whole dict pytree.

    ``Symmetry({"qpos": joint_map, "image": image_op(), "point_cloud": point_cloud_op(m)})``
    maps a batch ``{"qpos": [B, T, n], "image": [B, T, H, W, C], ...}`` field by field.
    Each operator acts on trailing axes, so any leading batch/time dims work.

    Args:
      ops: field name -> operator.
      passthrough: fields left as they are (e.g. episode ids); any other field that has no
        operator is an error, so a new field is never silently left unmirrored.
    """

    ops: Mapping[str, Op]
    passthrough: tuple[str, ...] = ()

    def __post_init__(self):
        for k, v in self.ops.items():
            if not callable(v):
                raise TypeError(f"Symmetry op for field {k!r} is not callable: {v!r}")
        object.__setattr__(self, "ops", dict(self.ops))
        object.__setattr__(self, "passthrough", tuple(self.passthrough))

    @property
    def fields(self) -> tuple[str, ...]:
        return tuple(self.ops)

    def __call__(self, tree: Mapping[str, Array]) -> dict[str, Array]:
        """Mirror every field of ``tree``. Unknown fields raise ``KeyError``."""
        if not isinstance(tree, Mapping):
            raise TypeError(f"Symmetry expects a dict of fields, got {type(tree).__name__}")
        out = {}
        for k, v in tree.items():
            if k in self.ops:
                out[k] = self.ops[k](v)
            elif k in self.passthrough:
                out[k] = v
            else:
                raise KeyError(
                    f"Symmetry has no operator for field {k!r}; known fields: "
                    f"{sorted(self.ops)}; passthrough: {list(self.passthrough)}"
                )
        return out

    def subset(self, fields) -> "Symmetry":
        """The symmetry restricted to ``fields``."""
        missing = [f for f in fields if f not in self.ops]
        if missing:
            raise KeyError(f"Symmetry has no operator for {missing}; known: {sorted(self.ops)}")
        return Symmetry({f: self.ops[f] for f in fields}, self.passthrough)

    def with_ops(self, **ops: Op) -> "Symmetry":
        """A new symmetry with extra or replaced field operators."""
        return Symmetry({**self.ops, **ops}, self.passthrough)
