"""The one training loop for every jaxtalk model.

* :func:`train`: AdamW (warm-up + cosine), global-norm clipping, optional bias-corrected EMA, frozen
  parameters, data parallelism over a device mesh, tqdm progress, periodic evaluation, orbax
  checkpoints with exact resumption, a best-validated checkpoint and a ``history.jsonl`` curve; how it
  runs is one :class:`LoopSettings`.
* Lower level: :class:`OptimConfig`, :func:`make_optimizer`, :func:`create_train_state`,
  :func:`make_train_step`, :func:`ema_update`, :class:`Checkpointer`, :func:`save_checkpoint`,
  :func:`restore_checkpoint`, :func:`make_mesh`, :func:`shard_batch`.
* Reading a run's folder: :func:`best_checkpoint_dir` (best vs latest), :func:`read_best`,
  :func:`read_history`, :func:`read_metrics` (``metrics.jsonl``; :mod:`jaxtalk.train.writers` also
  writes TensorBoard event files beside it).
* Watching steps of a run: :class:`StepObserver`, :class:`TraceSteps` (a :mod:`jax.profiler` trace).
"""

from __future__ import annotations

from jaxtalk.train.checkpoint import (
    BEST_DIR,
    HISTORY_FILE,
    Checkpointer,
    CheckpointMismatchError,
    best_checkpoint_dir,
    latest_checkpoint_step,
    read_best,
    read_history,
    restore_checkpoint,
    save_checkpoint,
)
from jaxtalk.train.checks import BatchSpec, check_finite
from jaxtalk.train.ema import ema_decay_at, ema_update
from jaxtalk.train.loop import LoopSettings, NonFiniteLossError, TrainResult, train
from jaxtalk.train.observers import StepObserver, StopRequest, TraceSteps
from jaxtalk.train.optim import OptimConfig, make_optimizer, make_schedule, trainable_mask
from jaxtalk.train.sharding import make_mesh, replicate, shard_batch
from jaxtalk.train.state import TrainState, create_train_state
from jaxtalk.train.step import make_train_step
from jaxtalk.train.writers import METRICS_FILE, RunMetrics, read_metrics

__all__ = [
    "train",
    "LoopSettings",
    "TrainResult",
    "NonFiniteLossError",
    "OptimConfig",
    "make_schedule",
    "make_optimizer",
    "trainable_mask",
    "ema_update",
    "ema_decay_at",
    "TrainState",
    "create_train_state",
    "make_train_step",
    "Checkpointer",
    "CheckpointMismatchError",
    "save_checkpoint",
    "restore_checkpoint",
    "latest_checkpoint_step",
    "best_checkpoint_dir",
    "read_best",
    "read_history",
    "read_metrics",
    "RunMetrics",
    "METRICS_FILE",
    "BEST_DIR",
    "HISTORY_FILE",
    "BatchSpec",
    "check_finite",
    "make_mesh",
    "shard_batch",
    "replicate",
    "StepObserver",
    "StopRequest",
    "TraceSteps",
]
