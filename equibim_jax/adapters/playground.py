"""MuJoCo Playground adapter: our task envs behind the ``MjxEnv`` interface.

``make(task, **options)`` returns a :class:`PlaygroundEnv`, which follows the interface of
MuJoCo Playground's ``mujoco_playground._src.mjx_env.MjxEnv``:

- ``reset(rng) -> State`` and ``step(state, action) -> State``, pure functions of one
  environment (jit and vmap them as with any Playground env);
- ``State`` with ``data`` (``mjx.Data``), ``obs``, ``reward`` (float32 []), ``done``
  (float32 [], 1.0 when done), ``metrics`` (dict of float32 []) and ``info`` (dict);
- properties ``observation_size``, ``action_size``, ``dt``, ``sim_dt``, ``n_substeps``,
  ``mj_model``, ``mjx_model``, ``xml_path``, ``model_assets``, ``unwrapped``, and
  ``render(trajectory)``.

Reward and done: ``reward`` is the task's success as a float (1.0 on every step from the
first success on, else 0.0), not the task's shaped reward (that one is in
``metrics["task_reward"]``); ``done`` is success or the step limit (``step_limit``, default
the task's ``episode_length``). Like Playground's own envs, stepping a done state keeps
simulating; auto-reset is the training wrapper's job.

Observations: ``obs`` is one flat float32 vector [observation_size] when every observed
field is a vector (``qpos``, ``ee``), else the env's dict of fields (shapes in
``equibim_jax.sim.env``); ``flatten`` chooses explicitly.

MuJoCo Playground itself is not a dependency (see docs/data.md): when ``mujoco_playground``
has been imported, :class:`PlaygroundEnv` is registered as a virtual subclass of its
``MjxEnv``, so ``isinstance`` checks pass.
"""

from __future__ import annotations

import functools
import sys
from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from equibim_jax.sim.env import Env
from equibim_jax.sim.env import State as EnvState

__all__ = ["State", "PlaygroundEnv", "make"]

VECTOR_FIELDS = ("qpos", "ee")


@struct.dataclass
class State:
    """One environment's state, with the fields of Playground's ``mjx_env.State``.

    Attributes:
      data: ``mjx.Data``.
      obs: float32 [observation_size], or a dict of fields.
      reward: float32 [], the task's success (0.0 or 1.0).
      done: float32 [], 1.0 once the task succeeded or the step limit is reached.
      metrics: dict of float32 [] (``success``, ``task_reward``, ``nan_action``,
        ``clipped`` and the task's own).
      info: dict: ``step`` (int32 []), ``success`` (bool []), the task's episode fields
        and ``env_obs`` (the env's observation dict).
    """

    data: mjx.Data
    obs: Any
    reward: jax.Array
    done: jax.Array
    metrics: dict
    info: dict

    def tree_replace(self, params: Mapping[str, Any]) -> "State":
        """A copy with dotted attributes replaced, e.g. ``{"data.qpos": q, "info.step": 0}``."""
        new = self
        for path, value in params.items():
            new = _replace(new, path.split("."), value)
        return new


def _replace(base, attrs, value):
    if len(attrs) == 1:
        return base.replace(**{attrs[0]: value}) if hasattr(base, "replace") and not isinstance(base, dict) \
            else {**base, attrs[0]: value}
    child = getattr(base, attrs[0]) if not isinstance(base, dict) else base[attrs[0]]
    new = _replace(child, attrs[1:], value)
    return base.replace(**{attrs[0]: new}) if not isinstance(base, dict) else {**base, attrs[0]: new}


class PlaygroundEnv:
    """An :class:`~equibim_jax.sim.env.Env` with MuJoCo Playground's ``MjxEnv`` interface.

    Args:
      env: our env (``equibim_jax.tasks.make_env``).
      step_limit: control steps before ``done`` (default ``env.config.episode_length``).
      flatten: flat float32 observations (default: when every observed field is a vector).
    """

    def __init__(self, env: Env, step_limit: int | None = None, flatten: bool | None = None):
        self.env = env
        self.step_limit = int(step_limit or env.config.episode_length)
        if self.step_limit < 1:
            raise ValueError(f"step_limit must be >= 1, got {step_limit}")
        vec = all(f in VECTOR_FIELDS for f in env.config.obs)
        if flatten and not vec:
            raise ValueError(f"flatten=True needs vector observations only ({VECTOR_FIELDS}); the env observes "
                             f"{env.config.obs}")
        self.flatten = vec if flatten is None else bool(flatten)
        self._ctrl_dt = float(env.ctrl_dt)
        self._sim_dt = float(env.mj_model.opt.timestep)
        mp = sys.modules.get("mujoco_playground._src.mjx_env")
        if mp is not None and hasattr(mp, "MjxEnv"):
            mp.MjxEnv.register(PlaygroundEnv)

    # ------------------------------------------------------------------ core
    def _obs(self, env_obs: dict):
        if not self.flatten:
            return env_obs
        return jnp.concatenate([env_obs[f].astype(jnp.float32).reshape(-1) for f in self.env.config.obs])

    def _wrap(self, s: EnvState) -> State:
        success = s.info["success"]
        done = jnp.logical_or(success, s.info["step"] >= self.step_limit)
        metrics = {**{k: jnp.asarray(v, jnp.float32) for k, v in s.metrics.items()},
                   "task_reward": jnp.asarray(s.reward, jnp.float32)}
        return State(data=s.data, obs=self._obs(s.obs), reward=success.astype(jnp.float32),
                     done=done.astype(jnp.float32), metrics=metrics, info={**s.info, "env_obs": s.obs})

    def reset(self, rng: jax.Array) -> State:
        """A new episode from PRNG key ``rng`` (pure; one environment)."""
        return self._wrap(self.env.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        """One control step with ``action`` [action_size] (pure; one environment)."""
        info = {k: v for k, v in state.info.items() if k != "env_obs"}
        inner = EnvState(data=state.data, obs=state.info["env_obs"], reward=state.reward,
                         done=state.done.astype(bool), metrics={}, info=info)
        return self._wrap(self.env.step(inner, action))

    @functools.cached_property
    def jit_reset(self):
        """``jax.jit(reset)``, built once per adapter (the Gymnasium wrapper shares it)."""
        return jax.jit(self.reset)

    @functools.cached_property
    def jit_step(self):
        """``jax.jit(step)``, built once per adapter."""
        return jax.jit(self.step)

    # ------------------------------------------------------------------ properties
    @property
    def observation_size(self):
        """``int`` for flat observations, else ``{field: shape}`` (from ``jax.eval_shape``)."""
        obs = jax.eval_shape(self.reset, jax.random.PRNGKey(0)).obs
        if isinstance(obs, Mapping):
            return {k: tuple(v.shape) for k, v in obs.items()}
        return int(obs.shape[-1])

    @property
    def action_size(self) -> int:
        return int(self.env.action_size)

    @property
    def dt(self) -> float:
        """Control period in seconds."""
        return self._ctrl_dt

    @property
    def sim_dt(self) -> float:
        """Physics timestep in seconds."""
        return self._sim_dt

    @property
    def n_substeps(self) -> int:
        return int(round(self.dt / self.sim_dt))

    @property
    def mj_model(self) -> mujoco.MjModel:
        return self.env.mj_model

    @property
    def mjx_model(self) -> mjx.Model:
        return self.env.mjx_model

    @property
    def xml_path(self) -> str:
        """No XML file: the model is compiled from the robot's and the task's ``MjSpec``
        (``mj_model`` is that model; ``mujoco.mj_saveLastXML`` can write it out)."""
        return ""

    @property
    def model_assets(self) -> dict:
        """No asset files: meshes and textures are inside the compiled ``mj_model``."""
        return {}

    @property
    def unwrapped(self) -> "PlaygroundEnv":
        return self

    def render(self, trajectory: State | Sequence[State], height: int = 240, width: int = 320,
               camera: str | None = None, **_ignored) -> np.ndarray | list[np.ndarray]:
        """RGB frames uint8 [height, width, 3] of a state or a list of states, from
        ``camera`` (default: the robot's camera on the mirror plane), ray-cast in JAX
        (``equibim_jax.sim.render``; no OpenGL needed). Playground's scene options are
        accepted and ignored."""
        fn = self._renderer(camera or self.env.camera, int(height), int(width))
        if isinstance(trajectory, (list, tuple)):
            return [np.asarray(fn(s.data)) for s in trajectory]
        return np.asarray(fn(trajectory.data))

    @functools.lru_cache(maxsize=4)
    def _renderer(self, camera: str, height: int, width: int):
        from equibim_jax.sim.render import CameraConfig, make_renderer

        r = make_renderer(self.env.mj_model, CameraConfig(camera=camera, width=width, height=height))
        return jax.jit(r.rgb)


def make(task_name: str, step_limit: int | None = None, flatten: bool | None = None, **options) -> PlaygroundEnv:
    """The :class:`PlaygroundEnv` of a registered task (``equibim tasks``); ``options`` are
    ``make_env``'s (env settings such as ``obs``, and the task's own)."""
    from equibim_jax.tasks import make_env

    return PlaygroundEnv(make_env(task_name, **options), step_limit=step_limit, flatten=flatten)
