"""The task registry: ``name -> Scene factory``, and :func:`make_env`, the public entry point.

Example::

    from equibim_jax.tasks import make_env
    env = make_env("place_empty_cup", obs=("qpos", "point_cloud"), action="joint", side="left")

Options are split by name between :class:`~equibim_jax.sim.env.EnvConfig` fields (``obs``,
``action``, ``rotation``, ``image_size``, ``n_points``, ``episode_length``, ...) and the
task's own scene fields (``side``, ranges, tolerances). A task's default
``episode_length`` is its step limit from ``TASKS.md``.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from equibim_jax.sim.env import Env, EnvConfig, Scene
from equibim_jax.tasks.place_empty_cup import PlaceEmptyCup

__all__ = ["TASKS", "STEP_LIMITS", "make_env", "make_scene", "task_names", "task_options"]

TASKS: dict[str, Callable[..., Scene]] = {
    "place_empty_cup": PlaceEmptyCup,
}
"""Task name -> factory of its :class:`Scene` (a frozen dataclass; options are its fields)."""

STEP_LIMITS: dict[str, int] = {
    "place_empty_cup": 500,
}
"""Task name -> default ``episode_length`` (control steps), from TASKS.md."""

_ENV_FIELDS = tuple(f.name for f in dataclasses.fields(EnvConfig))


def task_names() -> list[str]:
    """Registered task names, sorted."""
    return sorted(TASKS)


def _check_task(task: str) -> Callable[..., Scene]:
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; valid tasks: {task_names()}")
    return TASKS[task]


def task_options(task: str) -> tuple[str, ...]:
    """Every option ``make_env(task, ...)`` accepts: EnvConfig fields, then scene fields."""
    factory = _check_task(task)
    scene_fields = tuple(f.name for f in dataclasses.fields(factory)) if dataclasses.is_dataclass(factory) else ()
    return _ENV_FIELDS + tuple(f for f in scene_fields if f not in _ENV_FIELDS)


def make_scene(task: str, **options) -> Scene:
    """The task's scene with ``options`` (scene fields only); ValueError on unknown names."""
    factory = _check_task(task)
    valid = task_options(task)[len(_ENV_FIELDS):]
    bad = sorted(k for k in options if k not in valid)
    if bad:
        raise ValueError(f"unknown option(s) {bad} for task {task!r}; valid scene options: {list(valid)}")
    return factory(**options)


def make_env(task: str, **options) -> Env:
    """Build the environment of ``task``.

    Args:
      task: a name from :func:`task_names`.
      **options: EnvConfig fields (``obs``, ``action``, ``rotation``, ``ctrl_dt``,
        ``image_size``, ``n_points``, ``episode_length`` (default: the task's step limit),
        ...) and scene fields of the task (e.g. ``side="left"|"right"|"both"``).

    Returns:
      An :class:`~equibim_jax.sim.env.Env` (pure ``reset(key)`` / ``step(state, action [A])``).

    Raises:
      ValueError: unknown task, or an option that is neither an EnvConfig nor a scene
        field (the message lists the valid ones), or an invalid value.
    """
    valid = task_options(task)
    bad = sorted(k for k in options if k not in valid)
    if bad:
        raise ValueError(f"unknown option(s) {bad} for task {task!r}; valid options: {list(valid)}")
    env_kw = {k: v for k, v in options.items() if k in _ENV_FIELDS}
    scene_kw = {k: v for k, v in options.items() if k not in _ENV_FIELDS}
    env_kw.setdefault("episode_length", STEP_LIMITS.get(task, EnvConfig.episode_length))
    return Env(EnvConfig(**env_kw), make_scene(task, **scene_kw))
