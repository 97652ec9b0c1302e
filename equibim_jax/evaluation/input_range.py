"""How far a policy's state input leaves its training range in closed loop.

The normaliser maps the training data's range of each channel to ``[-1, 1]`` (min-max;
unscaled channels keep their raw values). A closed-loop episode that drives a channel
far outside that range feeds the network inputs it has never seen. This module rolls a
trained run out and reports, per channel of its state field (``qpos`` or ``ee``), the
largest ``|normalised value|`` reached, over all episodes and control steps, with the
step at which each episode first leaves ``[-2, 2]`` on any channel. Run::

    python -m equibim_jax.evaluation.input_range RUN_DIR --episodes 4 --out F.json
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from equibim_jax._io import atomic_write_json

STATE_FIELDS = ("qpos", "ee")


def state_from_qpos(env: Any, field: str, qpos: jax.Array) -> jax.Array:
    """The ``field`` observation (``"qpos"`` or ``"ee"``) of full joint states ``qpos``
    ``[..., nq]``: per arm the arm joints (or the end-effector pose by forward kinematics)
    and the gripper opening, ``[..., 2 * (n_arm + 1)]`` or ``[..., 2 * (3 + R + 1)]``."""
    if field not in STATE_FIELDS:
        raise ValueError(f"input_range: state field must be one of {STATE_FIELDS}, got {field!r}")
    lead = qpos.shape[:-1]
    flat = qpos.reshape(-1, qpos.shape[-1])
    arm = flat[:, np.asarray(env.arm_qadr).reshape(-1)].reshape(-1, 2, env.info.n_arm)
    opening = jax.vmap(env.gripper_opening)(flat)[..., None]  # [B, 2, 1]
    joint = jnp.concatenate([arm, opening], -1).reshape(flat.shape[0], -1)
    out = joint if field == "qpos" else env.ee_action_from_joint(joint)
    return out.reshape(lead + out.shape[-1:])


def closed_loop_input_range(env: Any, policy: Any, normalizer: Any, params: Any, key: jax.Array,
                            episodes: int, field: str | None = None, threshold: float = 2.0) -> dict:
    """Roll ``episodes`` trained-side episodes and measure the normalised state input.

    Returns ``{"field", "episodes", "success": [E] bool, "max_abs": [D] (per channel, over
    episodes and steps), "max_abs_t": [T] (over episodes and channels, per control step),
    "first_out": [E] (first step with a channel beyond ``threshold``, -1 if none),
    "threshold"}`` as lists.
    """
    from equibim_jax.evaluation.rollout import make_policy_rollout

    field = field or getattr(policy.config, "state_key", None)
    if field not in STATE_FIELDS:
        raise ValueError(f"input_range: the policy's state field is {field!r}; supported: {STATE_FIELDS}")
    if field not in normalizer.fields:
        raise ValueError(f"input_range: the normaliser has no statistics for {field!r}")
    roll = make_policy_rollout(env, policy, normalizer, record_qpos=True)
    out = jax.jit(jax.vmap(roll, in_axes=(None, 0)))(params, jax.random.split(key, episodes))
    state = state_from_qpos(env, field, out["qpos_t"])  # [E, T, D]
    norm = np.abs(np.asarray(normalizer.fields[field].normalize(state)))
    beyond = (norm > threshold).any(-1)  # [E, T]
    first = np.where(beyond.any(-1), beyond.argmax(-1), -1)
    return {"field": field, "episodes": episodes, "success": np.asarray(out["success"]).tolist(),
            "max_abs": norm.max((0, 1)).round(4).tolist(), "max_abs_t": norm.max((0, 2)).round(4).tolist(),
            "first_out": first.tolist(), "threshold": threshold}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m equibim_jax.evaluation.input_range", description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir", help="a trained run's folder (equibim train / experiment output)")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", type=Path, default=None, help="write the report as JSON here")
    a = p.parse_args(argv)
    if a.episodes < 1:
        p.error(f"--episodes must be at least 1, got {a.episodes}")
    from equibim_jax.training.run import load_run

    r = load_run(a.run_dir)
    rep = closed_loop_input_range(r.make_env(), r.policy, r.normalizer, r.state.ema_params,
                                  jax.random.key(a.seed), a.episodes)
    rep = {"run": str(a.run_dir), "command": f"python -m equibim_jax.evaluation.input_range {a.run_dir} "
           f"--episodes {a.episodes} --seed {a.seed}", **rep}
    t = rep["max_abs_t"]
    print(f"{rep['field']}: max |normalised| per channel {rep['max_abs']}")
    print(f"over steps (every 40th): {t[::40]}; first step beyond {rep['threshold']}: {rep['first_out']}; "
          f"success {rep['success']}")
    if a.out is not None:
        atomic_write_json(a.out, rep)
    return rep


if __name__ == "__main__":
    main()
