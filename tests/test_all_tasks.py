"""Every registered task, one parameterised set of checks.

Default suite (no MJX compile): the registry entry and bad options; the initial-state
distribution is mirror-symmetric (starts drawn by the task's ``init`` against their mirror
images, coordinate by coordinate); a few starts and their mirror images are valid: no
interpenetration, objects where the task put them, success false.

The generic expert check (``task_rollouts.check_expert_episodes``, slow: one compiled rollout
program per task): ``jit`` reset, mirror and step; shapes and no NaN; the expert's success
rate (>= 95 %) on the first 50 of the 200 seeded starts that ``equibim experts --episodes
200`` runs (its JSON, committed under ``docs/results/``, holds the rate on all 200); and ``S``
maps a recorded expert demo (observations and actions) onto the demo the expert records from
the mirrored start. A task with its own ``tests/test_<task>.py`` runs it there, on the same
episodes as its task-specific expert checks; this file runs it for the other tasks and checks
that each task file does.
"""

import importlib
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from scipy.stats import ks_2samp

from equibim_jax.tasks import make_env, make_scene, task_entry, task_names

from task_rollouts import check_expert_episodes, expert_episodes

TASKS = task_names()


@pytest.fixture(scope="module", params=TASKS)
def task(request):
    return request.param


def test_registry_entry_and_bad_options(task):
    entry = task_entry(task)
    assert entry.name == task and entry.step_limit >= 100 and entry.expert is not None
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['no_such_option'\]"):
        make_env(task, no_such_option=1)
    if "side" in entry.scene_fields:  # tasks where one arm acts pick its side
        with pytest.raises(ValueError, match="side must be one of"):
            make_scene(task, side="middle")
    with pytest.raises(ValueError, match="robot"):
        make_env(task, robot="robot_b" if entry.robot == "robot_a" else "robot_a")


def _host_forward(env, qpos):
    d = mujoco.MjData(env.mj_model)
    d.qpos[:] = np.asarray(qpos, np.float64)
    mujoco.mj_forward(env.mj_model, d)
    return d


def test_initial_distribution_is_mirror_symmetric_and_valid(task):
    env = make_env(task, obs=("qpos",))
    n = 1024
    keys = jax.random.split(jax.random.key(7), n)
    qpos, info = jax.jit(jax.vmap(lambda k: env.scene.init(k, env)))(keys)
    qpos = np.asarray(qpos, np.float64)
    assert qpos.shape == (n, env.mj_model.nq) and np.all(np.isfinite(qpos))
    mirrored = np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(qpos)), np.float64)
    np.testing.assert_allclose(np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(mirrored))), qpos, atol=1e-5)
    # Coordinate by coordinate, the starts and their mirror images follow one law (two-sample
    # KS, alpha 1e-4 per coordinate). A one-sided or skewed distribution fails here.
    varying = np.flatnonzero(qpos.std(0) > 1e-6)
    assert varying.size > 0, "the initial state does not vary"
    for i in varying:
        p = ks_2samp(qpos[:, i], mirrored[:, i]).pvalue
        assert p > 1e-4, f"{task}: qpos[{i}] has a different law in the mirrored starts (KS p = {p:.2e})"
    # A few starts and their mirror images, checked in MuJoCo: no interpenetration beyond
    # 2 mm, the success predicate false.
    for q in (*qpos[:3], *mirrored[:3]):
        d = _host_forward(env, q)
        depth = min((c.dist for c in d.contact[: d.ncon]), default=0.0)
        assert depth > -2e-3, f"{task}: a start interpenetrates by {-depth * 1000:.1f} mm"
        dx = mjx.put_data(env.mj_model, d)
        _, success, _ = env.scene.evaluate(dx, {k: v[0] for k, v in info.items()}, env)
        assert not bool(success), f"{task}: success is true at a start"


# ----------------------------------------------------------------- the generic expert check
HERE = Path(__file__).resolve().parent


def own_test_file(task: str) -> Path:
    return HERE / f"test_{task}.py"


@pytest.mark.parametrize("task", [t for t in TASKS if own_test_file(t).is_file()])
def test_own_test_file_runs_the_generic_expert_check(task):
    """A task with its own test file runs the generic expert check there, on the episodes its
    own expert checks use (one compiled program per task), instead of here: the module holds
    ``task_rollouts.expert_fixtures(task)``'s fixture and slow test under their own names."""
    mod = importlib.import_module(own_test_file(task).stem)
    check = getattr(mod, "test_expert_generic_checks", None)
    assert getattr(check, "expert_task", None) == task, (
        f"{own_test_file(task).name} must define `episodes, test_expert_generic_checks = "
        f"expert_fixtures({task!r})` (task_rollouts)")
    assert any(m.name == "slow" for m in getattr(check, "pytestmark", []))
    assert getattr(mod, "episodes", None) is not None


@pytest.mark.slow
@pytest.mark.parametrize("task", [t for t in TASKS if not own_test_file(t).is_file()])
def test_expert_success_and_mirror_equivariance(task):
    """The first 50 of the 200 seeded starts of ``equibim experts --seed 2024``, run to the end
    of the expert's script, plus the mirror images of the first 25 (one compiled program), for
    tasks without a test file of their own."""
    check_expert_episodes(expert_episodes(task))
