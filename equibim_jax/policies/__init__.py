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
from equibim_jax.policies.act import ACTConfig, make_act
from equibim_jax.policies.dp import DPConfig, ImageObsConfig, make_dp
from equibim_jax.policies.dp3 import DP3Config, make_dp3
from equibim_jax.policies.encoders import EncoderConfig
from equibim_jax.policies.unet1d import UNetConfig
from equibim_jax.policies.vision import VisionConfig

register_policy("act", ACTConfig, make_act)
register_policy("dp", DPConfig, make_dp)
register_policy("dp3", DP3Config, make_dp3)

__all__ = [
    "ACTConfig",
    "DPConfig",
    "DP3Config",
    "ImageObsConfig",
    "EncoderConfig",
    "Policy",
    "PolicyConfig",
    "UNetConfig",
    "VisionConfig",
    "make_policy",
    "policy_config_class",
    "policy_names",
    "predict_action",
    "register_policy",
]
