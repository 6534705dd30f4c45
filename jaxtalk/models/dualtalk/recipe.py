"""The DualTalk baseline's recipe: TIMAR's windows, TIMAR's training settings, DualTalk's loss.

TIMAR's Table 1 retrains DualTalk "under the same training configuration as TIMAR", so the windows
(``num_turns`` whole turns of both sides' per-turn speech and motion, every turn step of every training
conversation), the normaliser fitted on the training agents, the still pose of motionless partners and
the optimiser settings are all TIMAR's (:mod:`jaxtalk.models.turns.windows`, :mod:`jaxtalk.models.turns.training`,
shared a layer below both models): both models see identical data.
"""

from __future__ import annotations

from typing import Any


from jaxtalk.data.loader import PreparedData
from jaxtalk.models.dualtalk.config import DualTalkConfig
from jaxtalk.runs import RunSettings
from jaxtalk.train import OptimConfig
from jaxtalk.train.recipes import VAL_CLIPS, RecipeResult, TrainSettings
from jaxtalk.models.turns.training import TURN_DEFAULTS, TURN_PRESET_DEFAULTS, train_on_turn_windows
from jaxtalk.models.turns.windows import Normalizer
from jaxtalk.types import PRNGKeyArray

__all__ = ["DEFAULTS", "PRESET_DEFAULTS", "train"]

PyTree = Any

# TIMAR's settings per preset (small: AdamW 1e-3, 20 warm-up steps, decay to a tenth; paper: AdamW
# 1e-4, batch 32, 100 warm-up steps, constant after), the same objects so the two never drift apart.
DEFAULTS: TrainSettings = TURN_DEFAULTS
PRESET_DEFAULTS: dict[str, TrainSettings] = dict(TURN_PRESET_DEFAULTS)


def train(
    config: DualTalkConfig,
    data: PreparedData,
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    run: RunSettings = RunSettings(),
    params: PyTree | None = None,
    val_clips: int = VAL_CLIPS,
    normalizer: Normalizer | dict[str, Any] | None = None,
) -> RecipeResult:
    """Train the DualTalk baseline on ``data``'s training conversations (arguments as every recipe's
    ``train``). Each evaluation also predicts ``val_clips`` val conversation sides turn by turn (as
    ``jaxtalk eval``) and the best checkpoint is the one of the lowest FD
    (:func:`~jaxtalk.models.turns.training.conversation_validation`).

    ``normalizer``: the standardisation to train with (a fine-tuned run keeps its starting run's, as
    ``jaxtalk train --init`` does); None: fitted on ``data``'s training agents. ``run.window_frames`` must
    be None (the windows are whole turns).

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``extra`` holds the normaliser, the window's
        turns and the still pose of motionless partners (as TIMAR's run).
    """
    from jaxtalk.models.dualtalk.loss import make_loss_fn
    from jaxtalk.models.dualtalk.model import init_params
    from jaxtalk.models.dualtalk.predict import predict_turns

    def predict(p: PyTree, streams: Any, key: PRNGKeyArray, context: int) -> Any:
        return predict_turns(p, config, *streams, context=context)  # deterministic: no key

    return train_on_turn_windows("dualtalk", config, data, optim, init_params, make_loss_fn, key=key, run=run,
                                 params=params, normalizer=normalizer, predict=predict, val_clips=val_clips)
