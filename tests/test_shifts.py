"""The distribution shifts of the robot-B tasks (``equibim_jax.tasks._shifts``).

Each shift changes the distribution it names and nothing else. Starts are drawn with the
same keys with and without the option (``init`` splits its key the same way whatever the
options), so most checks are exact: ``side`` keeps every start already on that side and
turns the others into their mirror images; ``mirrored_orientation`` changes only the
object's orientation; ``asymmetric_quality`` changes only ``info["perturbed"]``;
``wide_init`` widens the ranges (spreads grow by the factor) and leaves the robot alone.
No MJX compile in the default suite; the slow test generates a dataset with bad demos.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from equibim_jax.tasks import make_env, task_entry, task_names
from equibim_jax.tasks._shifts import SHIFT_FIELDS, ShiftScene, widen, widen_abs

TASKS = [t for t in task_names() if task_entry(t).robot == "robot_b"]
N = 512


def _sided(task):
    return task_entry(task).scene.sided


def _starts(task, **options):
    env = make_env(task, obs=("qpos",), **options)
    keys = jax.random.split(jax.random.key(11), N)
    qpos, info = jax.jit(jax.vmap(lambda k: env.scene.init(k, env)))(keys)
    return env, np.asarray(qpos, np.float64), jax.tree.map(np.asarray, info)


def _object_adr(env):
    m = env.mj_model
    return int(m.jnt_qposadr[m.joint(env.scene.main_object).id])


def test_widen_helpers():
    assert widen((1.0, 3.0), 1.5) == (0.5, 3.5)
    assert widen_abs((0.1, 0.3), 2.0, 0.05) == (0.05, 0.4)
    assert widen_abs((0.2, 0.3), 1.5, 0.05) == pytest.approx((0.175, 0.325))


def test_robot_b_tasks_are_registered():
    assert set(TASKS) == {"banana_handover", "drumstick_hook", "chicken_hook"}, TASKS
    for t in TASKS:
        assert issubclass(task_entry(t).scene, ShiftScene)
        assert set(SHIFT_FIELDS) <= set(task_entry(t).scene_fields)


@pytest.mark.parametrize("task", TASKS)
def test_shift_options_are_recorded_and_checked(task):
    side = "left" if _sided(task) else "both"
    env = make_env(task, side=side, mirrored_orientation=True, wide_init=1.5,
                   asymmetric_quality=0.25, asymmetric_side="left")
    opts = env.task_options
    assert (opts["side"], opts["mirrored_orientation"], opts["wide_init"],
            opts["asymmetric_quality"], opts["asymmetric_side"]) == (side, True, 1.5, 0.25, "left")
    # strings from a command line are parsed
    assert make_env(task, wide_init="1.5", mirrored_orientation="true").scene.wide_init == 1.5
    bad = [({"wide_init": 0.5}, "wide_init"), ({"asymmetric_quality": 1.5}, "asymmetric_quality"),
           ({"asymmetric_side": "both"}, "asymmetric_side"),
           ({"mirrored_orientation": 1}, "mirrored_orientation")]
    if _sided(task):
        bad.append(({"side": "left", "asymmetric_quality": 0.3, "asymmetric_side": "right"},
                    "never puts the object there"))
    else:
        bad.append(({"side": "left"}, "mirror plane"))
    for opts, msg in bad:
        with pytest.raises(ValueError, match=msg):
            make_env(task, **opts)


@pytest.mark.parametrize("task", TASKS)
def test_info_fields(task):
    env, qpos, info = _starts(task)
    assert {"side", "yaw", "perturbed"} <= set(info)
    assert info["side"].shape == info["yaw"].shape == info["perturbed"].shape == (N,)
    assert set(np.unique(info["side"])) == {-1.0, 1.0}
    assert not info["perturbed"].any()  # asymmetric_quality 0 by default


@pytest.mark.parametrize("task", [t for t in TASKS if _sided(t)])
@pytest.mark.parametrize("side,sign", [("left", 1.0), ("right", -1.0)])
def test_side_keeps_that_side_and_mirrors_the_rest(task, side, sign):
    env, q_both, i_both = _starts(task)
    _, q_side, i_side = _starts(task, side=side)
    assert np.all(i_side["side"] == sign)
    same = i_both["side"] == sign
    assert 0.3 < same.mean() < 0.7
    np.testing.assert_allclose(q_side[same], q_both[same], atol=1e-6)
    mirrored = np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(q_both[~same])), np.float64)
    np.testing.assert_allclose(q_side[~same], mirrored, atol=1e-5)
    np.testing.assert_array_equal(i_side["yaw"][same], i_both["yaw"][same])
    np.testing.assert_allclose(i_side["yaw"][~same], -i_both["yaw"][~same], atol=1e-6)


@pytest.mark.parametrize("task", TASKS)
def test_mirrored_orientation_changes_only_the_yaw(task):
    env, q0, i0 = _starts(task)
    _, q1, i1 = _starts(task, mirrored_orientation=True)
    np.testing.assert_allclose(i1["yaw"], -i0["yaw"], atol=1e-6)
    np.testing.assert_array_equal(i1["side"], i0["side"])
    a = _object_adr(env)
    quat = np.zeros(q0.shape[1], bool)
    quat[a + 3 : a + 7] = True
    np.testing.assert_allclose(q1[:, ~quat], q0[:, ~quat], atol=1e-6)
    moved = np.abs(q1[:, quat] - q0[:, quat]).max(axis=1) > 1e-4
    assert moved.mean() > 0.9  # the orientation itself changes (yaw 0 is measure zero)


@pytest.mark.parametrize("task", TASKS)
def test_wide_init_widens_the_ranges_only(task):
    env, q0, i0 = _starts(task)
    _, q1, i1 = _starts(task, wide_init=1.5)
    nr = env.info.nq_robot
    np.testing.assert_array_equal(q1[:, :nr], q0[:, :nr])  # the arms start at home either way
    np.testing.assert_array_equal(i1["side"], i0["side"])
    a = _object_adr(env)
    spread = lambda v: np.ptp(v)
    # x of the object, and the yaw relative to the side: a uniform draw on a range widened
    # 1.5x about its centre, with the same key
    for name, v0, v1 in (("x", q0[:, a], q1[:, a]),
                         ("yaw", i0["yaw"] * i0["side"], i1["yaw"] * i1["side"])):
        if spread(v0) < 1e-6:
            continue
        ratio = spread(v1) / spread(v0)
        assert 1.45 < ratio < 1.55, f"{task}: {name} spread grew {ratio:.3f}x, not 1.5x"
    # the object's lateral offset (|y| from the mirror plane) spreads wider too
    assert spread(np.abs(q1[:, a + 1])) > 1.2 * spread(np.abs(q0[:, a + 1]))


@pytest.mark.parametrize("task", TASKS)
def test_asymmetric_quality_flags_only_that_side(task):
    env, q0, i0 = _starts(task)
    _, q1, i1 = _starts(task, asymmetric_quality=0.3, asymmetric_side="right")
    np.testing.assert_array_equal(q1, q0)
    np.testing.assert_array_equal(i1["side"], i0["side"])
    np.testing.assert_array_equal(i1["yaw"], i0["yaw"])
    on = i1["side"] < 0 if _sided(task) else np.ones(N, bool)
    assert not i1["perturbed"][~on].any()
    n, k = on.sum(), i1["perturbed"][on].sum()
    assert abs(k - 0.3 * n) < 4 * np.sqrt(n * 0.3 * 0.7), (k, n)
    _, _, i2 = _starts(task, asymmetric_quality=1.0, asymmetric_side="right")
    np.testing.assert_array_equal(i2["perturbed"], on)


@pytest.mark.slow
def test_generation_keeps_and_records_the_bad_demos():
    """drumstick_hook, the paper's uneven-quality task: with every right-side demo
    perturbed, generation keeps them (as failures) and says which they are."""
    from equibim_jax.data.generate import generate_demos

    if "drumstick_hook" not in TASKS:
        pytest.skip("drumstick_hook is not registered")
    env = make_env("drumstick_hook", obs=("qpos",), asymmetric_quality=1.0, asymmetric_side="right")
    demos, stats = generate_demos(env, jax.random.key(3), 12, chunk=12, progress=False)
    pert = np.asarray(demos.meta["perturbed"])
    assert pert.shape == (12,) and pert.any() and not pert.all()
    assert demos.meta["task_options"]["asymmetric_quality"] == 1.0
    assert not demos.success[pert].any(), "a perturbed demo succeeded"
    assert demos.success[~pert].all()
    assert stats["perturbed"] == int(pert.sum())
