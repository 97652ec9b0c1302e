"""The task registry: one :class:`TaskEntry` per task, and ``make_env`` / ``make_expert``.

Example::

    import equibim_jax as eb
    env = eb.make_env("place_empty_cup", side="left", n_points=64)
    expert = eb.make_expert(env)

A task is one module in this package that defines its :class:`~equibim_jax.sim.env.Scene`
(a frozen dataclass whose fields are the task's options) and a module-level
``TASK = TaskEntry(...)``; modules are discovered on first use. Code outside the package
(a test, a notebook) registers a task with :func:`register_task`.

``make_env(task, **options)`` splits the options by name between
:class:`~equibim_jax.sim.env.EnvConfig` fields (``obs``, ``action``, ``n_points``,
``episode_length``, ...) and the scene's fields (e.g. ``side``). Unset env fields take the
task's defaults (``TaskEntry.env_defaults``, its robot, ``episode_length`` = its step
limit, and ``max_contacts`` = :data:`TASK_MAX_CONTACTS`). Option values may be strings (from
a command line); they are converted to the field's type. The env records the task's name
and the full resolved options (``env.task``, ``env.task_options``), which datasets and runs
store, so that generic code rebuilds the same env without knowing what the options mean.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import pkgutil
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any

from equibim_jax.sim.env import Env, EnvConfig, Scene

__all__ = ["TaskEntry", "register_task", "task_names", "task_entry", "task_options", "make_env",
           "make_scene", "make_expert"]

_ENV_FIELDS = tuple(f.name for f in dataclasses.fields(EnvConfig))

# Contacts kept per physics step (EnvConfig.max_contacts, the deepest first). Every
# candidate geom pair of a task yields contacts whether or not they touch, and the
# constraint solve is sized by them. The scripted experts' episodes measured so far never
# have more than 16 touching at once (docs/tasks.md, "Contacts"), so their physics is that
# of keeping every contact, up to float rounding. ``max_contacts=None`` keeps all.
TASK_MAX_CONTACTS = 24


@dataclasses.dataclass(frozen=True)
class TaskEntry:
    """Everything the registry knows about one task.

    Attributes:
      name: the task's name.
      scene: factory of its scene: a frozen dataclass subclass of ``Scene`` whose fields
        are the task's options.
      robot: the robot it is built for (``equibim_jax.sim.robot_names()``).
      step_limit: default ``episode_length`` in control steps.
      expert: ``(env, **kwargs) -> Expert`` scripted expert, or ``"module:function"`` to
        import it on first use, or None when the task has none.
      env_defaults: default ``EnvConfig`` fields for the task (observations, action mode,
        point count, ...).
    """

    name: str
    scene: Callable[..., Scene]
    robot: str
    step_limit: int
    expert: Callable[..., Any] | str | None = None
    env_defaults: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if not self.name:
            raise ValueError("TaskEntry.name must be non-empty")
        if not (isinstance(self.scene, type) and dataclasses.is_dataclass(self.scene)):
            raise ValueError(f"task {self.name!r}: scene must be a dataclass (its fields are the options)")
        if int(self.step_limit) < 1:
            raise ValueError(f"task {self.name!r}: step_limit must be >= 1, got {self.step_limit}")
        bad = sorted(set(self.env_defaults) - set(_ENV_FIELDS))
        if bad or "robot" in self.env_defaults or "episode_length" in self.env_defaults:
            raise ValueError(f"task {self.name!r}: env_defaults may only hold EnvConfig fields other "
                             f"than robot and episode_length; got {sorted(self.env_defaults)}")

    @property
    def scene_fields(self) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(self.scene) if f.name not in _ENV_FIELDS)


_REGISTRY: dict[str, TaskEntry] = {}
_DISCOVERED = [False]


def register_task(entry: TaskEntry) -> TaskEntry:
    """Add ``entry`` to the registry (the same entry twice is a no-op).

    Raises:
      ValueError: another entry already has that name.
    """
    old = _REGISTRY.get(entry.name)
    if old is not None and old != entry:
        raise ValueError(f"task {entry.name!r} is already registered")
    _REGISTRY[entry.name] = entry
    return entry


def _discover() -> None:
    if _DISCOVERED[0]:
        return
    _DISCOVERED[0] = True
    for mod in pkgutil.iter_modules(__path__):
        m = importlib.import_module(f"{__name__}.{mod.name}")
        entry = getattr(m, "TASK", None)
        if isinstance(entry, TaskEntry):
            register_task(entry)


def task_names() -> list[str]:
    """Registered task names, sorted."""
    _discover()
    return sorted(_REGISTRY)


def task_entry(task: str) -> TaskEntry:
    """The registry entry of ``task``; ValueError naming the valid tasks if unknown."""
    _discover()
    if task not in _REGISTRY:
        raise ValueError(f"unknown task {task!r}; valid tasks: {task_names()}")
    return _REGISTRY[task]


def task_options(task: str) -> tuple[str, ...]:
    """Every option ``make_env(task, ...)`` accepts: EnvConfig fields, then scene fields."""
    return _ENV_FIELDS + task_entry(task).scene_fields


_UNIONS = (typing.Union, types.UnionType)  # Optional[str] and str | None


def _coerce(name: str, tp: Any, value: Any) -> Any:
    """``value`` as the field type ``tp``: strings are parsed (JSON, or comma lists for
    tuples of strings), lists become tuples."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if isinstance(value, str) and tp is not str and not (origin in _UNIONS and str in args):
        text = value.strip()
        if text.lower() == "none":
            return None
        if tp is bool and text.lower() in ("true", "false"):  # Python's spelling as well as JSON's
            return text.lower() == "true"
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            if origin is tuple or (origin in _UNIONS and any(typing.get_origin(a) is tuple for a in args)):
                try:  # "0.1,0.2" -> [0.1, 0.2]; "qpos,point_cloud" -> ["qpos", "point_cloud"]
                    value = json.loads(f"[{text}]")
                except json.JSONDecodeError:
                    value = [v.strip() for v in text.split(",") if v.strip()]
            else:
                raise ValueError(f"option {name}={value!r} is not a valid {tp}") from None
    if isinstance(value, list):
        value = _tuples(value)
    return value


def _tuples(v: Any) -> Any:
    return tuple(_tuples(x) for x in v) if isinstance(v, list) else v


def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # unresolvable annotations: no coercion
        return {}


def make_scene(task: str, **options) -> Scene:
    """The task's scene with ``options`` (scene fields only); ValueError on unknown names."""
    entry = task_entry(task)
    bad = sorted(k for k in options if k not in entry.scene_fields)
    if bad:
        raise ValueError(f"unknown option(s) {bad} for task {task!r}; its scene options are "
                         f"{list(entry.scene_fields)}")
    hints = _hints(entry.scene)
    return entry.scene(**{k: _coerce(k, hints.get(k, Any), v) for k, v in options.items()})


def make_env(task: str, **options) -> Env:
    """Build the environment of ``task``.

    Args:
      task: a name from :func:`task_names`.
      **options: EnvConfig fields and the task's scene fields (module docstring).
    Returns:
      an :class:`~equibim_jax.sim.env.Env` with ``env.task`` and ``env.task_options`` set.
    Raises:
      ValueError: unknown task, an option that is neither an EnvConfig nor a scene field
        (the message lists the valid ones), or an invalid value.
    """
    entry = task_entry(task)
    valid = task_options(task)
    bad = sorted(k for k in options if k not in valid)
    if bad:
        raise ValueError(f"unknown option(s) {bad} for task {task!r}; valid options: {list(valid)}")
    env_hints = _hints(EnvConfig)
    env_kw = {"robot": entry.robot, "episode_length": int(entry.step_limit), "max_contacts": TASK_MAX_CONTACTS,
              **entry.env_defaults}
    env_kw.update({k: _coerce(k, env_hints.get(k, Any), v) for k, v in options.items() if k in _ENV_FIELDS})
    if env_kw["robot"] != entry.robot:
        raise ValueError(f"task {task!r} is built for robot {entry.robot!r}, not {env_kw['robot']!r}")
    scene = make_scene(task, **{k: v for k, v in options.items() if k not in _ENV_FIELDS})
    env = Env(EnvConfig(**env_kw), scene)
    env.task = task
    env.task_options = {
        **{f.name: getattr(env.config, f.name) for f in dataclasses.fields(EnvConfig)},
        **{f: getattr(scene, f) for f in entry.scene_fields},
    }
    return env


def make_expert(env: Env, **kwargs) -> Any:
    """The scripted expert of ``env``'s task.

    Raises:
      ValueError: the env was not built by :func:`make_env`, or its task has no expert.
    """
    task = getattr(env, "task", None)
    if task is None:
        raise ValueError("make_expert needs an env built by make_env(task, ...)")
    entry = task_entry(task)
    factory = entry.expert
    if factory is None:
        raise ValueError(f"task {task!r} has no scripted expert; tasks with one: "
                         f"{[n for n in task_names() if task_entry(n).expert is not None]}")
    if isinstance(factory, str):
        mod, _, fn = factory.partition(":")
        factory = getattr(importlib.import_module(mod), fn)
    return factory(env, **kwargs)
