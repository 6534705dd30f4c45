"""The DualTalk baseline's recipe: TIMAR's windows, TIMAR's training settings, DualTalk's loss.

TIMAR's Table 1 retrains DualTalk "under the same training configuration as TIMAR", so the windows
(``num_turns`` whole turns of both sides' per-turn speech and motion, every turn step of every training
conversation), the normaliser fitted on the training agents, the still pose of motionless partners and
the optimiser settings are all TIMAR's (:mod:`jaxtalk.models.turns.windows`, :mod:`jaxtalk.models.turns.training`,
shared a layer below both models): both models see identical data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


from jaxtalk.data.loader import PreparedData
from jaxtalk.models.dualtalk.config import DualTalkConfig
from jaxtalk.runs import RunInfo
from jaxtalk.train import OptimConfig
from jaxtalk.train.recipes import VAL_CLIPS, RecipeResult, TrainSettings
from jaxtalk.models.turns.training import TURN_DEFAULTS, TURN_PRESET_DEFAULTS, train_on_turn_windows
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
    """Train the DualTalk baseline on ``data``'s training conversations (arguments as every recipe's
    ``train``). Each evaluation also predicts ``val_clips`` val conversation sides turn by turn (as
    ``jaxtalk eval``) and the best checkpoint is the one of the lowest FD
    (:func:`~jaxtalk.models.turns.training.conversation_validation`).

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``extra`` holds the normaliser, the window's
        turns and the still pose of motionless partners (as TIMAR's run).
    """
    from jaxtalk.models.dualtalk.loss import make_loss_fn
    from jaxtalk.models.dualtalk.model import init_params
    from jaxtalk.models.dualtalk.predict import predict_turns

    def predict(p: PyTree, streams: Any, key: PRNGKeyArray, context: int) -> Any:
        return predict_turns(p, config, *streams, context=context)  # deterministic: no key

    return train_on_turn_windows("dualtalk", config, data, optim, init_params, make_loss_fn, steps=steps,
                                 key=key, batch_size=batch_size, seed=seed, params=params, run_dir=run_dir,
                                 run_info=run_info, ckpt_dir=ckpt_dir, mesh=mesh, eval_every=eval_every,
                                 predict=predict, val_clips=val_clips, **loop_kwargs)
