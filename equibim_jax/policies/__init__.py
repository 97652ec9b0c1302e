"""Policies behind one interface (:class:`Policy`) and a registry.

``policy_names()`` lists the registered policies and ``make_policy(name, config)`` builds
one. A new policy is one module (a :class:`PolicyConfig` subclass and a factory returning
a :class:`Policy`) plus one :func:`register_policy` line below.
"""

from equibim_jax.policies.base import (
    Policy,
    PolicyConfig,
    make_policy,
    policy_config_class,
    policy_names,
    predict_action,
    register_policy,
)
from equibim_jax.policies.dp3 import DP3Config, make_dp3
from equibim_jax.policies.encoders import EncoderConfig
from equibim_jax.policies.unet1d import UNetConfig

register_policy("dp3", DP3Config, make_dp3)

__all__ = [
    "DP3Config",
    "EncoderConfig",
    "Policy",
    "PolicyConfig",
    "UNetConfig",
    "make_policy",
    "policy_config_class",
    "policy_names",
    "predict_action",
    "register_policy",
]
