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

from jaxtalk.data.conversation import make_windows
from jaxtalk.data.loader import PreparedData
from jaxtalk.runs import RunInfo
from jaxtalk.train.optim import OptimConfig
from jaxtalk.train.recipes import RecipeResult, TrainSettings, fit_recipe
from jaxtalk.types import PRNGKeyArray

__all__ = ["TURN_DEFAULTS", "TURN_PRESET_DEFAULTS", "train_on_turn_windows"]

PyTree = Any

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
    return fit_recipe(recipe, data, make_loss_fn(config), params, optim, key=k_train, eval_key=k_eval, steps=steps,
                      batch_size=batch_size, seed=seed, ckpt_dir=ckpt_dir, mesh=mesh, eval_every=eval_every,
                      metadata={"model": model}, extra=extra, config=config, run_dir=run_dir, run_info=run_info, **loop_kwargs)
