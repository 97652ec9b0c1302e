"""Mirror-consistent per-field normalisation.

Every field (``"action"``, ``"qpos"``, ``"point_cloud"``, ...) is normalised by a
per-channel affine map on its trailing axis, ``y = x * scale + offset``. The statistics
are fitted on ``data ∪ S(data)``. That union is mapped to itself by the mirror ``S``
(``S`` is an involution), so for a joint map ``x'[i] = s_i x[p(i)] + b_i`` the fitted
statistics obey ``scale[i] == scale[p(i)]`` and ``center[i] == s_i center[p(i)] + b_i``.
Substituting, ``normalise(S(x)) == S_n(normalise(x))`` with ``S_n(y)[i] = s_i y[p(i)]``:
a signed permutation, the offsets vanish. This is what lets ``L_sym`` be computed with a
linear ``S_a`` in normalised action space.

Degenerate channels (range or std below ``eps``, e.g. a joint that never moves) would
give an enormous or infinite scale. They get ``scale = 1`` and are centred on their
constant value, so they normalise to 0. Centring (rather than mapping to -1, as some
implementations do) keeps the mirror consistency: a constant channel and its mirror
image both map to 0, and ``S_n`` stays a signed permutation.

Channels named in ``identity`` are passed through unscaled (``scale = 1, offset = 0``).
This is for values that already live on a fixed scale in ``[-1, 1]``, such as the entries
of an end-effector rotation (6D or quaternion). A task that holds the gripper's orientation
nearly fixed gives such a channel a tiny demo range, and a min-max fit would blow every
closed-loop deviation up by the inverse of that range. ``S`` acts on rotation entries as
a signed permutation with no offset, so unscaled channels keep ``S_n`` a signed permutation.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Literal

import flax.struct
import jax.numpy as jnp
import numpy as np

Array = Any
Mode = Literal["minmax", "meanstd"]

__all__ = [
    "FieldNormalizer",
    "Normalizer",
    "fit_normalizer",
    "mirror_in_normalized_space",
    "normalized_symmetry",
    "conjugate_op",
    "signed_permutation",
]


@flax.struct.dataclass
class FieldNormalizer:
    """Per-channel affine normaliser of one field, ``y = x * scale + offset``.

    Attributes:
      scale: ``[D]`` float32, positive.
      offset: ``[D]`` float32.
    ``D`` is the size of the field's trailing axis (joint count, or 3 for points).
    """

    scale: Array
    offset: Array

    def normalize(self, x: Array) -> Array:
        """Map raw values ``[..., D]`` to normalised values ``[..., D]``."""
        return x * self.scale + self.offset

    def unnormalize(self, y: Array) -> Array:
        """Map normalised values ``[..., D]`` back to raw values ``[..., D]``."""
        return (y - self.offset) / self.scale


@flax.struct.dataclass
class Normalizer:
    """A :class:`FieldNormalizer` per field; a pytree, so it can be checkpointed.

    Attributes:
      fields: ``{name: FieldNormalizer}``.
    """

    fields: dict[str, FieldNormalizer]

    def normalize(self, batch: Mapping[str, Array]) -> dict[str, Array]:
        """Normalise each field of ``batch`` (``{name: [..., D_name]}``) that has stats.

        Fields without statistics are passed through unchanged.
        """
        return {k: self.fields[k].normalize(v) if k in self.fields else v for k, v in batch.items()}

    def unnormalize(self, batch: Mapping[str, Array]) -> dict[str, Array]:
        """Inverse of :meth:`normalize`, field by field."""
        return {
            k: self.fields[k].unnormalize(v) if k in self.fields else v for k, v in batch.items()
        }

    def to_state_dict(self) -> dict[str, dict[str, np.ndarray]]:
        """Plain nested dict ``{field: {"scale": [D], "offset": [D]}}`` for saving."""
        return {
            k: {"scale": np.asarray(f.scale), "offset": np.asarray(f.offset)}
            for k, f in self.fields.items()
        }

    @classmethod
    def from_state_dict(cls, d: Mapping[str, Mapping[str, Array]]) -> Normalizer:
        """Rebuild from the output of :meth:`to_state_dict`."""
        try:
            return cls(
                {
                    k: FieldNormalizer(
                        scale=jnp.asarray(v["scale"], jnp.float32),
                        offset=jnp.asarray(v["offset"], jnp.float32),
                    )
                    for k, v in d.items()
                }
            )
        except (KeyError, TypeError) as e:
            raise ValueError(
                "Normalizer.from_state_dict: expected {field: {'scale': [D], 'offset': [D]}}, "
                f"got keys {list(d)!r} ({e})"
            ) from e


def _as_field_ops(symmetry: Any) -> Callable[[str], Callable[[Array], Array] | None]:
    """Return ``get(name) -> op or None`` for a symmetry given in any accepted form.

    Accepted: a mapping ``{field: op}``; an object with an ``ops`` mapping (the
    ``equibim_jax.symmetry.Symmetry`` shape); or any callable ``dict -> dict``.
    """
    ops = getattr(symmetry, "ops", symmetry)
    if isinstance(ops, Mapping):
        return lambda name: ops.get(name)
    if callable(symmetry):
        return lambda name: (lambda x: symmetry({name: x})[name])
    raise TypeError(
        "symmetry must be a mapping {field: op}, an object with an `ops` mapping, or a "
        f"callable dict -> dict; got {type(symmetry).__name__}"
    )


def _channel_stats(x: np.ndarray, mode: Mode, eps: float, name: str):
    """Per-channel (scale, offset) of ``x [..., D]``, reducing all but the last axis."""
    flat = x.reshape(-1, x.shape[-1]).astype(np.float64)
    if mode == "minmax":
        lo, hi = flat.min(0), flat.max(0)
        center, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    elif mode == "meanstd":
        center, half = flat.mean(0), flat.std(0)
    else:
        raise ValueError(f"field {name!r}: mode must be 'minmax' or 'meanstd', got {mode!r}")
    # See module docstring: degenerate channels get scale 1 and are centred on 0.
    half = np.where(half < eps, 1.0, half)
    scale = 1.0 / half
    return scale.astype(np.float32), (-center * scale).astype(np.float32)


def fit_normalizer(
    data: Mapping[str, Array],
    symmetry: Any = None,
    *,
    mode: Mode | Mapping[str, Mode] = "minmax",
    eps: float = 1e-4,
    identity: Mapping[str, Array] | None = None,
) -> Normalizer:
    """Fit per-channel statistics on ``data ∪ S(data)``.

    Args:
      data: ``{field: [N, ..., D]}`` raw arrays; statistics are per channel of the
        trailing axis ``D``, over all other axes (frames, time, points).
      symmetry: the mirror ``S`` in raw space: ``{field: op}``, an object with ``.ops``,
        or a callable ``dict -> dict``. ``None`` fits on ``data`` alone (not
        mirror-consistent; only for policies trained without ``L_sym``).
      mode: ``"minmax"`` maps the range to ``[-1, 1]``; ``"meanstd"`` to zero mean, unit
        std. One mode for all fields, or a mapping ``{field: mode}``.
      eps: a channel whose half-range (or std) is below ``eps`` is degenerate and gets
        ``scale = 1``, centred on its value (see module docstring).
      identity: ``{field: bool [D]}``, channels left unscaled (``scale = 1``,
        ``offset = 0``), e.g. rotation entries (see module docstring). The mask must be
        mapped to itself by ``S`` for the normaliser to stay mirror-consistent.

    Returns:
      A :class:`Normalizer` with a ``FieldNormalizer`` (``scale, offset: [D]``) per field.

    Raises:
      ValueError: for an empty field, a field with no trailing channel axis, or
        non-finite values (NaN/inf) in the data or in its mirror image.
    """
    get_op = _as_field_ops(symmetry) if symmetry is not None else (lambda name: None)
    identity = dict(identity or {})
    unknown = sorted(set(identity) - set(data))
    if unknown:
        raise ValueError(f"fit_normalizer: identity names fields {unknown} that are not in the data "
                         f"({sorted(data)})")
    fields = {}
    for name, x in data.items():
        x = np.asarray(x)
        if x.ndim < 1 or x.size == 0:
            raise ValueError(f"fit_normalizer: field {name!r} is empty (shape {x.shape})")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"fit_normalizer: field {name!r} contains NaN or inf")
        op = get_op(name)
        if op is not None:
            mx = np.asarray(op(jnp.asarray(x)))
            if mx.shape != x.shape:
                raise ValueError(
                    f"fit_normalizer: mirror op for {name!r} changed shape {x.shape} -> {mx.shape}"
                )
            if not np.all(np.isfinite(mx)):
                raise ValueError(f"fit_normalizer: mirror of field {name!r} contains NaN or inf")
            x = np.concatenate([x, mx], axis=0)
        field_mode = mode[name] if isinstance(mode, Mapping) else mode
        scale, offset = _channel_stats(x, field_mode, eps, name)
        if name in identity:
            keep = np.asarray(identity[name])
            if keep.dtype != bool or keep.shape != (x.shape[-1],):
                raise ValueError(
                    f"fit_normalizer: identity[{name!r}] must be a bool mask of shape ({x.shape[-1]},) "
                    f"(the field's channels); got dtype {keep.dtype}, shape {keep.shape}"
                )
            scale = np.where(keep, 1.0, scale).astype(np.float32)
            offset = np.where(keep, 0.0, offset).astype(np.float32)
        fields[name] = FieldNormalizer(scale=jnp.asarray(scale), offset=jnp.asarray(offset))
    return Normalizer(fields)


def signed_permutation(perm: Array, signs: Array) -> Callable[[Array], Array]:
    """The linear op ``y'[..., i] = signs[i] * y[..., perm[i]]`` (pure, jit/vmap-safe).

    Args:
      perm: ``[D]`` int permutation. signs: ``[D]`` of +-1.
    Returns:
      ``op([..., D]) -> [..., D]``.
    """
    perm = jnp.asarray(perm, jnp.int32)
    signs = jnp.asarray(signs, jnp.float32)
    return lambda y: signs * jnp.take(y, perm, axis=-1)


def mirror_in_normalized_space(
    perm: Array,
    signs: Array,
    offsets: Array,
    field: FieldNormalizer,
    *,
    rtol: float = 1e-4,
    atol: float = 1e-5,
) -> tuple[np.ndarray, np.ndarray]:
    """The normalised-space form of a joint map ``x'[i] = signs[i] x[perm[i]] + offsets[i]``.

    For a mirror-consistent ``field`` it is the signed permutation ``(perm, signs)`` with
    no offset. That is checked: the function refuses a normaliser that was not fitted on
    ``data ∪ S(data)``.

    Args:
      perm: ``[D]`` int. signs: ``[D]`` +-1. offsets: ``[D]`` raw-space offsets.
      field: the field's fitted normaliser (``scale, offset: [D]``).

    Returns:
      ``(perm, signs)`` as numpy arrays ``[D]``; use :func:`signed_permutation` to apply.

    Raises:
      ValueError: if the statistics are not mirror-consistent, naming the channels.
    """
    perm = np.asarray(perm, np.int64)
    signs = np.asarray(signs, np.float64)
    offsets = np.asarray(offsets, np.float64)
    scale = np.asarray(field.scale, np.float64)
    offset = np.asarray(field.offset, np.float64)
    d = scale.shape[-1]
    if perm.shape != (d,) or signs.shape != (d,) or offsets.shape != (d,):
        raise ValueError(
            f"joint map has shapes perm {perm.shape}, signs {signs.shape}, offsets "
            f"{offsets.shape}; the normaliser has {d} channels"
        )
    # normalise(S(x))[i] = scale_i (s_i x_p + b_i) + offset_i
    #                    = s_i (scale_i/scale_p) (y_p - offset_p) + scale_i b_i + offset_i
    ratio = scale / scale[perm]
    residual = signs * ratio * (-offset[perm]) + scale * offsets + offset
    bad = ~np.isclose(ratio, 1.0, rtol=rtol, atol=0) | ~np.isclose(residual, 0.0, atol=atol)
    if np.any(bad):
        idx = np.flatnonzero(bad).tolist()
        raise ValueError(
            "normaliser is not mirror-consistent for this joint map at channels "
            f"{idx} (scale ratio {ratio[bad].round(6).tolist()}, normalised offset "
            f"{residual[bad].round(6).tolist()}); fit it with fit_normalizer(data, symmetry)"
        )
    return perm.astype(np.int32), signs.astype(np.float32)


def conjugate_op(op: Callable[[Array], Array], field: FieldNormalizer) -> Callable[[Array], Array]:
    """The op acting in normalised space: ``normalize ∘ op ∘ unnormalize``.

    If ``op`` looks like a joint map (has ``perm``, ``signs``, ``offsets`` attributes, as
    ``equibim_jax.symmetry.JointMap`` does), the exact signed permutation is returned
    (checked by :func:`mirror_in_normalized_space`), so the op is exactly linear and an
    exact involution in floating point. Otherwise the composition is returned, which is
    correct for any op (e.g. a point-cloud reflection) up to float rounding.

    Args:
      op: raw-space op ``[..., D] -> [..., D]``. field: that field's normaliser.
    Returns:
      normalised-space op ``[..., D] -> [..., D]``.
    """
    if all(hasattr(op, a) for a in ("perm", "signs", "offsets")):
        perm, signs = mirror_in_normalized_space(op.perm, op.signs, op.offsets, field)
        return signed_permutation(perm, signs)
    return lambda y: field.normalize(op(field.unnormalize(y)))


def normalized_symmetry(symmetry: Any, normalizer: Normalizer, names=None) -> dict:
    """Per-field normalised-space ops ``{field: op}`` for the fields in ``names``.

    Args:
      symmetry: the raw-space mirror (mapping, object with ``.ops``, or ``dict -> dict``).
      normalizer: a normaliser fitted with this symmetry.
      names: fields to convert; defaults to all fields of ``normalizer``.
    Returns:
      ``{field: op}`` with each ``op: [..., D] -> [..., D]`` in normalised space; feed it
      to the training losses.
    """
    get_op = _as_field_ops(symmetry)
    out = {}
    passthrough = getattr(symmetry, "passthrough", ())
    for name in names if names is not None else normalizer.fields:
        if name in passthrough:
            out[name] = lambda y: y
            continue
        op = get_op(name)
        if op is None:
            raise ValueError(f"symmetry has no op for field {name!r}")
        out[name] = conjugate_op(op, normalizer.fields[name])
    return out
