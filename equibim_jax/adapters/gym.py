"""Gymnasium wrapper: one environment of a task as a ``gymnasium.Env``.

For tools that drive one environment at a time from Python (LeRobot's evaluation, Gymnasium
vector wrappers): ``reset(seed=)`` and ``step(action)`` call the adapter's jitted pure
functions (compiled once, at the first call) and return numpy.

- ``observation_space``: ``Box`` float32 [n] for flat vector observations, else a ``Dict``
  of ``Box`` per field (images uint8 in [0, 255], the rest float32 unbounded).
- ``action_space``: ``Box`` float32 [action_size]; for joint actions the arm entries are
  bounded by the arm actuators' control ranges and the gripper openings by [0, 1];
  end-effector actions are unbounded.
- ``step`` returns ``(obs, reward, terminated, truncated, info)``: reward is the task's
  success (1.0 / 0.0), ``terminated`` the task succeeded, ``truncated`` the step limit was
  reached without success; ``info["is_success"]`` (the key LeRobot's evaluation reads).
- ``render()`` (``render_mode="rgb_array"``): uint8 [H, W, 3] from the robot's camera.

Episode randomness: ``reset(seed=s)`` seeds ``self.np_random``; every reset draws the
episode's PRNG key ``jax.random.PRNGKey(k)`` from it, so a seed fixes the episode sequence.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from equibim_jax.adapters.playground import PlaygroundEnv, make as make_playground

try:
    import gymnasium
    from gymnasium import spaces
except ImportError as e:  # pragma: no cover - exercised where gymnasium is missing
    raise ImportError(f"the Gymnasium wrapper needs gymnasium; install it with "
                      f"`pip install 'equibim-jax[interop]'` ({e})") from None

__all__ = ["EquibimGymEnv", "make"]


def _box(shape, dtype) -> spaces.Box:
    if np.dtype(dtype) == np.uint8:
        return spaces.Box(0, 255, shape=tuple(shape), dtype=np.uint8)
    return spaces.Box(-np.inf, np.inf, shape=tuple(shape), dtype=np.float32)


class EquibimGymEnv(gymnasium.Env):
    """A task env as a Gymnasium env (module docstring).

    Args:
      env: a :class:`~equibim_jax.adapters.playground.PlaygroundEnv` (its jitted ``reset`` /
        ``step`` are reused).
      render_mode: ``None`` or ``"rgb_array"``.
      render_size: (height, width) of :meth:`render`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, env: PlaygroundEnv, render_mode: str | None = None, render_size: tuple[int, int] = (96, 96)):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.env = env
        self.render_mode = render_mode
        self.render_size = tuple(int(s) for s in render_size)
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / env.dt))}
        shapes = jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs
        if isinstance(shapes, dict):
            self.observation_space = spaces.Dict({k: _box(v.shape, v.dtype) for k, v in shapes.items()})
        else:
            self.observation_space = _box(shapes.shape, np.float32)
        self.action_space = self._action_box()
        self._state = None

    def _action_box(self) -> spaces.Box:
        inner = self.env.env
        n = inner.action_size
        if inner.config.action != "joint":
            return spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float32)
        per_arm = inner.info.n_arm + 1
        lo, hi = np.full(n, -np.inf, np.float32), np.full(n, np.inf, np.float32)
        for side in (0, 1):
            acts = inner.arm_act[side]
            lo[side * per_arm: side * per_arm + per_arm - 1] = inner.ctrl_lo[acts]
            hi[side * per_arm: side * per_arm + per_arm - 1] = inner.ctrl_hi[acts]
            lo[side * per_arm + per_arm - 1], hi[side * per_arm + per_arm - 1] = 0.0, 1.0
        return spaces.Box(lo, hi, dtype=np.float32)

    def _obs(self, state) -> Any:
        obs = jax.device_get(state.obs)
        if isinstance(obs, dict):
            return {k: np.asarray(v, self.observation_space[k].dtype) for k, v in obs.items()}
        return np.asarray(obs, np.float32)

    def _info(self, state) -> dict:
        success = bool(state.info["success"])
        return {"is_success": success, "step": int(state.info["step"])}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``seed`` reseeds the episode-key generator. Returns ``(obs, info)``."""
        super().reset(seed=seed)
        k = int(self.np_random.integers(0, 2**31 - 1))
        self._state = self.env.jit_reset(jax.random.PRNGKey(k))
        return self._obs(self._state), self._info(self._state)

    def step(self, action):
        """Apply ``action`` [action_size]; returns ``(obs, reward, terminated, truncated, info)``."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, np.float32).reshape(self.action_space.shape)
        self._state = self.env.jit_step(self._state, a)
        success = bool(self._state.info["success"])
        truncated = (not success) and int(self._state.info["step"]) >= self.env.step_limit
        return self._obs(self._state), float(self._state.reward), success, truncated, self._info(self._state)

    def render(self):
        """uint8 [H, W, 3] of the current state (``render_mode="rgb_array"``), else None."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        h, w = self.render_size
        return self.env.render(self._state, height=h, width=w)


def make(task_name: str, render_mode: str | None = None, step_limit: int | None = None, **options) -> EquibimGymEnv:
    """The Gymnasium env of a registered task; ``options`` are ``make_env``'s."""
    return EquibimGymEnv(make_playground(task_name, step_limit=step_limit, **options), render_mode=render_mode)
