"""Our task envs behind other libraries' environment interfaces.

- :mod:`.playground`: MuJoCo Playground's ``MjxEnv`` interface (pure, jittable, vmappable
  ``reset`` / ``step``); ``playground.make(task, **options)``.
- :mod:`.gym`: one environment as a ``gymnasium.Env`` (needs ``gymnasium``, part of the
  ``interop`` extra); ``gym.make(task, **options)``.

Reward is the task's success as a float; done is success or the step limit. See
docs/data.md. The submodules are imported on use, so this package needs nothing optional.
"""
