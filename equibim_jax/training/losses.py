"""Losses of any :class:`~equibim_jax.policies.Policy`: behaviour cloning and ``L_sym``.

All in normalised space. ``S`` is given per field, ``{field: op}`` (or an object with an
``ops`` mapping), with an op for the action field that is *linear* in normalised space (a
signed permutation, which a mirror-consistent normaliser guarantees).

``L_sym`` (EquiBim) compares the policy's prediction on mirrored inputs with the mirror of
its prediction on the original inputs: for sample ``i`` the residual is

    e_i = v(S x_i) - S v(x_i),    v = policy.sym_view(inputs, policy.apply(params, inputs)),

with ``D`` elements per sample (``Tp * A`` for an action chunk) and ``N`` mirrored samples.
The forms (:data:`SYM_NORMS`):

* ``"mse"``: ``(1 / (N D)) sum_i ||e_i||^2``, the squared error. With ``stop_gradient`` and
  ``lambda = 0.1`` this is the form of the paper's public code (ACT).
* ``"rms"``: ``(1 / N) sum_i ||e_i||_2 / sqrt(D)``, each sample's root-mean-square
  residual: on the scale of one element, so at the same ``lambda`` it weighs ``L_sym``
  ``sqrt(D)`` times less than ``"l2"``.
* ``"l2"``: ``(1 / N) sum_i ||e_i||_2``, the unsquared per-sample norm the paper writes
  (it gives no ``lambda``).

``stop_gradient`` treats ``S v(x)`` as a fixed target, so ``L_sym`` pulls only the mirrored
prediction. Both branches go through the network as one concatenated batch ``[B + N]``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp

from equibim_jax.policies.base import Policy, tree_concat, tree_take

Array = Any

__all__ = ["SYM_NORMS", "as_ops", "mirror_batch", "sym_residual_norm", "both_branches",
           "sym_loss", "policy_loss", "equivariance_error"]

SYM_NORMS = ("mse", "rms", "l2")


def as_ops(symmetry: Any) -> Mapping[str, Callable[[Array], Array]]:
    """``{field: op}`` from a mapping or an object with an ``ops`` mapping."""
    ops = getattr(symmetry, "ops", symmetry)
    if not isinstance(ops, Mapping):
        raise TypeError(f"a symmetry must be a mapping {{field: op}} or have .ops, got {type(symmetry).__name__}")
    return ops


def mirror_batch(symmetry: Any, batch: Mapping[str, Array], names=None) -> dict[str, Array]:
    """Apply ``S`` field by field: ``{f: [B, ...]} -> {f: [B, ...]}`` for ``f`` in ``names``.

    Raises:
      KeyError: ``S`` has no op for one of the fields.
    """
    ops = as_ops(symmetry)
    names = list(batch) if names is None else list(names)
    missing = [n for n in names if n not in ops]
    if missing:
        raise KeyError(f"symmetry has no op for field(s) {missing}; it has {sorted(ops)}")
    return {n: ops[n](batch[n]) for n in names}


def sym_residual_norm(e: Array, norm: str) -> Array:
    """Reduce the residual ``e [N, ...]`` to a scalar in the form ``norm`` (module docstring)."""
    if norm not in SYM_NORMS:
        raise ValueError(f"sym norm must be one of {SYM_NORMS}, got {norm!r}")
    if norm == "mse":
        return jnp.mean(jnp.square(e))
    e = e.reshape(e.shape[0], -1)
    sq = jnp.sum(jnp.square(e), axis=-1)
    if norm == "rms":
        sq = sq / e.shape[1]
    # sqrt(x + tiny): a finite gradient at an exactly equivariant prediction (e == 0).
    return jnp.mean(jnp.sqrt(sq + 1e-12))


def both_branches(policy: Policy, params: Any, inputs: Mapping[str, Any], sym: Any,
                  n: int | None = None) -> tuple[Any, Any, Any]:
    """One network pass over ``[B + n]``: the ``B`` inputs, then the first ``n`` mirrored.

    Returns:
      ``(pred [B, ...], mirrored inputs [n, ...], pred_m [n, ...])``.
    """
    b = jax.tree.leaves(inputs)[0].shape[0]
    n = b if n is None else int(n)
    if not 1 <= n <= b:
        raise ValueError(f"the mirrored branch needs 1 <= n <= B={b}, got {n}")
    m_inputs = policy.mirror_inputs(as_ops(sym), tree_take(inputs, n))
    pred = policy.apply(params, tree_concat(inputs, m_inputs))
    return tree_take(pred, b), m_inputs, jax.tree.map(lambda x: x[b:], pred)


def _sym_term(policy: Policy, sym: Any, inputs, pred, m_inputs, pred_m, n: int,
              stop_gradient: bool, norm: str) -> Array:
    target = policy.mirror_view(as_ops(sym), policy.sym_view(tree_take(inputs, n), tree_take(pred, n)))
    if stop_gradient:
        target = jax.lax.stop_gradient(target)
    return sym_residual_norm(policy.sym_view(m_inputs, pred_m) - target, norm)


def sym_loss(policy: Policy, params: Any, batch: Mapping[str, Array], key: Array, sym: Any, *,
             stop_gradient: bool = False, norm: str = "mse") -> Array:
    """``L_sym`` alone on one batch (module docstring), all samples mirrored.

    Args:
      policy: the policy. params: its parameters.
      batch: ``{action_key: [B, Tp, A], obs fields: [B, To, ...]}`` normalised.
      key: PRNG key for ``policy.prepare``.
      sym: normalised-space ``S`` with an op for the action and each observation field.
    Returns:
      scalar.
    """
    inputs, _ = policy.prepare(batch, key)
    pred, m_inputs, pred_m = both_branches(policy, params, inputs, sym)
    b = jax.tree.leaves(inputs)[0].shape[0]
    return _sym_term(policy, sym, inputs, pred, m_inputs, pred_m, b, stop_gradient, norm)


def policy_loss(
    policy: Policy,
    params: Any,
    batch: Mapping[str, Array],
    key: Array,
    sym: Any = None,
    *,
    sym_weight: float = 0.0,
    sym_scale: Array | float = 1.0,
    stop_gradient: bool = False,
    norm: str = "mse",
    sym_batch: int | None = None,
    mirror_augment: bool = False,
) -> tuple[Array, dict[str, Array]]:
    """Total loss ``bc + sym_scale * sym_weight * L_sym`` on one batch, with named terms.

    The mirrored branch runs (in the same concatenated batch) when ``sym_weight > 0`` or
    ``mirror_augment``; otherwise only the batch goes through the network and ``sym`` is
    reported as 0.

    Args:
      policy: the policy. params: its parameters.
      batch: ``{action_key: [B, Tp, A], obs fields: [B, To, ...]}`` normalised.
      key: PRNG key for ``policy.prepare``.
      sym: normalised-space ``S`` (needed when the mirrored branch runs).
      sym_weight: ``lambda``; a Python float (it decides statically whether the mirrored
        branch is built).
      sym_scale: multiplier of ``sym_weight``; may be traced (a ramp).
      stop_gradient: ``S v(x)`` is a fixed target.
      norm: form of ``L_sym``, one of :data:`SYM_NORMS`.
      sym_batch: how many samples (the first ones; batches are drawn at random) also go
        through the mirrored branch; ``None``: all ``B``. ``L_sym`` and the mirrored BC term
        are then means over those samples; BC always uses all ``B``.
      mirror_augment: also fit the mirrored samples by BC (mirror data augmentation);
        ``bc`` is then the mean of the two branches' BC losses.
    Returns:
      ``(total, {"bc", "sym", "total"})``, scalars.
    """
    inputs, targets = policy.prepare(batch, key)
    if not (mirror_augment or sym_weight > 0):
        bc = policy.bc_loss(policy.apply(params, inputs), targets)
        return bc, {"bc": bc, "sym": jnp.zeros_like(bc), "total": bc}
    if sym is None:
        raise ValueError("policy_loss: sym_weight > 0 or mirror_augment needs a symmetry")
    b = jax.tree.leaves(inputs)[0].shape[0]
    n = b if sym_batch is None else int(sym_batch)
    if not 1 <= n <= b:
        raise ValueError(f"policy_loss: sym_batch must be in [1, B={b}] or None, got {sym_batch}")
    pred, m_inputs, pred_m = both_branches(policy, params, inputs, sym, n)
    bc = policy.bc_loss(pred, targets)
    if mirror_augment:
        m_targets = policy.mirror_targets(as_ops(sym), tree_take(targets, n))
        bc = 0.5 * (bc + policy.bc_loss(pred_m, m_targets))
    sym_term = _sym_term(policy, sym, inputs, pred, m_inputs, pred_m, n, stop_gradient, norm)
    total = bc + (sym_scale * sym_weight) * sym_term
    return total, {"bc": bc, "sym": sym_term, "total": total}


def equivariance_error(policy: Policy, params: Any, batch: Mapping[str, Array], key: Array,
                       sym: Any) -> Array:
    """Relative equivariance error of what ``L_sym`` compares, on one batch:
    ``sum ||v(S x) - S v(x)||^2 / sum ||v(x)||^2``.

    0 for an exactly equivariant policy; about 2 for unrelated predictions of equal size.
    Fix ``batch`` and ``key`` to track it over training.
    """
    inputs, _ = policy.prepare(batch, key)
    pred, m_inputs, pred_m = both_branches(policy, params, inputs, sym)
    v = policy.sym_view(inputs, pred)
    e = policy.sym_view(m_inputs, pred_m) - policy.mirror_view(as_ops(sym), v)
    return jnp.sum(jnp.square(e)) / jnp.sum(jnp.square(v))
