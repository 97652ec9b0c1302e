"""The config tree: task, evaluation and run configs, and their JSON form.

Every setting is a field of one frozen dataclass, with one default:

* :class:`TaskConfig`: a registered task and its options (``make_env`` options: env
  settings such as ``obs`` or ``n_points``, and the task's own, such as ``side``);
* a policy config per policy (``equibim_jax.policies``; its registry name is ``name``);
* :class:`~equibim_jax.training.TrainConfig`;
* :class:`EvalConfig`.

The command line parses these same dataclasses (with tyro), and every run writes its
resolved config to ``config.json``; :func:`load_config` reads such a file back into the
dataclasses, so a run can be repeated from it. The files in the repository's ``tasks/``
folder are configs in this format.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from equibim_jax._io import atomic_write_json

__all__ = [
    "TaskConfig",
    "EvalConfig",
    "ConfigError",
    "config_to_dict",
    "config_from_dict",
    "save_config",
    "load_config",
    "find_config",
]


class ConfigError(ValueError):
    """A config file or value is missing, malformed or invalid."""


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """A task of the registry and its options.

    Attributes:
      name: a name from ``equibim_jax.task_names()``.
      options: keyword options of ``equibim_jax.make_env(name, **options)``: env settings
        (``obs``, ``action``, ``n_points``, ``episode_length``, ...) and the task's own
        (e.g. ``side``). Unset options take the task's defaults.
    """

    name: str = "place_empty_cup"
    options: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.options, Mapping):
            raise ConfigError(f"TaskConfig.options must be a mapping, got {type(self.options).__name__}")
        object.__setattr__(self, "options", dict(self.options))

    def __hash__(self):
        return hash((self.name, json.dumps(self.options, sort_keys=True, default=str)))

    def make_env(self):
        """The task's env with these options (checked by the task registry)."""
        from equibim_jax.tasks import make_env

        return make_env(self.name, **self.options)


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Closed-loop evaluation settings.

    Attributes:
      episodes: episodes per side. Episode ``i`` of the mirrored side starts from the
        mirror image of episode ``i``'s initial state (paired).
      seed: seed of the episode keys.
      batch: episodes per compiled batch.
      mirror_noise: the mirrored episode also samples with the mirrored policy noise, so
        the pair is mirrored in all its randomness.
      temporal_ensemble: ``None``: execute ``Ta`` actions of each predicted chunk. A float
        ``k`` (ACT uses 0.01): ACT's temporal ensembling, the policy queried every step
        and the overlapping predictions averaged with weights ``exp(-k i)``.
    """

    episodes: int = 32
    seed: int = 1
    batch: int = 32
    mirror_noise: bool = False
    temporal_ensemble: float | None = None

    def __post_init__(self):
        if self.episodes < 1 or self.batch < 1:
            raise ConfigError(f"EvalConfig: episodes and batch must be >= 1, got {self.episodes}, {self.batch}")
        if self.temporal_ensemble is not None and not math.isfinite(self.temporal_ensemble):
            raise ConfigError(f"EvalConfig.temporal_ensemble must be a finite float or None, "
                              f"got {self.temporal_ensemble}")
        if self.temporal_ensemble is not None and self.mirror_noise:
            raise ConfigError("EvalConfig: mirror_noise and temporal_ensemble cannot be combined")


def config_to_dict(config: Any) -> Any:
    """JSON-ready form of a (nested) dataclass config, or of a dict of them.

    Tuples become lists and dataclasses dicts; a policy config also records its registry
    ``name``, so :func:`config_from_dict` can rebuild the right class.
    """
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        out = {}
        name = getattr(type(config), "name", None)
        from equibim_jax.policies.base import PolicyConfig

        if isinstance(config, PolicyConfig):
            out["name"] = name
        out.update({f.name: config_to_dict(getattr(config, f.name)) for f in dataclasses.fields(config)})
        return out
    if isinstance(config, Mapping):
        return {str(k): config_to_dict(v) for k, v in config.items()}
    if isinstance(config, (list, tuple)):
        return [config_to_dict(v) for v in config]
    if config is None or isinstance(config, (bool, int, float, str)):
        return config
    raise TypeError(f"config value {config!r} of type {type(config).__name__} is not JSON-able")


def config_from_dict(cls: type, data: Mapping[str, Any]) -> Any:
    """Rebuild a frozen-dataclass config of type ``cls`` from :func:`config_to_dict` output.

    Nested dataclass fields are rebuilt from their type annotations; a field typed as the
    policy-config base class is rebuilt as the registered class its ``name`` names. Lists
    become tuples where the field is a tuple. Each class's ``__post_init__`` validates.

    Raises:
      ConfigError: unknown, missing or invalid fields.
    """
    from equibim_jax.policies.base import PolicyConfig, policy_config_class

    if not isinstance(data, Mapping):
        raise ConfigError(f"{cls.__name__}: expected a mapping, got {type(data).__name__}")
    data = dict(data)
    if isinstance(cls, type) and issubclass(cls, PolicyConfig):
        name = data.pop("name", None)
        if cls is PolicyConfig:
            if name is None:
                raise ConfigError("a policy config needs its registry 'name'")
            try:
                cls = policy_config_class(name)
            except ValueError as e:
                raise ConfigError(str(e)) from None
        elif name is not None and name != cls.name:
            raise ConfigError(f"{cls.__name__} is policy {cls.name!r}, the config says {name!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ConfigError(f"{cls.__name__}: unknown config fields {sorted(unknown)}; valid: {sorted(names)}")
    try:
        kwargs = {name: _from_json(hints[name], value) for name, value in data.items()}
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{cls.__name__}: {e}") from None


def _from_json(tp: Any, value: Any) -> Any:
    if value is None:
        return None
    if dataclasses.is_dataclass(tp):
        return config_from_dict(tp, value)
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            if arg is not type(None) and dataclasses.is_dataclass(arg) and isinstance(value, Mapping):
                return config_from_dict(arg, value)
        return _tuples(value) if isinstance(value, list) else value
    if origin is tuple or tp is tuple:
        return _tuples(value)
    return value


def _tuples(value: Any) -> Any:
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def save_config(path: str | os.PathLike, config: Mapping[str, Any]) -> None:
    """Write a config tree (a dict of dataclasses and plain values) atomically as JSON."""
    atomic_write_json(path, config_to_dict(config))


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """Read a JSON config file.

    Raises:
      ConfigError: the file is missing or not a JSON object.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"no config file at {path}")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path} is not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must hold a JSON object, got {type(data).__name__}")
    return data


def find_config(path: str | os.PathLike) -> Path:
    """Resolve a config path: as given, else relative to the repository root (for the
    ``tasks/*.json`` files of an editable install).

    Raises:
      ConfigError: not found in either place.
    """
    p = Path(path)
    if p.is_file():
        return p
    repo = Path(__file__).resolve().parent.parent
    if not p.is_absolute() and (repo / p).is_file():
        return repo / p
    raise ConfigError(f"no config file at {p} (nor at {repo / p})")
