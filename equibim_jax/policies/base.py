"""The policy interface and the policy registry.

A policy is a :class:`Policy`: a named tuple of pure functions over one config, in the
style of optax's ``GradientTransformation``. The train step, ``L_sym``, the rollout,
checkpoint loading and the command line use only these functions, so a new policy is one
module (its config dataclass and a factory returning a :class:`Policy`) plus one
:func:`register_policy` line.

Every array the functions see is in normalised units (the data pipeline normalises before,
and unnormalises after). ``sym`` is the normalised-space mirror: a mapping
``{field: op}`` with an op per observation field and one for the action field, each op
acting on trailing axes (``equibim_jax.data.normalized_symmetry`` builds it).

How ``L_sym`` uses a policy (written once, in ``equibim_jax.training.losses``)::

    inputs, targets = policy.prepare(batch, key)          # the randomness is drawn here
    pred   = policy.apply(params, inputs)                  # network pass
    pred_m = policy.apply(params, policy.mirror_inputs(sym, inputs))
    L_sym  = || policy.sym_view(S inputs, pred_m) - policy.mirror_view(sym, policy.sym_view(inputs, pred)) ||

Both passes run as one concatenated batch.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Annotated, Any, ClassVar, NamedTuple

import jax
import tyro

Array = Any
Params = Any
Sym = Mapping[str, Callable[[Array], Array]]

__all__ = [
    "PolicyConfig",
    "Policy",
    "register_policy",
    "policy_names",
    "policy_config_class",
    "make_policy",
    "predict_action",
    "tree_concat",
    "tree_take",
]


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """Fields every policy config has (frozen, hashable; subclass it per policy).

    Attributes:
      obs_horizon: ``To``, observation frames the policy reads.
      pred_horizon: ``Tp``, predicted action steps.
      action_horizon: ``Ta``, steps executed per prediction, starting at index ``To - 1``.
      action_key: name of the action field in batches.
      action_dim: ``A``; set from the data by :meth:`with_data` (``None`` until then).
      state_dim: width of the state observation; set from the data (``None`` until then).
    """

    name: ClassVar[str] = ""
    obs_horizon: int = 2
    pred_horizon: int = 16
    action_horizon: int = 8
    action_key: str = "action"
    action_dim: Annotated[int | None, tyro.conf.Suppress] = None
    state_dim: Annotated[int | None, tyro.conf.Suppress] = None

    def __post_init__(self):
        for name in ("obs_horizon", "pred_horizon", "action_horizon"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{type(self).__name__}.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("action_dim", "state_dim"):
            v = getattr(self, name)
            if v is not None and int(v) < 1:
                raise ValueError(f"{type(self).__name__}.{name} must be >= 1 or None, got {v}")
        if self.obs_horizon - 1 + self.action_horizon > self.pred_horizon:
            raise ValueError(
                f"{type(self).__name__}: obs_horizon - 1 + action_horizon = "
                f"{self.obs_horizon - 1 + self.action_horizon} exceeds pred_horizon="
                f"{self.pred_horizon}; the executed actions must lie inside the prediction"
            )
        if self.action_key in self.obs_keys:
            raise ValueError(f"{type(self).__name__}.action_key {self.action_key!r} is also an observation key")

    @property
    def obs_keys(self) -> tuple[str, ...]:
        """Observation fields the policy reads (override per policy)."""
        return ()

    @property
    def state_key(self) -> str | None:
        """The observation field whose width is ``state_dim`` (None: no such field)."""
        return None

    def unresolved(self) -> list[str]:
        """Names of the data-dependent fields still unset (``with_data`` sets them)."""
        out = ["action_dim"] if self.action_dim is None else []
        if self.state_key is not None and self.state_dim is None:
            out.append("state_dim")
        return out

    def with_data(self, action_dim: int, obs_dims: Mapping[str, int],
                  obs_shapes: Mapping[str, tuple[int, ...]] | None = None):
        """This config with ``action_dim`` and ``state_dim`` taken from the data.

        Args:
          action_dim: width of the action field.
          obs_dims: ``{field: width of its last axis}`` of the available observations.
          obs_shapes: ``{field: shape of one frame}``; policies that size themselves from
            more than the last axis (image policies) read it.
        Raises:
          ValueError: the data lack a field the policy reads.
        """
        missing = [k for k in self.obs_keys if k not in obs_dims]
        if missing:
            raise ValueError(f"policy {self.name!r} reads observation fields {missing}, which the "
                             f"data do not have (they have {sorted(obs_dims)})")
        state_dim = int(obs_dims[self.state_key]) if self.state_key is not None else None
        return dataclasses.replace(self, action_dim=int(action_dim), state_dim=state_dim)


class Policy(NamedTuple):
    """A policy as pure functions (see the module docstring for how ``L_sym`` uses them).

    Attributes:
      config: the (resolved) :class:`PolicyConfig` subclass instance.
      init: ``key -> params``.
      prepare: ``(batch, key) -> (inputs, targets)``. ``batch`` is
        ``{action_key: [B, Tp, A], obs field: [B, To, ...]}``; ``inputs`` and ``targets``
        are dicts of ``[B, ...]`` arrays (everything random in the loss is drawn here).
      apply: ``(params, inputs) -> pred``, a pytree of ``[B, ...]`` arrays.
      bc_loss: ``(pred, targets) -> scalar``, the imitation loss.
      mirror_inputs: ``(sym, inputs) -> inputs`` of the mirrored sample, so that an
        equivariant network gives the mirrored prediction.
      mirror_targets: ``(sym, targets) -> targets`` of the mirrored sample (mirror
        augmentation trains on them).
      sym_view: ``(inputs, pred) -> [B, ...]``, what ``L_sym`` compares.
      mirror_view: ``(sym, view) -> view``, how ``S`` acts on it.
      sample: ``(params, obs, key, noise_op) -> [B, Tp, A]`` normalised action chunks from
        ``obs = {field: [B, To, ...]}``. ``noise_op`` (or None) is applied to any noise the
        sampler draws, e.g. the action mirror, so that an equivariant policy maps
        mirrored observations to the mirrored sample.
    """

    config: PolicyConfig
    init: Callable[[Array], Params]
    prepare: Callable[[Mapping[str, Array], Array], tuple[dict, dict]]
    apply: Callable[[Params, Mapping[str, Array]], Any]
    bc_loss: Callable[[Any, Mapping[str, Array]], Array]
    mirror_inputs: Callable[[Sym, Mapping[str, Array]], dict]
    mirror_targets: Callable[[Sym, Mapping[str, Array]], dict]
    sym_view: Callable[[Mapping[str, Array], Any], Array]
    mirror_view: Callable[[Sym, Array], Array]
    sample: Callable[..., Array]


_REGISTRY: dict[str, tuple[type, Callable[[Any], Policy]]] = {}


def register_policy(name: str, config_cls: type, factory: Callable[[Any], Policy]) -> None:
    """Register ``factory(config) -> Policy`` under ``name``.

    Args:
      name: registry name (``config_cls.name`` must equal it).
      config_cls: the policy's frozen config dataclass, a :class:`PolicyConfig` subclass.
      factory: builds the policy from a resolved config (dims set).
    Raises:
      ValueError: the name is taken by another policy, or does not match the config class.
    """
    if not (isinstance(config_cls, type) and issubclass(config_cls, PolicyConfig)):
        raise ValueError(f"register_policy({name!r}): config class must subclass PolicyConfig")
    if config_cls.name != name:
        raise ValueError(f"register_policy({name!r}): {config_cls.__name__}.name is {config_cls.name!r}")
    if name in _REGISTRY and _REGISTRY[name] != (config_cls, factory):
        raise ValueError(f"policy {name!r} is already registered")
    _REGISTRY[name] = (config_cls, factory)


def policy_names() -> list[str]:
    """Registered policy names, sorted."""
    return sorted(_REGISTRY)


def policy_config_class(name: str) -> type:
    """The config class of a registered policy."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown policy {name!r}; registered policies: {policy_names()}")
    return _REGISTRY[name][0]


def make_policy(name: str, config: PolicyConfig | None = None) -> Policy:
    """Build a registered policy.

    Args:
      name: a name from :func:`policy_names`.
      config: its config with ``action_dim`` (and ``state_dim`` where the policy reads a
        state) set, e.g. by ``config.with_data(...)``; ``None`` is an error for the same
        reason.
    Returns:
      the :class:`Policy`. Equal configs give the same object (memoised), so states and
      compiled steps built from them are interchangeable.
    Raises:
      ValueError: unknown name, a config of another policy, or unresolved dims.
    """
    cls = policy_config_class(name)
    if config is None:
        raise ValueError(f"make_policy({name!r}) needs a config with the data's dims "
                         f"(e.g. {cls.__name__}().with_data(action_dim, obs_dims))")
    if type(config) is not cls:
        raise ValueError(f"policy {name!r} takes a {cls.__name__}, got {type(config).__name__}")
    unresolved = config.unresolved()
    if unresolved:
        raise ValueError(f"{cls.__name__} has unresolved data-dependent fields {unresolved}; "
                         f"call config.with_data(...) first")
    return _make_cached(name, config)


@functools.lru_cache(maxsize=64)
def _make_cached(name: str, config: PolicyConfig) -> Policy:
    return _REGISTRY[name][1](config)


def tree_take(tree: Any, n: int) -> Any:
    """The first ``n`` entries along axis 0 of every leaf."""
    return jax.tree.map(lambda x: x[:n], tree)


def tree_concat(a: Any, b: Any) -> Any:
    """Concatenate two pytrees of the same structure along axis 0."""
    import jax.numpy as jnp

    return jax.tree.map(lambda x, y: jnp.concatenate([x, y], axis=0), a, b)


def predict_action(policy: Policy, params: Params, obs_raw: Mapping[str, Array], key: Array,
                   normalizer: Any, noise_op: Callable[[Array], Array] | None = None) -> dict:
    """Closed-loop inference: normalise, sample, unnormalise, cut the executed window.

    Args:
      policy: the :class:`Policy`. params: its parameters.
      obs_raw: ``{field: [B, To, ...]}`` raw observations (at least ``config.obs_keys``).
      key: PRNG key of the sampler.
      normalizer: an ``equibim_jax.data.Normalizer`` with the action and obs fields.
      noise_op: passed to ``policy.sample`` (normalised action space).
    Returns:
      ``{"action_pred": [B, Tp, A], "action": [B, Ta, A]}`` in raw units; ``"action"``
      starts at index ``To - 1`` (the current frame).
    """
    cfg = policy.config
    obs = normalizer.normalize({k: obs_raw[k] for k in cfg.obs_keys})
    a = policy.sample(params, obs, key, noise_op)
    a = normalizer.fields[cfg.action_key].unnormalize(a)
    start = cfg.obs_horizon - 1
    return {"action_pred": a, "action": a[:, start : start + cfg.action_horizon]}
