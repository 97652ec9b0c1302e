"""Losses for the diffusion policy: behaviour cloning (ε-MSE) and the symmetry loss.

All in normalised space. ``S`` is given per field: ``{field: op}`` (or an object with an
``ops`` mapping, or a callable ``dict -> dict``), each op acting on trailing axes. The
action op ``S_a`` must be *linear* in normalised space (a signed permutation, which a
mirror-consistent normaliser guarantees): the mirrored branch uses the mirrored noise
``S_a eps`` and relies on ``S_a add_noise(a0, eps, k) == add_noise(S_a a0, S_a eps, k)``.

``L_sym`` (EquiBim, for an ε-predictor): at the same ``k`` and with the same noise
mirrored, ``eps(S_a a_k, k, S O) ≈ S_a eps(a_k, k, O)``. Both branches go through the
network as one concatenated batch ``[2B, ...]``: one forward and one backward pass at
twice the batch, which XLA runs more efficiently than two passes.

Whether gradients should flow through the ``S_a eps(a_k, k, O)`` side (the "target") of
``L_sym`` is a choice: by default both sides get gradients (the loss is symmetric in the
two branches); ``stop_gradient=True`` treats the original branch as a fixed target, so
``L_sym`` only pulls the mirrored prediction.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp

from equibim_jax.policies.diffusion import DiffusionSchedule, add_noise

Array = Any
ApplyFn = Callable[[Any, Array, Array, Mapping[str, Array]], Array]

__all__ = ["field_op", "mirror_batch", "bc_loss", "sym_loss", "diffusion_loss", "concat_branches"]


def field_op(symmetry: Any, name: str) -> Callable[[Array], Array]:
    """The op of one field from a symmetry in any accepted form.

    Args:
      symmetry: ``{field: op}``, an object with an ``ops`` mapping (and optionally a
        ``passthrough`` tuple of unchanged fields), or ``dict -> dict``.
      name: field name.
    Returns:
      ``op: [..., D] -> [..., D]``.
    Raises:
      KeyError: if a mapping has no op for ``name``.
    """
    ops = getattr(symmetry, "ops", symmetry)
    if name in getattr(symmetry, "passthrough", ()):
        return lambda x: x
    if isinstance(ops, Mapping):
        if name not in ops:
            raise KeyError(f"symmetry has no op for field {name!r}; it has {sorted(ops)}")
        return ops[name]
    if callable(symmetry):
        return lambda x: symmetry({name: x})[name]
    raise TypeError(f"unsupported symmetry type {type(symmetry).__name__}")


def mirror_batch(symmetry: Any, batch: Mapping[str, Array], names=None) -> dict[str, Array]:
    """Apply ``S`` field by field: ``{f: [B, ...]} -> {f: [B, ...]}`` for ``f`` in ``names``."""
    names = list(batch) if names is None else list(names)
    return {n: field_op(symmetry, n)(batch[n]) for n in names}


def concat_branches(a: Mapping[str, Array], b: Mapping[str, Array]) -> dict[str, Array]:
    """Stack two batches along axis 0: ``{f: [B, ...]}, {f: [B, ...]} -> {f: [2B, ...]}``."""
    return {k: jnp.concatenate([a[k], b[k]], axis=0) for k in a}


def bc_loss(eps_pred: Array, noise: Array) -> Array:
    """ε-prediction MSE: ``mean((eps_pred - noise) ** 2)`` over ``[B, Tp, A]`` -> scalar."""
    return jnp.mean(jnp.square(eps_pred - noise))


SYM_NORMS = ("mse", "l2")
SYM_SPACES = ("eps", "x0")


def predict_x0(schedule: DiffusionSchedule, a_k: Array, eps: Array, k: Array,
               clip: bool = True) -> Array:
    """The clean action the noise prediction implies: ``(a_k - sqrt(1 - abar_k) eps) /
    sqrt(abar_k)``, clipped to ``[-1, 1]`` as DDIM clips it (``clip``)."""
    acp = schedule.alphas_cumprod[k].reshape((-1,) + (1,) * (a_k.ndim - 1))
    x0 = (a_k - jnp.sqrt(1.0 - acp) * eps) / jnp.sqrt(acp)
    return jnp.clip(x0, -1.0, 1.0) if clip else x0


def _sym_term(eps_orig: Array, eps_mirr: Array, action_op, stop_gradient: bool,
              norm: str = "mse") -> Array:
    """The equivariance residual ``e = eps_mirr - S_a eps_orig`` reduced to a scalar.

    ``norm="mse"``: ``mean(e ** 2)`` over all elements. ``norm="l2"``: the paper's
    unsquared form, the mean over samples of ``||e_i||_2 / sqrt(D)`` (``D = Tp * A``
    elements per sample, so both forms are on the scale of one element). Its gradient does
    not shrink with the residual, so it keeps pulling where MSE has gone flat.
    """
    if norm not in SYM_NORMS:
        raise ValueError(f"sym norm must be one of {SYM_NORMS}, got {norm!r}")
    target = action_op(eps_orig)
    if stop_gradient:
        target = jax.lax.stop_gradient(target)
    e = eps_mirr - target
    if norm == "mse":
        return jnp.mean(jnp.square(e))
    e = e.reshape(e.shape[0], -1)
    # sqrt(x + tiny): finite gradient at an exactly equivariant prediction (e == 0).
    return jnp.mean(jnp.sqrt(jnp.mean(jnp.square(e), axis=-1) + 1e-12))


def _both_branches(apply_fn: ApplyFn, params: Any, a_k: Array, k: Array,
                   obs: Mapping[str, Array], symmetry: Any, s_a, n: int | None = None):
    """One network pass over ``[B + n]``: the ``B`` originals, then the first ``n`` mirrored
    (``n = B`` by default). Returns ``(eps_orig [B, ...], eps_mirr [n, ...])``."""
    b = a_k.shape[0]
    n = b if n is None else n
    x = jnp.concatenate([a_k, s_a(a_k[:n])], axis=0)
    o = concat_branches(obs, mirror_batch(symmetry, {f: v[:n] for f, v in obs.items()}))
    eps = apply_fn(params, x, jnp.concatenate([k, k[:n]], axis=0), o)
    return eps[:b], eps[b:]


def sym_loss(
    apply_fn: ApplyFn,
    params: Any,
    noisy_actions: Array,
    k: Array,
    obs: Mapping[str, Array],
    symmetry: Any,
    *,
    action_key: str = "action",
    stop_gradient: bool = False,
    norm: str = "mse",
) -> Array:
    """``L_sym = mean || eps(S_a a_k, k, S O) - S_a eps(a_k, k, O) ||^2`` (standalone).

    Args:
      apply_fn: ``(params, noisy_actions [B, Tp, A], k [B], obs) -> eps [B, Tp, A]``.
      params: network parameters.
      noisy_actions: ``[B, Tp, A]`` normalised noisy actions ``a_k``.
      k: ``[B]`` int diffusion steps.
      obs: ``{field: [B, To, ...]}`` normalised observations; every field is mirrored.
      symmetry: normalised-space ``S`` with an op for ``action_key`` and each obs field.
      action_key: name of the action op.
      stop_gradient: stop gradients through ``S_a eps(a_k, k, O)``.
      norm: ``"mse"`` (squared, mean over elements) or ``"l2"`` (unsquared per-sample
        norm, as the paper writes ``L_sym``); see :func:`_sym_term`.
    Returns:
      scalar (for ``"mse"`` the mean over ``B * Tp * A`` elements).
    """
    s_a = field_op(symmetry, action_key)
    eps_orig, eps_mirr = _both_branches(apply_fn, params, noisy_actions, k, obs, symmetry, s_a)
    return _sym_term(eps_orig, eps_mirr, s_a, stop_gradient, norm)


def diffusion_loss(
    apply_fn: ApplyFn,
    params: Any,
    batch: Mapping[str, Array],
    key: Array,
    schedule: DiffusionSchedule,
    symmetry: Any = None,
    *,
    sym_weight: float = 0.0,
    stop_gradient: bool = False,
    mirror_augment: bool = False,
    action_key: str = "action",
    sym_norm: str = "mse",
    sym_scale: Array | float = 1.0,
    sym_batch: int | None = None,
    sym_space: str = "eps",
) -> tuple[Array, dict[str, Array]]:
    """Total loss ``bc + sym_scale * sym_weight * sym`` on one batch, with named terms.

    The mirrored branch runs (in the same concatenated batch) when ``sym_weight > 0`` or
    ``mirror_augment``; otherwise only the original batch goes through the network and
    ``sym`` is reported as 0.

    Args:
      apply_fn: ``(params, [N, Tp, A], [N], obs) -> [N, Tp, A]``.
      params: network parameters.
      batch: ``{action_key: [B, Tp, A], obs fields: [B, To, ...]}`` normalised.
      key: PRNG key for the noise and the diffusion steps.
      schedule: DDPM schedule (``K`` steps).
      symmetry: normalised-space ``S`` (needed if the mirrored branch runs).
      sym_weight: ``lambda``, weight of ``L_sym``; a Python float (it decides statically
        whether the mirrored branch is built).
      stop_gradient: see :func:`sym_loss`.
      mirror_augment: also add BC on the mirrored branch (mirror data augmentation);
        ``bc`` is then the mean over both branches.
      action_key: name of the action field.
      sym_norm: ``"mse"`` or ``"l2"`` (see :func:`_sym_term`).
      sym_scale: multiplier of ``sym_weight``; may be traced (a warm-up schedule).
      sym_batch: how many samples of the batch (the first ``sym_batch``; batches are drawn
        at random) also go through the mirrored branch; ``None``: all ``B``. ``L_sym`` (and
        the mirrored BC term of ``mirror_augment``) is then the mean over those samples, an
        unbiased estimate of the same expectation for ``1 + sym_batch / B`` of the
        network cost instead of 2x. BC always uses all ``B`` samples.
      sym_space: ``"eps"`` compares the noise predictions (DESIGN.md's form); ``"x0"``
        compares the clean actions they imply (:func:`predict_x0`, clipped as in DDIM),
        the policy's action output at step ``k``. For unclipped elements the ``x0``
        residual is the ``eps`` residual times ``sqrt((1 - abar_k) / abar_k)``, so it
        weights the high-noise steps, where DDIM decides the coarse action, far more.
    Returns:
      ``(total, {"bc", "sym", "total"})``, all scalars.
    """
    k_noise, k_step = jax.random.split(key)
    a0 = batch[action_key]
    obs = {f: v for f, v in batch.items() if f != action_key}
    b = a0.shape[0]
    noise = jax.random.normal(k_noise, a0.shape, a0.dtype)
    k = jax.random.randint(k_step, (b,), 0, schedule.alphas_cumprod.shape[0])
    a_k = add_noise(schedule, a0, noise, k)
    if not (mirror_augment or sym_weight > 0):
        bc = bc_loss(apply_fn(params, a_k, k, obs), noise)
        return bc, {"bc": bc, "sym": jnp.zeros_like(bc), "total": bc}
    if symmetry is None:
        raise ValueError("diffusion_loss: sym_weight > 0 or mirror_augment needs a symmetry")
    n = b if sym_batch is None else int(sym_batch)
    if not 1 <= n <= b:
        raise ValueError(f"diffusion_loss: sym_batch must be in [1, B={b}], got {sym_batch}")
    s_a = field_op(symmetry, action_key)
    # Same k, same noise mirrored: S_a a_k == add_noise(S_a a0, S_a noise, k) as S_a is linear.
    eps_orig, eps_mirr = _both_branches(apply_fn, params, a_k, k, obs, symmetry, s_a, n)
    bc = bc_loss(eps_orig, noise)
    if mirror_augment:
        bc = 0.5 * (bc + bc_loss(eps_mirr, s_a(noise[:n])))
    if sym_space not in SYM_SPACES:
        raise ValueError(f"sym space must be one of {SYM_SPACES}, got {sym_space!r}")
    if sym_space == "x0":
        # S_a is a signed permutation in normalised space: it commutes with the clip.
        sym = _sym_term(predict_x0(schedule, a_k[:n], eps_orig[:n], k[:n]),
                        predict_x0(schedule, s_a(a_k[:n]), eps_mirr, k[:n]), s_a, stop_gradient, sym_norm)
    else:
        sym = _sym_term(eps_orig[:n], eps_mirr, s_a, stop_gradient, sym_norm)
    total = bc + (sym_scale * sym_weight) * sym
    return total, {"bc": bc, "sym": sym, "total": total}
