"""The image policies end to end at a tiny size: expert demos with rendered images, a
training run with ``L_sym`` through the run folder, and closed-loop evaluation on both
sides (``act`` with temporal ensembling). ``dp3``'s end-to-end run is ``make demo``'s
(tests/test_demo.py)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from equibim_jax.config import EvalConfig
from equibim_jax.data.generate import generate_demos
from equibim_jax.evaluation.evaluate import evaluate_run
from equibim_jax.policies import ACTConfig, DPConfig, ImageObsConfig, UNetConfig, VisionConfig
from equibim_jax.tasks import make_env
from equibim_jax.training import TrainConfig, load_run, read_log, train

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)

VISION = VisionConfig(channels=(8,), groups=4, keypoints=4, out=8, crop_ratio=0.75)
ENC = ImageObsConfig(image_keys=("image",), vision=VISION, state_hidden=(16,), state_out=8)
POLICIES = {
    "dp": DPConfig(obs_horizon=2, pred_horizon=8, action_horizon=4, encoder=ENC,
                   unet=UNetConfig(down_dims=(16,), kernel_size=3, n_groups=4, step_embed_dim=16),
                   num_inference_steps=4),
    "act": ACTConfig(obs_horizon=1, pred_horizon=8, action_horizon=4, encoder=ENC, d_model=32, n_heads=2,
                     enc_layers=1, dec_layers=1, ff_dim=64, latent_dim=8, cvae_layers=1),
}


@pytest.fixture(scope="module")
def demos():
    env = make_env("click_bell", obs=("qpos", "image"), image_size=16, episode_length=24)
    d, _ = generate_demos(env, jax.random.key(0), 2, length=24, chunk=2, keep_failures=True,
                          progress=False)
    return d


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(POLICIES))
def test_image_policy_trains_and_evaluates(name, demos, tmp_path):
    tc = TrainConfig(batch_size=8, total_steps=20, warmup_steps=2, steps_per_dispatch=10, sym_weight=0.1)
    summary = train(demos, tmp_path / "run", POLICIES[name], tc, progress=False)
    assert summary["steps"] == 20
    rows = read_log(tmp_path / "run" / "train.jsonl")
    assert len(rows) == 2 and all(np.isfinite([r["bc"], r["sym"], r["equiv_err"]]).all() for r in rows)
    assert rows[-1]["sym"] > 0
    run = load_run(tmp_path / "run")
    assert run.policy.config.image_shapes == ((16, 16, 3),)
    ev = EvalConfig(episodes=2, batch=2, temporal_ensemble=0.01 if name == "act" else None)
    res = evaluate_run(tmp_path / "run", ev, progress=False)
    for side in ("trained", "mirrored"):
        assert res[side]["episodes"] == 2
        assert 0.0 <= res[side]["success"] <= 1.0
