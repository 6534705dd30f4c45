"""TIMAR's recipe: conversation windows of a prepared dataset, and the one way the model is trained.

The windows (:mod:`jaxtalk.models.turns.windows`), the training settings and the training itself
(:mod:`jaxtalk.models.turns.training`) are shared with the DualTalk baseline, which TIMAR's Table 1 retrains on
TIMAR's data; this module re-exports the window pieces as part of TIMAR's recipe.
"""

from __future__ import annotations

from typing import Any

from jaxtalk.models.turns.windows import (Normalizer, TurnWindows, agent_sides, fit_data_normalizer, make_windows,
                                          window_turns)
from jaxtalk.data.loader import PreparedData
from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.runs import RunSettings
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
    key: PRNGKeyArray,
    run: RunSettings = RunSettings(),
    params: PyTree | None = None,
    val_clips: int = VAL_CLIPS,
    normalizer: Normalizer | dict[str, Any] | None = None,
) -> RecipeResult:
    """Train TIMAR on ``data``'s training conversations (arguments as every recipe's ``train``). Each
    evaluation also streams ``val_clips`` val conversation sides turn by turn (as ``jaxtalk eval``)
    and the best checkpoint is the one of the lowest FD (:func:`~jaxtalk.models.turns.training.conversation_validation`).

    ``normalizer``: the standardisation to train with (a fine-tuned run keeps its starting run's, as
    ``jaxtalk train --init`` does); None: fitted on ``data``'s training agents. ``run.window_frames`` must
    be None (the windows are whole turns).

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``extra`` holds the normaliser, the window's
        turns and the still pose of motionless partners.
    """
    from jaxtalk.models.timar.loss import make_loss_fn
    from jaxtalk.models.timar.model import init_params
    from jaxtalk.models.timar.streaming import stream

    def predict(p: PyTree, streams: Any, key: PRNGKeyArray, context: int) -> Any:
        return stream(p, config, *streams, key, context=context)

    return train_on_turn_windows("timar", config, data, optim, init_params, make_loss_fn, key=key, run=run,
                                 params=params, normalizer=normalizer, predict=predict, val_clips=val_clips)
