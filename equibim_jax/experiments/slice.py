"""DRAFT, not yet run end to end (issue 4): nothing imports it and no test covers it.

The first end-to-end slice: expert demos on one side -> baseline vs +EquiBim -> both sides.

``run_slice(SliceConfig(...))`` generates demos of one task on the ``train_side`` only,
fits ONE mirror-consistent normaliser, trains two diffusion policies with identical
settings (seed included) that differ only in ``L_sym``'s weight, and evaluates both in
closed loop on the trained side and on the mirrored side. Every number it returns comes
from this run.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from equibim_jax._io import atomic_write_json
from equibim_jax.data import fit_normalizer, normalized_symmetry
from equibim_jax.data.dataset import Demos, save
from equibim_jax.data.generate import generate_demos
from equibim_jax.evaluation.rollout import evaluate, make_policy_rollout
from equibim_jax.policies import EncoderConfig, PolicyConfig, UNetConfig, init_params
from equibim_jax.tasks import make_env
from equibim_jax.training import TrainConfig, create_train_state, make_dataset, make_train_loop
from equibim_jax.training.checkpoint import save_checkpoint


@dataclasses.dataclass(frozen=True)
class SliceConfig:
    """Settings of the slice (frozen; the README's main command uses the defaults)."""

    task: str = "place_empty_cup"
    train_side: str = "left"
    n_demos: int = 24
    n_points: int = 64
    episode_length: int = 300
    down_dims: tuple[int, ...] = (32, 64, 128)
    batch_size: int = 64
    train_steps: int = 1500
    steps_per_dispatch: int = 50
    learning_rate: float = 1e-3
    sym_weight: float = 1.0
    eval_episodes: int = 64
    seed: int = 0
    out_dir: str = "results/demo"

    def __post_init__(self):
        if self.train_side not in ("left", "right"):
            raise ValueError(f"train_side must be 'left' or 'right', got {self.train_side!r}")
        for name in ("n_demos", "n_points", "episode_length", "batch_size", "train_steps",
                     "steps_per_dispatch", "eval_episodes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.train_steps % self.steps_per_dispatch:
            raise ValueError("train_steps must be a multiple of steps_per_dispatch")
        if self.sym_weight <= 0:
            raise ValueError("sym_weight must be > 0 (the EquiBim run needs L_sym)")


def flatten_episodes(demos: Demos) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Concatenate the valid steps of every episode: ``{field: [F, ...]}``, ends ``[E]``."""
    frames = {k: np.concatenate([v[e, : demos.length[e]] for e in range(demos.n_episodes)])
              for k, v in demos.obs.items()}
    frames["action"] = np.concatenate([demos.action[e, : demos.length[e]] for e in range(demos.n_episodes)])
    return frames, np.cumsum(demos.length).astype(np.int64)


def _env(cfg: SliceConfig, side: str):
    return make_env(cfg.task, obs=("qpos", "point_cloud"), action="joint", side=side,
                    n_points=cfg.n_points, episode_length=cfg.episode_length)


def run_slice(cfg: SliceConfig, progress: bool = True) -> dict:
    """Run the slice; returns the results dict (also written to ``out_dir/results.json``)."""
    t_start = time.perf_counter()
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    key = jax.random.key(cfg.seed)
    k_demo, k_eval = jax.random.split(key)
    timings = {}

    # 1. Demos on the training side only.
    env = _env(cfg, cfg.train_side)
    t0 = time.perf_counter()
    demos, gen_stats = generate_demos(env, k_demo, cfg.n_demos, chunk=min(32, cfg.n_demos),
                                      progress=progress, meta={"seed": cfg.seed})
    save(demos, out / "demos.zarr", overwrite=True)
    timings["generate_s"] = time.perf_counter() - t0

    # 2. One mirror-consistent normaliser for both runs.
    frames, ends = flatten_episodes(demos)
    raw_sym = {"qpos": env.obs_symmetry.ops["qpos"], "point_cloud": env.obs_symmetry.ops["point_cloud"],
               "action": env.action_symmetry}
    normalizer = fit_normalizer(frames, raw_sym)
    nframes = normalizer.normalize(frames)
    sym = normalized_symmetry(raw_sym, normalizer)
    policy_cfg = PolicyConfig(
        action_dim=env.action_size, state_dim=frames["qpos"].shape[-1],
        encoder=EncoderConfig(state_key="qpos", pc_key="point_cloud"),
        unet=UNetConfig(down_dims=cfg.down_dims),
    )
    dataset = make_dataset(nframes, ends, policy_cfg)

    results = {}
    model = init_params(policy_cfg, jax.random.key(cfg.seed))[0]
    for name, weight in (("baseline", 0.0), ("equibim", cfg.sym_weight)):
        train_cfg = TrainConfig(batch_size=cfg.batch_size, learning_rate=cfg.learning_rate,
                                total_steps=cfg.train_steps, warmup_steps=min(100, cfg.train_steps // 10),
                                steps_per_dispatch=cfg.steps_per_dispatch, sym_weight=weight,
                                seed=cfg.seed)
        state, model = create_train_state(policy_cfg, train_cfg)
        loop = make_train_loop(policy_cfg, train_cfg, dataset, sym if weight > 0 else None)
        tkey = jax.random.key(cfg.seed + 1)
        log_path = out / f"{name}_train.jsonl"
        t0 = time.perf_counter()
        with open(log_path, "w") as log, tqdm(total=cfg.train_steps, desc=f"train {name}",
                                               disable=not progress) as bar:
            for _ in range(cfg.train_steps // cfg.steps_per_dispatch):
                state, metrics = loop(state, tkey)
                m = {k: float(np.mean(v)) for k, v in jax.device_get(metrics).items()}
                log.write(json.dumps({"step": int(state.step), **m}) + "\n")
                bar.update(cfg.steps_per_dispatch)
                bar.set_postfix(bc=f"{m['bc']:.4f}", sym=f"{m['sym']:.4f}")
        train_s = time.perf_counter() - t0
        save_checkpoint(out / f"{name}_ckpt", state, normalizer, {"policy": policy_cfg, "train": train_cfg},
                        step=int(state.step))

        res = {"train_s": train_s, "final_bc": m["bc"], "final_sym": m["sym"]}
        for label, side in (("trained_side", cfg.train_side),
                            ("mirrored_side", "right" if cfg.train_side == "left" else "left")):
            eval_env = _env(cfg, side)
            roll = make_policy_rollout(eval_env, model, normalizer)
            r = evaluate(roll, state.ema_params, k_eval, cfg.eval_episodes)
            res[label] = {k: r[k] for k in ("success", "ci95", "episodes", "successes", "wall_s")}
        results[name] = res

    results.update({
        "wall_time_s": time.perf_counter() - t_start,
        "demos": {"n": demos.n_episodes, "steps": demos.n_steps, **gen_stats},
        "timings": timings,
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()},
    })
    return results
