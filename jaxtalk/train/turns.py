"""How TIMAR and the DualTalk baseline are trained: the same turn windows, settings and key split.

TIMAR's Table 1 retrains DualTalk "under the same training configuration as TIMAR"; both recipes call
:func:`train_on_turn_windows` with their own model's ``init_params`` and loss, so neither imports the
other.
"""

from __future__ import annotations

import dataclasses

from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxtalk.data.batching import fit_length
from jaxtalk.data.conversation import TimarWindows, agent_sides, make_windows, side_streams
from jaxtalk.data.loader import PreparedData
from jaxtalk.runs import RunInfo
from jaxtalk.train.optim import OptimConfig
from jaxtalk.train.recipes import VAL_CLIPS, RecipeResult, TrainSettings, fit_recipe, host_copy, spread
from jaxtalk.types import PRNGKeyArray

__all__ = ["TURN_DEFAULTS", "TURN_PRESET_DEFAULTS", "train_on_turn_windows", "conversation_validation",
           "SELECTION_METRIC"]

PyTree = Any
# ``predict(params, (user_speech, user_motion, agent_speech), key, context) -> (1, F, 56)``: a turn
# model's agent motion for one conversation side, in the training normalisation.
Predict = Callable[[PyTree, tuple[np.ndarray, np.ndarray, np.ndarray], PRNGKeyArray, int], Any]

# The metric a turn model's run selects its best checkpoint by: the Frechet distance of the agent's
# motion to the truth's, at the scale the published tables print, averaged over the three groups
# (expression, jaw, pose); the metric TIMAR's tables lead with.
SELECTION_METRIC = "FD"

# What trains TIMAR's small model (and the baseline's) on 2 CPU cores.
TURN_DEFAULTS = TrainSettings(lr=1e-3, warmup_steps=20, final_lr_ratio=0.1)
# Training settings of each config preset. The paper (Sec. 4): AdamW at 1e-4, batch 32, a 100-iteration
# warm-up and no stated decay, so the rate stays constant after the warm-up (as MAR's public recipe).
TURN_PRESET_DEFAULTS: dict[str, TrainSettings] = {
    "small": TURN_DEFAULTS,
    "paper": TrainSettings(lr=1e-4, warmup_steps=100, final_lr_ratio=1.0, batch_size=32),
}
# The public code's released model (``TimarConfig.reference``, ``jaxtalk convert``) trained like the paper.
TURN_PRESET_DEFAULTS["reference"] = TURN_PRESET_DEFAULTS["paper"]


def train_on_turn_windows(
    model: str,
    config: Any,
    data: PreparedData,
    optim: OptimConfig,
    init_params: Callable[[Any, PRNGKeyArray], PyTree],
    make_loss_fn: Callable[[Any], Callable[..., Any]],
    *,
    steps: int | None,
    key: PRNGKeyArray,
    batch_size: int,
    seed: int,
    params: PyTree | None,
    run_dir: str | Path | None,
    run_info: RunInfo | None,
    ckpt_dir: Any,
    mesh: Any,
    eval_every: int | None,
    normalizer: Any = None,
    predict: Predict | None = None,
    val_clips: int = VAL_CLIPS,
    **loop_kwargs: Any,
) -> RecipeResult:
    """The training TIMAR and the DualTalk baseline share: :func:`make_windows`' turn windows and
    normaliser, one key split (init / train / eval) and the run's ``extra`` (normaliser, window turns,
    still pose), so that both models see the same data under the same settings.

    Args:
        model: the run's model name (``"timar"``, ``"dualtalk"``).
        config: the model's config (a :class:`TurnConfig`).
        init_params: ``(config, key) -> params`` (used when ``params`` is None).
        make_loss_fn: ``config -> loss_fn`` for :func:`~jaxtalk.train.recipes.fit_recipe`.
        normalizer: the standardisation to train with (a :class:`~jaxtalk.data.conversation.Normalizer`
            or its ``to_dict()``): a fine-tuned run keeps its starting run's; None: fitted on ``data``.
        predict: how the model predicts a conversation side as users run it (TIMAR: streamed turn by
            turn; the baseline: turn windows); each evaluation then predicts ``val_clips`` val sides
            (:func:`conversation_validation`) and the best checkpoint is the one of the lowest
            :data:`SELECTION_METRIC`. None: the validation loss only.
        val_clips: conversation sides predicted at each evaluation (0: the validation loss only).
        others: as every recipe's ``train``.
    """
    recipe = make_windows(config, data)
    if normalizer is not None:
        from jaxtalk.data.conversation import Normalizer

        given = normalizer if isinstance(normalizer, Normalizer) else Normalizer.from_dict(normalizer)
        recipe = dataclasses.replace(recipe, normalizer=given)
    k_init, k_train, k_eval = jax.random.split(key, 3)
    if params is None:
        params = init_params(config, k_init)
    extra = {"normalizer": recipe.normalizer.to_dict(), "num_turns": recipe.num_turns, "still": list(recipe.still)}
    if normalizer is not None:
        extra["init"] = True  # the normaliser came with the starting parameters: a resume keeps it
    sample_eval = None if predict is None else conversation_validation(
        data, recipe, "val", predict=predict, key=jax.random.fold_in(k_eval, 1), clips=val_clips)
    return fit_recipe(recipe, data, make_loss_fn(config), params, optim, key=k_train, eval_key=k_eval, steps=steps,
                      sample_eval=sample_eval, best_metric=SELECTION_METRIC, batch_size=batch_size, seed=seed, ckpt_dir=ckpt_dir,
                      mesh=mesh, eval_every=eval_every, metadata={"model": model}, extra=extra, config=config, run_dir=run_dir,
                      run_info=run_info, **loop_kwargs)


def conversation_validation(
    data: PreparedData,
    windows: TimarWindows,
    split: str = "val",
    *,
    predict: Predict,
    key: PRNGKeyArray,
    clips: int = VAL_CLIPS,
) -> Callable[[Any, Any, int], dict[str, float]] | None:
    """An ``eval_fn`` for the training loop that predicts ``clips`` conversation sides of ``split`` as
    ``jaxtalk eval`` does and scores them with the DualTalk benchmark's metrics.

    Each side is the agent's whole turns (with ``windows.num_turns - 1`` turns of context), and the
    frames after its last whole turn repeat the last prediction (TIMAR's protocol); a partner without
    tracked motion is the run's still pose. The same sides and keys at every evaluation. Scored with
    :func:`~jaxtalk.metrics.conversation_metrics` at the published scale, without SID (its k-means is
    slow and needs 40 frames per side).

    Args:
        data: the prepared dataset.
        windows: the run's turn windows (normaliser, turns per window, still pose).
        split: the split to score.
        predict: the model's prediction of one side (see :data:`Predict`).
        key: the sampling key (side ``n`` uses ``fold_in(key, n)``).
        clips: how many sides, evenly spread over the split's.

    Returns:
        ``eval_fn(params, ema_params, step) -> {"FD_g", "P-FD_g", "MSE_g", "rPCC_g" for g in exp, jaw,
        pose, and "FD": the mean of the three FDs}`` (the EMA parameters when the run keeps them), or
        None when ``clips`` is 0 or the split has no side of a whole turn.
    """
    from jaxtalk.metrics import conversation_metrics

    if clips < 1 or not data.split(split):
        return None
    norm = windows.normalizer
    context = max(windows.num_turns - 1, 0)
    sides = [side for i, j in agent_sides(data, split)
             if (side := side_streams(data, i, j, norm, windows.still, windows.config.frames_per_turn)) is not None]
    if not sides:
        return None
    sides = [sides[int(k)] for k in spread(len(sides), clips)]

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = host_copy(ema_params if ema_params is not None else params)
        preds = [fit_length(norm.unmotion(np.asarray(predict(use, s.streams, jax.random.fold_in(key, n), context))[0]),
                            s.truth.shape[0]) for n, s in enumerate(sides)]
        scores = conversation_metrics(preds, [s.truth for s in sides], [s.partner for s in sides], scaled=True,
                                      sid_convention=None)
        scores[SELECTION_METRIC] = float(np.mean([scores[f"FD_{g}"] for g in ("exp", "jaw", "pose")]))
        return scores

    return eval_fn
