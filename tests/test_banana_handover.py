"""banana_handover (robot B): registry and option errors, the model (physical, mirror
symmetric, few contact pairs), the initial distribution and its shift options, the success
predicate on hand-built states and on states the scripted expert reaches in MuJoCo C.

Slow tests: one compiled MJX rollout program, the task's ``task_rollouts.expert_episodes``
(50 seeded starts and the mirror images of 25), serves the generic expert check and, in
batches of 25, runs the expert from more starts: seeded starts on both sides and their
mirror images, starts drawn with ``mirrored_orientation=True`` (the shift the paper applies
to this task), and starts on the right side with ``asymmetric_quality=1.0`` (every one
perturbed: those must fail).
"""

import copy
import types

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from equibim_jax.experts import make_expert
from equibim_jax.experts.banana_handover import BananaExpertConfig
from equibim_jax.tasks import make_env, make_scene, task_entry, task_names, task_options
from equibim_jax.tasks.banana_handover import BananaHandover

from task_rollouts import collides, expert_fixtures, run_starts

TASK = "banana_handover"
CFG = BananaExpertConfig()


@pytest.fixture(scope="module")
def env():
    return make_env(TASK, obs=("qpos",))


# ---------------------------------------------------------------------------- registry
def test_registry_and_option_errors(env):
    assert TASK in task_names()
    entry = task_entry(TASK)
    assert entry.robot == "robot_b" and entry.step_limit == 600 and entry.expert is not None
    assert dict(entry.env_defaults) == {"obs": ("qpos", "point_cloud"), "action": "joint", "n_points": 64}
    assert BananaHandover.main_object == "banana"
    with pytest.raises(ValueError, match="robot"):
        make_env(TASK, robot="robot_a")
    with pytest.raises(ValueError, match="built for robot_b"):
        BananaHandover().build(mujoco.MjSpec(), types.SimpleNamespace(name="robot_a"))
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['colour'\]"):
        make_env(TASK, colour="yellow")
    with pytest.raises(ValueError, match="side must be one of"):
        make_scene(TASK, side="middle")
    with pytest.raises(ValueError, match="mirrored_orientation must be a bool"):
        make_scene(TASK, mirrored_orientation=1)
    with pytest.raises(ValueError, match="wide_init must be a factor >= 1"):
        make_scene(TASK, wide_init=0.5)
    with pytest.raises(ValueError, match="asymmetric_quality must be a fraction"):
        make_scene(TASK, asymmetric_quality=1.5)
    with pytest.raises(ValueError, match="never puts the object there"):
        make_scene(TASK, side="left", asymmetric_quality=0.3, asymmetric_side="right")
    with pytest.raises(ValueError, match="low <= high"):
        make_scene(TASK, x_range=(0.2, 0.1))
    with pytest.raises(ValueError, match="wholly on its side"):
        make_scene(TASK, y_range=(0.05, 0.15))
    with pytest.raises(ValueError, match="bend must be in"):
        make_scene(TASK, bend=2.0)
    with pytest.raises(ValueError, match="mass must be positive"):
        make_scene(TASK, mass=0.0)
    with pytest.raises(ValueError, match="touch_tol must be >= 0"):
        make_scene(TASK, touch_tol=-0.001)
    # expert options
    with pytest.raises(ValueError, match="durations needs 14"):
        BananaExpertConfig(durations=(10,) * 13)
    with pytest.raises(ValueError, match="on the middle capsule"):
        make_expert(env, config=BananaExpertConfig(receiver_offset=0.05))
    with pytest.raises(ValueError, match="at least 2 mm apart"):
        make_expert(env, config=BananaExpertConfig(receiver_offset=0.015))
    with pytest.raises(ValueError, match="into the table"):
        make_expert(env, config=BananaExpertConfig(giver_above=0.005))
    with pytest.raises(ValueError, match="no room for the"):
        make_expert(env, config=BananaExpertConfig(receiver_clearance=0.03))
    with pytest.raises(ValueError, match="joint actions"):
        make_expert(make_env(TASK, action="ee", obs=("qpos",)))
    assert {"side", "mirrored_orientation", "wide_init", "asymmetric_quality", "asymmetric_side",
            "x_range", "yaw_range"} <= set(task_options(TASK))
    assert make_scene(TASK, mirrored_orientation="true").mirrored_orientation is True


# ---------------------------------------------------------------------------- model
def test_model_is_physical_and_mirror_symmetric(env):
    m = env.mj_model
    sc = env.scene
    assert m.neq == 0 and m.nmocap == 0  # friction grasps only: no welds, no mocap
    assert m.jnt_type[m.joint("banana").id] == mujoco.mjtJoint.mjJNT_FREE
    b = m.body("banana").id
    assert abs(m.body_mass[b] - 0.1) < 1e-9
    assert 0.15 <= sc.length() <= 0.18 and 2 * sc.radius == pytest.approx(0.03)
    assert 2 * sc.radius < env.info.gripper_span  # the open jaws straddle it
    assert env.sym.residual < 1e-6 and env.sym.dynamics_exact
    # the banana is its own mirror image about its x-z plane: yaw -> -yaw
    np.testing.assert_allclose(env.sym.body_local[b], np.diag([1.0, -1.0, 1.0]), atol=1e-9)
    # Few contact pairs: the middle capsule touches the table, jaws and palms; the bent
    # ends the table and the jaws.
    g = lambda n: m.geom(n).id
    jaws = {g(p) for side in env.info.gripper_pads for p in side}
    palms = {g("left_palm"), g("right_palm")}
    partners = lambda k: {h for h in range(m.ngeom) if m.geom_bodyid[h] != m.geom_bodyid[k] and collides(m, k, h)}
    assert partners(g("banana_mid")) == jaws | palms | {g("table")}
    assert partners(g("banana_end_a")) == partners(g("banana_end_b")) == jaws | {g("table")}
    # reference posture on the mirror plane; the scene's crop is its own mirror image
    assert abs(m.qpos0[sc._ids(env)["qadr"] + 1]) < 1e-12
    lo, hi = sc.point_cloud_crop
    assert lo[1] == -hi[1]


# ---------------------------------------------------------------------------- starts
def _starts(scene_opts, env, n=64, seed=0):
    """``n`` starts drawn by the scene with ``scene_opts`` (the options change only the
    initial-state law, so the default env's model serves)."""
    scene = make_scene(TASK, **scene_opts)
    keys = jax.random.split(jax.random.key(seed), n)
    qpos, info = jax.jit(jax.vmap(lambda k: scene.init(k, env)))(keys)
    return np.asarray(qpos, np.float64), jax.tree.map(np.asarray, info)


def test_initial_distribution_and_shift_options(env):
    sc = env.scene
    a = sc._ids(env)["qadr"]
    q, info = _starts({}, env)
    s = info["side"]
    assert set(np.unique(s)) == {-1.0, 1.0} and info["yaw"].dtype == np.float32
    assert not info["perturbed"].any()
    assert np.all(np.sign(q[:, a + 1]) == s)
    assert np.all((q[:, a] >= sc.x_range[0]) & (q[:, a] <= sc.x_range[1]))
    assert np.all((np.abs(q[:, a + 1]) >= sc.y_range[0]) & (np.abs(q[:, a + 1]) <= sc.y_range[1]))
    np.testing.assert_allclose(q[:, a + 2], sc.radius)  # flat on the table
    yaw = 2 * np.arctan2(q[:, a + 6], q[:, a + 3])
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(yaw, info["yaw"], atol=1e-5)
    assert np.all((s * info["yaw"] >= sc.yaw_range[0] - 1e-6) & (s * info["yaw"] <= sc.yaw_range[1] + 1e-6))
    # the arms are at home, the banana wholly on its side of the mirror plane
    nr = env.info.nq_robot
    np.testing.assert_allclose(q[:, :nr], np.broadcast_to(env.home_qpos[:nr], (64, nr)), atol=1e-6)
    assert np.all(np.abs(q[:, a + 1]) > sc.footprint_radius())
    # With the same key, "left" and "right" are exact mirror images (S on qpos)
    ql, il = _starts({"side": "left"}, env, n=8)
    qr, ir = _starts({"side": "right"}, env, n=8)
    np.testing.assert_allclose(np.asarray(jax.vmap(env.sym.qpos)(jnp.asarray(ql))), qr, atol=1e-6)
    np.testing.assert_allclose(il["yaw"], -ir["yaw"])
    # each option changes only what it names
    qm, im = _starts({"mirrored_orientation": True}, env)
    quat = slice(a + 3, a + 7)
    np.testing.assert_array_equal(np.delete(qm, np.r_[quat], axis=1), np.delete(q, np.r_[quat], axis=1))
    np.testing.assert_allclose(im["yaw"], -info["yaw"])
    assert np.all(s * im["yaw"] < 0)
    qa, ia = _starts({"asymmetric_quality": 1.0}, env)
    np.testing.assert_array_equal(qa, q)
    np.testing.assert_array_equal(ia["perturbed"], s < 0)  # every right-side episode
    qw, iw = _starts({"wide_init": 1.5}, env, n=256)
    assert np.abs(iw["yaw"]).max() > sc.yaw_range[1] and np.abs(iw["yaw"]).min() < sc.yaw_range[0]
    assert np.all(np.abs(qw[:, a + 1]) > sc.footprint_radius())


def test_starts_are_clear_and_not_successful(env):
    q, info = _starts({"wide_init": 1.5}, env, n=6)
    m = env.mj_model
    table = m.geom("table").id
    banana = set(env.scene._ids(env)["geoms"])
    for i in range(len(q)):
        d = mujoco.MjData(m)
        d.qpos[:] = q[i]
        mujoco.mj_forward(m, d)
        for c in d.contact[: d.ncon]:  # only the banana resting on the table
            pair = {int(c.geom1), int(c.geom2)}
            assert c.dist > -1e-3 and table in pair and (pair - {table}) <= banana
        _, success, metrics = env.scene.evaluate(mjx.put_data(m, d), {k: v[i] for k, v in info.items()}, env)
        assert not bool(success) and float(metrics["banana_height"]) < 1e-3


# ---------------------------------------------------------------------------- success
_ACT = {}


def _host_expert(env, key, snapshots, info_over=None):
    """Run the expert against MuJoCo C from ``key``'s start; returns copies of the MjData
    after each control step count in ``snapshots`` (ascending) and the start's info."""
    if env not in _ACT:
        expert = make_expert(env)
        _ACT[env] = (expert, jax.jit(lambda e: expert.act(e, None)))
    expert, act = _ACT[env]
    q0, info = env.scene.init(key, env)
    info = {**info, **(info_over or {})}
    e = expert.init(types.SimpleNamespace(data=types.SimpleNamespace(qpos=q0), info=info))
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(q0)
    d.ctrl[:] = env.home_ctrl
    mujoco.mj_forward(m, d)
    out = []
    for t in range(max(snapshots)):
        e, a = act(e)
        a = np.asarray(a).reshape(2, -1)
        ctrl = env.home_ctrl.copy()
        ctrl[env.arm_act.reshape(-1)] = a[:, :-1].reshape(-1)
        ctrl[env.grip_act.reshape(-1)] = np.asarray(env.info.gripper_ctrl(a[:, -1:])).reshape(-1)
        d.ctrl[:] = np.clip(ctrl, env.ctrl_lo, env.ctrl_hi)
        for _ in range(env.n_substeps):
            mujoco.mj_step(m, d)
        if t + 1 in snapshots:
            out.append(copy.copy(d))
    return out, info


def _side_keys(env):
    """A key whose start is on the left, then one on the right."""
    keys = {}
    for seed in range(20):
        side = float(env.scene.init(jax.random.key(seed), env)[1]["side"])
        keys.setdefault(side, jax.random.key(seed))
    return keys[1.0], keys[-1.0]


def _evaluate(env, d, info):
    _, success, metrics = env.scene.evaluate(mjx.put_data(env.mj_model, d), info, env)
    return bool(success), {k: float(v) for k, v in metrics.items()}


def test_success_predicate_on_hand_built_and_expert_states(env):
    """True only when the receiver alone holds the banana above the table: checked on the
    expert's states in MuJoCo C (both hold it; the receiver alone; on both sides) and on
    hand-built states (floating banana touched by nobody; the start)."""
    m = env.mj_model
    sc = env.scene
    for key in _side_keys(env):
        (both, alone), info = _host_expert(env, key, (CFG.phase_end("settle2"), CFG.horizon + 5))
        ok, t = _evaluate(env, both, info)
        assert not ok and t["receiver_holds"] == 1 and t["giver_free"] == 0 and t["lifted"] == 1, t
        ok, t = _evaluate(env, alone, info)
        assert ok and t["receiver_holds"] == 1 and t["giver_free"] == 1 and t["banana_height"] > sc.min_height, t
        # the same state read with the other side as the giver: the "receiver" is free
        ok, t = _evaluate(env, alone, {**info, "side": -info["side"]})
        assert not ok and t["receiver_holds"] == 0
        # held by the receiver but lowered onto the table: not lifted
        low = mujoco.MjData(m)
        low.qpos[:] = alone.qpos
        a = sc._ids(env)["qadr"]
        low.qpos[a + 2] -= alone.xpos[m.body("banana").id][2] - sc.radius + 0.001
        mujoco.mj_forward(m, low)
        ok, t = _evaluate(env, low, info)
        assert not ok and t["lifted"] == 0
    # a banana floating in the air, touched by nobody
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(sc.placed_qpos(jnp.asarray(env.home_qpos), env, [0.3, 0.0, 0.1]))
    mujoco.mj_forward(m, d)
    ok, t = _evaluate(env, d, {"side": np.float32(1.0), "yaw": np.float32(0.0), "perturbed": False})
    assert not ok and t["receiver_holds"] == 0 and t["lifted"] == 1


def test_perturbed_expert_drops_the_banana(env):
    """The perturbed script opens the giver during the transfer (MuJoCo C)."""
    (d,), info = _host_expert(env, jax.random.key(1), (CFG.horizon + 5,), {"perturbed": jnp.asarray(True)})
    ok, t = _evaluate(env, d, info)
    assert not ok and t["banana_height"] < 0.005


# ---------------------------------------------------------------------------- slow
N_SEEDS = 4  # default starts (+ their mirror images)
N_MIRRORED = 4  # starts with mirrored_orientation=True (half on each side)
N_PERTURBED = 16  # right-side starts with asymmetric_quality=1.0


episodes, test_expert_generic_checks = expert_fixtures(TASK)


@pytest.fixture(scope="module")
def mjx_rollouts(episodes):
    """The shared episodes' compiled rollout run from another batch of starts: N_SEEDS starts
    on the left, the same keys' starts on the right (their exact mirror images, see
    ``test_initial_distribution_and_shift_options``), N_MIRRORED starts with
    ``mirrored_orientation=True`` and N_PERTURBED right-side starts with
    ``asymmetric_quality=1.0``. The options change only what a scene draws (``qpos`` and
    ``info``), so the one program (``env.reset_to`` the draws, then the expert) runs them all."""
    env = episodes.env
    k = jax.random.split(jax.random.key(5), N_SEEDS + N_MIRRORED + N_PERTURBED)
    groups = [({"side": "left"}, k[:N_SEEDS]), ({"side": "right"}, k[:N_SEEDS]),
              ({"mirrored_orientation": True, "side": "left"}, k[N_SEEDS : N_SEEDS + N_MIRRORED // 2]),
              ({"mirrored_orientation": True, "side": "right"}, k[N_SEEDS : N_SEEDS + N_MIRRORED // 2]),
              ({"side": "right", "asymmetric_quality": 1.0}, k[N_SEEDS + N_MIRRORED :])]
    scenes = [make_scene(TASK, **o) for o, _ in groups]

    @jax.jit  # one small program for the five scenes' draws (vmap alone runs op by op)
    def draws(keys):
        drawn = [jax.vmap(lambda key, sc=sc: sc.init(key, env))(ks) for sc, ks in zip(scenes, keys)]
        return jax.tree.map(lambda *x: jnp.concatenate(x), *drawn)

    qpos, info = draws([ks for _, ks in groups])
    assert len(qpos) == N_SEEDS * 2 + N_MIRRORED + N_PERTURBED
    return run_starts(episodes, qpos, info)


@pytest.mark.slow
def test_expert_hands_over_on_both_sides_and_mirrored_orientation(episodes, mjx_rollouts):
    env = episodes.env
    s0, final, traj = mjx_rollouts
    n = 2 * N_SEEDS + N_MIRRORED
    side = np.asarray(s0.info["side"])[:n]
    success = np.asarray(final.info["success"])[:n]
    print(f"\nbanana_handover MJX: sides {side.tolist()}, success {success.tolist()}, final "
          f"height {np.asarray(final.metrics['banana_height'], np.float64)[:n].round(3).tolist()}")
    assert np.all(side[:N_SEEDS] == 1.0) and np.all(side[N_SEEDS : 2 * N_SEEDS] == -1.0)
    yaw = np.asarray(s0.info["yaw"])
    assert np.all(side[2 * N_SEEDS :] * yaw[2 * N_SEEDS : n] < 0)  # mirrored orientations
    assert set(side[2 * N_SEEDS :].tolist()) == {-1.0, 1.0}
    assert success.all()
    # at the end the receiver alone holds the banana, above the table
    for k in ("receiver_holds", "giver_free", "lifted"):
        assert np.all(np.asarray(final.metrics[k])[:n] == 1.0), k
    # the mirror-image starts: S maps the actions (open loop)
    act = traj["action"]
    err = np.abs(np.asarray(env.action_symmetry(jnp.asarray(act[:N_SEEDS]))) - act[N_SEEDS : 2 * N_SEEDS]).max()
    assert err < 1e-3, err


@pytest.mark.slow
def test_perturbed_episodes_fail(mjx_rollouts):
    s0, final, _ = mjx_rollouts
    bad = slice(2 * N_SEEDS + N_MIRRORED, None)
    assert np.all(np.asarray(s0.info["perturbed"])[bad]) and np.all(np.asarray(s0.info["side"])[bad] < 0)
    success = np.asarray(final.info["success"])[bad]
    print(f"\nbanana_handover perturbed: {int(success.sum())}/{success.size} succeeded")
    assert success.sum() <= 1
