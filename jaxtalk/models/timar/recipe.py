"""TIMAR's recipe: conversation windows of a prepared dataset, and the one way the model is trained.

The windows (:mod:`jaxtalk.models.turns.windows`), the training settings and the training itself
(:mod:`jaxtalk.models.turns.training`) are shared with the DualTalk baseline, which TIMAR's Table 1 retrains on
TIMAR's data; this module re-exports the window pieces as part of TIMAR's recipe.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from jaxtalk.models.turns.windows import TurnWindows, agent_sides, fit_data_normalizer, make_windows, window_turns
from jaxtalk.data.loader import PreparedData
from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.runs import RunInfo
from jaxtalk.train import OptimConfig
from jaxtalk.train.recipes import VAL_CLIPS, RecipeResult, TrainSettings
from jaxtalk.models.turns.training import TURN_DEFAULTS, TURN_PRESET_DEFAULTS, train_on_turn_windows
from jaxtalk.types import PRNGKeyArray

__all__ = ["DEFAULTS", "PRESET_DEFAULTS", "TurnWindows", "agent_sides", "fit_data_normalizer", "window_turns", "make_windows",
           "train"]

PyTree = Any

# Small: AdamW 1e-3, 20 warm-up steps, decay to a tenth; paper: AdamW 1e-4, batch 32, 100 warm-up steps.
DEFAULTS: TrainSettings = TURN_DEFAULTS
PRESET_DEFAULTS: dict[str, TrainSettings] = TURN_PRESET_DEFAULTS


def train(
    config: TimarConfig,
    data: PreparedData,
    optim: OptimConfig,
    *,
    steps: int | None = None,
    key: PRNGKeyArray,
    batch_size: int = 16,
    seed: int = 0,
    params: PyTree | None = None,
    run_dir: str | Path | None = None,
    run_info: RunInfo | None = None,
    ckpt_dir: Any = None,
    mesh: Any = None,
    eval_every: int | None = None,
    val_clips: int = VAL_CLIPS,
    **loop_kwargs: Any,
) -> RecipeResult:
    """Train TIMAR on ``data``'s training conversations (arguments as every recipe's ``train``). Each
    evaluation also streams ``val_clips`` val conversation sides turn by turn (as ``jaxtalk eval``)
    and the best checkpoint is the one of the lowest FD (:func:`~jaxtalk.models.turns.training.conversation_validation`).

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``extra`` holds the normaliser, the window's
        turns and the still pose of motionless partners.
    """
    from jaxtalk.models.timar.loss import make_loss_fn
    from jaxtalk.models.timar.model import init_params
    from jaxtalk.models.timar.streaming import stream

    def predict(p: PyTree, streams: Any, key: PRNGKeyArray, context: int) -> Any:
        return stream(p, config, *streams, key, context=context)

    return train_on_turn_windows("timar", config, data, optim, init_params, make_loss_fn, steps=steps, key=key,
                                 batch_size=batch_size, seed=seed, params=params, run_dir=run_dir, run_info=run_info,
                                 ckpt_dir=ckpt_dir, mesh=mesh, eval_every=eval_every, predict=predict,
                                 val_clips=val_clips, **loop_kwargs)
