"""Training TIMAR with the shared loop (:func:`jaxtalk.train.train`) on turn windows."""

from __future__ import annotations

from typing import Any

import jax

from jaxtalk.data.batching import BatchIterator
from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.loss import STREAMS, make_loss_fn
from jaxtalk.models.timar.model import init_params
from jaxtalk.train import OptimConfig, TrainResult, train
from jaxtalk.types import PRNGKeyArray

__all__ = ["train_timar"]


def train_timar(
    config: TimarConfig,
    windows: dict[str, Any],
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    batch_size: int = 16,
    params: Any = None,
    seed: int = 0,
    **train_kwargs: Any,
) -> TrainResult:
    """Train on normalised in-memory windows (``jaxtalk.models.timar.data.windows``).

    The shape of every model's in-memory trainer (``toktalk.train.train_base`` likewise): the
    optimiser settings are one :class:`~jaxtalk.train.OptimConfig`, as the recipes take them.

    Args:
        config: model config.
        windows: ``user_speech``, ``user_motion``, ``agent_speech``, ``agent_motion`` arrays with a
            leading example axis.
        optim: optimiser settings (``total_steps`` is the training length unless ``max_steps``; the
            paper: AdamW 1e-4 at batch 32 on a 1024-wide model, 100 warm-up steps).
        key: PRNG key (initialisation and the per-step keys).
        batch_size: windows per batch (at most the number of windows).
        params: initial parameters (default: fresh :func:`init_params`).
        seed: data order seed.
        **train_kwargs: forwarded to :func:`jaxtalk.train.train` (checkpoints, eval, mesh, progress...).

    Returns:
        :class:`jaxtalk.train.TrainResult` (``result.state.eval_params`` are the parameters to use).

    Raises:
        ValueError: missing streams in ``windows``.
    """
    missing = [k for k in STREAMS if k not in windows]
    if missing:
        raise ValueError(f"windows is missing streams {missing}")
    k_init, k_train = jax.random.split(key)
    if params is None:
        params = init_params(config, k_init)
    n = int(windows["agent_motion"].shape[0])
    data = BatchIterator({k: windows[k] for k in STREAMS}, min(batch_size, n), seed=seed)
    return train(make_loss_fn(config), params, data, optim, key=k_train, metadata={"model": "timar"},
                 **train_kwargs)
