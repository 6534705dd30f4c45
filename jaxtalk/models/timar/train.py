"""Training TIMAR with the shared loop (:func:`jaxtalk.train.train`) on turn windows."""

from __future__ import annotations

from typing import Any

import jax

from jaxtalk.data.batching import BatchIterator
from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.loss import STREAMS, make_loss_fn
from jaxtalk.models.timar.model import init_params
from jaxtalk.train import OptimConfig, TrainResult, train

__all__ = ["train_timar"]


def train_timar(
    config: TimarConfig,
    windows: dict[str, Any],
    *,
    steps: int,
    batch_size: int = 16,
    lr: float = 1e-3,
    warmup_steps: int = 20,
    weight_decay: float = 1e-2,
    ema_decay: float | None = None,
    seed: int = 0,
    params: Any = None,
    progress: bool = False,
    **train_kwargs: Any,
) -> TrainResult:
    """Train on normalised windows (``jaxtalk.models.timar.data.windows``) with AdamW + cosine.

    Args:
        config: model config.
        windows: ``user_speech``, ``user_motion``, ``agent_speech``, ``agent_motion`` arrays with a
            leading example axis.
        steps: optimiser steps.
        batch_size: windows per batch.
        lr: peak learning rate (the paper: 1e-4 at batch 32 on a 1024-wide model; small models on
            CPU train faster with 1e-3).
        warmup_steps: linear warm-up (the paper: 100 iterations), capped at ``steps // 10`` so
            short runs keep a decay phase (optax's cosine needs ``decay > warm-up`` steps).
        weight_decay: AdamW weight decay.
        ema_decay: EMA of the weights (None: off).
        seed: seeds parameters, data order and the per-step keys.
        params: initial parameters (default: fresh :func:`init_params`).
        progress: tqdm progress bar.
        **train_kwargs: forwarded to :func:`jaxtalk.train.train` (checkpoints, eval, mesh, ...).

    Returns:
        :class:`jaxtalk.train.TrainResult` (``result.state.eval_params`` are the parameters to use).

    Raises:
        ValueError: missing streams in ``windows``, ``steps`` < 1, negative ``warmup_steps`` or
            bad optimiser settings.
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if warmup_steps < 0:
        raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
    missing = [k for k in STREAMS if k not in windows]
    if missing:
        raise ValueError(f"windows is missing streams {missing}")
    key = jax.random.key(seed)
    k_init, k_train = jax.random.split(key)
    if params is None:
        params = init_params(config, k_init)
    n = int(windows["agent_motion"].shape[0])
    data = BatchIterator({k: windows[k] for k in STREAMS}, min(batch_size, n), seed=seed)
    opt = OptimConfig(
        lr=lr, weight_decay=weight_decay, warmup_steps=min(warmup_steps, steps // 10), total_steps=steps,
        ema_decay=ema_decay, final_lr_ratio=0.1,
    )
    return train(
        make_loss_fn(config), params, data, opt, key=k_train, progress=progress,
        metadata={"model": "timar"}, **train_kwargs,
    )
