"""Environment API, mirror_state, observation/action symmetry, dynamics equivariance, bad input."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from equibim_jax.sim import robot_names
from equibim_jax.sim.env import Env, EnvConfig, Scene, VmapEnv
from equibim_jax.sim.scenes import BoxScene

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)



@functools.lru_cache(maxsize=None)
def _env(robot="robot_a", action="joint"):
    return Env(EnvConfig(robot=robot, obs=("qpos", "ee"), action=action, episode_length=5),
               BoxScene(side="both"))


@pytest.mark.parametrize("robot", [pytest.param(r, marks=pytest.mark.slow) if r != "robot_a" else r
                                   for r in robot_names()])
def test_reset_step_shapes_no_nan_and_vmap(robot):
    env = _env(robot)
    venv = VmapEnv(env)
    s = jax.jit(venv.reset)(jax.random.split(jax.random.key(0), 3))
    assert s.obs["qpos"].shape == (3, env.action_size)
    assert s.obs["ee"].shape == (3, 2 * (3 + 6 + 1))
    step = jax.jit(venv.step)
    q_start = np.asarray(s.obs["qpos"])
    for _ in range(6):
        s = step(s, s.obs["qpos"])
    for leaf in jax.tree.leaves((s.obs, s.data.qpos, s.data.qvel)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert s.done.tolist() == [True] * 3  # episode_length=5 reached
    # Holding the current joint targets keeps the arms near where they are.
    assert np.abs(np.asarray(s.obs["qpos"]) - q_start).max() < 0.05


def test_reset_is_deterministic_and_sides_mirror_symmetric():
    env = _env()
    keys = jax.random.split(jax.random.key(7), 64)
    r = jax.jit(jax.vmap(env.reset))
    a, b = r(keys), r(keys)
    np.testing.assert_array_equal(np.asarray(a.data.qpos), np.asarray(b.data.qpos))
    sides = np.asarray(a.info["side"])
    assert set(sides.tolist()) == {-1.0, 1.0}


@pytest.mark.parametrize("robot", [pytest.param(r, marks=pytest.mark.slow) if r != "robot_a" else r
                                   for r in robot_names()])
def test_mirror_state_involution_and_obs_equivariance(robot):
    env = _env(robot)
    # A random posture with velocities, so every field is non-trivial.
    rng = np.random.default_rng(0)
    dq = np.zeros(env.mj_model.nq, np.float32)
    dq[env.arm_qadr] = rng.uniform(-0.4, 0.4, env.arm_qadr.shape)
    qvel = jnp.asarray(rng.normal(size=env.mj_model.nv), jnp.float32)
    from mujoco import mjx

    @jax.jit  # one compiled program: reset, perturb, forward, observe, mirror twice
    def states(key, dq, qvel):
        s = env.reset(key)
        data = mjx.forward(env.mjx_model, s.data.replace(qpos=s.data.qpos + dq, qvel=qvel))
        s = s.replace(data=data, obs=env.observe(data))
        sm = env.mirror_state(s)
        return s, sm, env.mirror_state(sm)

    s, sm, smm = states(jax.random.key(3), jnp.asarray(dq), qvel)
    np.testing.assert_allclose(smm.data.qpos, s.data.qpos, atol=1e-6)
    np.testing.assert_allclose(smm.data.qvel, s.data.qvel, atol=1e-6)
    assert float(sm.info["side"]) == -float(s.info["side"])
    # Observations of the mirrored state are the mirrored observations.
    expect = env.obs_symmetry(s.obs)
    for k in ("qpos", "ee"):
        np.testing.assert_allclose(sm.obs[k], expect[k], atol=2e-5, err_msg=k)
    # Bodies: every body of the mirrored state sits at the mirror of its partner.
    xpos, xpos_m = np.asarray(s.data.xpos), np.asarray(sm.data.xpos)
    np.testing.assert_allclose(xpos_m[env.sym.bodies], xpos * [1, -1, 1], atol=2e-5)


@pytest.fixture
def x64():
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", False)


@pytest.mark.slow  # long compile; CI runs it with the slow suite
def test_dynamics_equivariance_with_contacts(x64):
    """step(S s, S a) stays close to S step(s, a) over 100 steps with the gripper on a box.

    The left gripper is driven down onto a box by end-effector targets, closes and lifts,
    with random noise on all actions; float64, elliptic friction cones (pyramidal cones
    are not invariant to rotations about the contact normal, so they break the mirror at
    ~1e-6 as soon as a contact slides). Contact dynamics amplify round-off, so the bound is
    relative to the chaos of the system itself: the mirror drift must stay within 10x the
    drift caused by moving the box by 1e-9 m in the initial state. A real asymmetry (a
    flipped sign, a moved pad) gives drift far above that.
    """
    env = Env(EnvConfig(obs=("qpos", "ee"), action="ee", cone="elliptic"),
              BoxScene(x_range=(0.3, 0.3), y_range=(0.3, 0.3), side="left"))
    s0 = jax.jit(env.reset)(jax.random.key(0))
    T = 100
    z = jnp.concatenate([jnp.linspace(0.2, 0.03, 50), jnp.linspace(0.03, 0.2, 50)])
    grip = jnp.concatenate([jnp.ones(40), jnp.zeros(60)])
    down = jnp.array([0.0, 0.0, -1.0, 0.0, 1.0, 0.0])
    left = jnp.concatenate([jnp.full((T, 2), 0.3), z[:, None], jnp.tile(down, (T, 1)), grip[:, None]], 1)
    right = jnp.tile(s0.obs["ee"][10:], (T, 1))
    acts = jnp.concatenate([left, right], 1) + 0.005 * jax.random.normal(jax.random.key(1), (T, 20))

    @jax.jit  # one program for the three rollouts (no eager MJX: op by op, it compiles thousands)
    def roll(s, acts, mirror_in, mirror_out):
        pick = lambda m, x: jnp.where(mirror_in, m, x)
        s = jax.tree.map(pick, env.mirror_state(s), s)
        acts = pick(jax.vmap(env.action_symmetry)(acts), acts)

        def body(s, a):
            s2 = env.step(s, a)
            q = jnp.where(mirror_out, env.mirror_data(s2.data).qpos, s2.data.qpos)
            return s2, q

        return jax.lax.scan(body, s, acts)[1]

    q_ref = roll(s0, acts, False, True)  # S(step^t(s, a))
    q_mir = roll(s0, acts, True, False)  # step^t(S s, S a)
    box = env.mj_model.jnt_qposadr[env.mj_model.joint("box").id]
    s_pert = s0.replace(data=s0.data.replace(qpos=s0.data.qpos.at[box].add(1e-9)))
    q_pert = roll(s_pert, acts, False, True)
    drift = np.abs(np.asarray(q_ref) - np.asarray(q_mir)).max(axis=1)
    chaos = np.abs(np.asarray(q_ref) - np.asarray(q_pert)).max(axis=1)
    moved = np.abs(np.asarray(q_ref)[:, box : box + 3] - np.asarray(q_ref)[0, box : box + 3]).max()
    print(f"\nmirror drift (max |qpos| diff) at steps 1/10/50/100: {drift[[0, 9, 49, 99]]}, max "
          f"{drift.max():.2e}; drift from a 1e-9 m box perturbation: max {chaos.max():.2e}; "
          f"box moved {moved * 1000:.1f} mm")
    assert moved > 1e-3, "the gripper never touched the box; the test lost its contacts"
    assert drift[:50].max() < 1e-9  # exact to float64 through the approach and first contact
    assert drift.max() <= 10 * chaos.max() + 1e-9


def test_bad_config_and_actions():
    with pytest.raises(ValueError, match="unknown observation field"):
        EnvConfig(obs=("qpos", "rgbd"))
    with pytest.raises(ValueError, match="unknown action mode"):
        EnvConfig(action="torque")
    with pytest.raises(ValueError, match="unknown robot"):
        EnvConfig(robot="robot_z")
    env = _env()
    s = jax.jit(env.reset)(jax.random.key(0))
    with pytest.raises(ValueError, match="action must have shape"):
        env.step(s, jnp.zeros(env.action_size + 1))
    with pytest.raises(ValueError, match=r"qpos must have shape \(%d,\)" % env.mj_model.nq):
        env.reset_to(jnp.zeros(env.mj_model.nq + 1), {})
    a = s.obs["qpos"].at[2].set(jnp.nan)
    s2 = jax.jit(env.step)(s, a)
    assert float(s2.metrics["nan_action"]) == 1.0
    np.testing.assert_array_equal(s2.data.ctrl, s.data.ctrl)  # targets held, not NaN
    assert np.all(np.isfinite(np.asarray(s2.data.qpos)))
    s3 = jax.jit(env.step)(s, s.obs["qpos"].at[0].set(50.0))
    assert float(s3.metrics["clipped"]) >= 1 and float(s3.metrics["nan_action"]) == 0.0


class _SideCamera(Scene):
    def build(self, spec, info):
        spec.worldbody.add_camera(name="side_cam", pos=[0.0, 0.4, 0.8], xyaxes=[0, -1, 0, 1, 0, 0])


def test_camera_off_the_mirror_plane_is_refused():
    with pytest.raises(ValueError, match="not on the mirror plane"):
        Env(EnvConfig(obs=("qpos", "image"), camera="side_cam"), _SideCamera())


def test_point_cloud_crop_option_and_checks():
    with pytest.raises(ValueError, match="crop must be"):
        EnvConfig(crop=((0.0, -0.1, 0.0), (0.0, 0.1, 0.2)))  # min == max in x
    with pytest.raises(ValueError, match="crop must be"):
        EnvConfig(crop=((0.0, 0.0), (1.0, 1.0)))
    # A box that is not its own mirror image would break point_cloud(mirror(s)) == S(cloud).
    with pytest.raises(ValueError, match="not symmetric about the mirror plane"):
        Env(EnvConfig(obs=("qpos", "point_cloud"), crop=((0.1, -0.2, 0.0), (0.5, 0.3, 0.3))),
            BoxScene(side="both"))
    crop = ((0.1, -0.25, 0.002), (0.5, 0.25, 0.3))
    env = Env(EnvConfig(obs=("qpos", "point_cloud"), n_points=32, crop=crop), BoxScene(side="both"))
    assert env.crop == crop
    pts = np.asarray(jax.jit(env.reset)(jax.random.key(1)).obs["point_cloud"])
    assert pts.shape == (32, 3)
    assert np.all(pts >= np.array(crop[0]) - 1e-6) and np.all(pts <= np.array(crop[1]) + 1e-6)
    # Without a crop the robot's workspace applies (its arms at rest are in the cloud).
    default = Env(EnvConfig(obs=("qpos", "point_cloud"), n_points=32), BoxScene(side="both"))
    assert default.crop == (tuple(default.info.workspace_min), tuple(default.info.workspace_max))
