"""Training: the optimiser and EMA, BC and ``L_sym`` losses of any policy, the jitted step
and loop, checkpoints, and training runs (run folder, resume)."""

from equibim_jax.training.checkpoint import (
    CheckpointError,
    latest_step,
    read_checkpoint_config,
    restore_checkpoint,
    save_checkpoint,
)
from equibim_jax.training.ema import EmaConfig, ema_decay, ema_update
from equibim_jax.training.losses import (
    SYM_NORMS,
    equivariance_error,
    mirror_batch,
    policy_loss,
    sym_loss,
    sym_residual_norm,
)
from equibim_jax.training.online import (
    OnlineConfig,
    OnlineLoop,
    RingBuffer,
    buffer_from_frames,
    empty_buffer,
    make_online_train_loop,
    sample_ring,
)
from equibim_jax.training.run import Run, TrainingDiverged, load_run, prepare_data, read_log, train, train_together
from equibim_jax.training.train_step import (
    BoundTrainFn,
    TrainConfig,
    TrainState,
    base_key,
    build_step_fn,
    create_train_state,
    make_joint_train_loop,
    make_optimizer,
    make_train_loop,
    make_train_step,
    sym_ramp,
)

__all__ = [
    "BoundTrainFn", "CheckpointError", "EmaConfig", "OnlineConfig", "OnlineLoop", "RingBuffer", "Run", "SYM_NORMS", "TrainConfig", "TrainState",
    "TrainingDiverged", "base_key", "build_step_fn", "create_train_state", "ema_decay", "ema_update",
    "equivariance_error", "latest_step", "load_run", "make_joint_train_loop", "make_optimizer", "make_train_loop",
    "make_train_step", "mirror_batch", "policy_loss", "prepare_data", "read_checkpoint_config",
    "read_log", "restore_checkpoint", "save_checkpoint", "sym_loss", "sym_ramp", "sym_residual_norm",
    "train", "train_together", "buffer_from_frames", "empty_buffer", "make_online_train_loop", "sample_ring",
]
