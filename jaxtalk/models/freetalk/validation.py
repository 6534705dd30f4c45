"""Validation that samples ATS as its users do: DDIM from noise on fixed held-out windows, scored in landmarks.

The denoising loss on validation windows says how well the model predicts the noise at random
timesteps; a user samples the whole DDIM chain and measures the landmarks. :func:`sampled_validation`
gives the training loop what ``jaxtalk eval`` reports for an ATS run, for the run to select its best
checkpoint by: each evaluation samples one window of each of a fixed, evenly spread set of clips of the
split (the run's own windows: 50-frame windows, or whole clips for a whole-clip run), with the
same starting noise every time, at the config's DDIM step count, and scores them with
:func:`~jaxtalk.metrics.landmarks.landmark_metrics`: LVE over the mouth landmarks (mm^2), the mean
landmark error LE (mm) and jitter (mm/frame^2), frame-weighted over the windows.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from jaxtalk.metrics.landmarks import landmark_metrics
from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.train.recipes import host_copy, spread
from jaxtalk.types import PRNGKeyArray

__all__ = ["sampled_validation", "SELECTION_METRIC", "VAL_CLIPS"]

# The metric an ATS run selects its best checkpoint by: the sampled lip error over the mouth landmarks.
SELECTION_METRIC = "LVE_mm2"
# Held-out clips (one window each) sampled at each evaluation.
VAL_CLIPS = 8

EvalFn = Callable[[Any, Any, int], dict[str, float]]


def sampled_validation(
    config: ATSConfig,
    data: Any,
    windows: Any,
    split: str = "val",
    *,
    key: PRNGKeyArray,
    clips: int = VAL_CLIPS,
) -> EvalFn | None:
    """An ``eval_fn`` for the training loop that samples ``clips`` windows of ``split`` and scores them.

    Args:
        config: the ATS config.
        data: the prepared dataset (:class:`~jaxtalk.data.loader.PreparedData`).
        windows: the run's window recipe (:class:`~jaxtalk.models.freetalk.recipe.ATSWindows`): the
            windows, their standardisation and the emotion vocabulary.
        split: the split to score.
        key: the sampling key (the same starting noise at every evaluation).
        clips: how many clips, evenly spread over the split's clips with a window; each gives its
            first window.

    Returns:
        ``eval_fn(params, ema_params, step) -> {"LVE_mm2", "LE_mm", "jitter_mm"}`` (the EMA
        parameters when the run keeps them), or None when ``clips`` is 0 or the split has no window.
    """
    if clips < 1 or not data.split(split):
        return None
    table = windows.table(data, split)
    if not len(table):
        return None
    _, first = np.unique(table[:, 0], return_index=True)  # each clip's first window
    rows = table[np.sort(first)]
    examples = [windows.example(data, rows[int(j)]) for j in spread(len(rows), clips)]
    batch = {name: np.stack([e[name] for e in examples]) for name in examples[0]}
    frames = [int(e["mask"].sum()) if "mask" in e else e["displacements"].shape[0] for e in examples]
    cond = ats.make_condition(config, batch["audio"], batch["emotion"], batch["intensity"],
                              mask=batch.get("mask"), audio_mask=batch.get("audio_mask"))
    stats = windows.stats
    truth = [np.asarray(stats.denormalize(d[:n]), np.float32) for d, n in zip(batch["displacements"], frames)]

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = host_copy(ema_params if ema_params is not None else params)
        sampled = np.asarray(stats.denormalize(np.asarray(ats.sample(use, config, cond, key))), np.float32)
        sums = {"LVE_mm2": 0.0, "LE_mm": 0.0, "jitter_mm": 0.0}
        for pred, gt, n in zip(sampled, truth, frames):
            for name, value in landmark_metrics(pred[:n], gt).items():
                sums[name] += n * value
        return {name: value / sum(frames) for name, value in sums.items()}

    return eval_fn
