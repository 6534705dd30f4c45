"""Validation that samples TokTalk as its users do: streamed, on fixed held-out clips, scored in vertices.

The flow-matching loss on validation windows did not track what users measure: on SynthTalk ``small``
the validation loss fell at every evaluation of a 3,000-step run while the streamed lip error of the
held-out clips rose above the mean pose's. :func:`streamed_validation` gives the training loop what
``jaxtalk eval`` reports, for the run to select its best checkpoint by: each evaluation streams a fixed,
evenly spread set of clips of the split chunk by chunk (:func:`~jaxtalk.models.toktalk.stream.stream`)
at each of the run's sampler step counts, with the same keys every time, and scores them on the built-in
face (:func:`~jaxtalk.face.builtin_face`) like ``jaxtalk eval``: LVE (mm^2, lips), MVE (mm) and jitter
(mm/frame^2), frame-weighted over the clips.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from jaxtalk.face import builtin_face
from jaxtalk.metrics import jitter, lve, mve
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.model import encode_style, frames_for_tokens
from jaxtalk.models.toktalk.sample import default_grid
from jaxtalk.models.toktalk.stream import stream
from jaxtalk.train.loop import EvalFn
from jaxtalk.train.recipes import VAL_CLIPS, host_copy, spread
from jaxtalk.types import PRNGKeyArray

__all__ = ["streamed_validation", "SELECTION_METRIC"]

# The metric a TokTalk run selects its best checkpoint by: the streamed lip error, averaged over the
# run's sampler step counts.
SELECTION_METRIC = "LVE_mm2"


def streamed_validation(
    config: TokTalkConfig,
    data: Any,
    split: str = "val",
    *,
    key: PRNGKeyArray,
    clips: int = VAL_CLIPS,
    step_counts: Sequence[int] | None = None,
) -> EvalFn | None:
    """An ``eval_fn`` for the training loop that streams ``clips`` clips of ``split`` and scores them.

    Each clip's style is a reference clip of the same speaker (another clip of the split when there is
    one, else the clip itself), its first ``4 * style_frames`` frames, as ``jaxtalk eval`` takes it.

    Args:
        config: the model config (only causal models stream; an offline model gets None).
        data: the prepared dataset (:class:`~jaxtalk.data.loader.PreparedData`).
        split: the split to score.
        key: the sampling key (clip ``n`` streams with ``fold_in(key, n)`` at every evaluation).
        clips: how many clips, evenly spread over the split's clips with tokens.
        step_counts: sampler step counts (default: 1 and ``config.sample_steps``).

    Returns:
        ``eval_fn(params, ema_params, step) -> {"LVE_mm2_<n>step", "MVE_mm_<n>step",
        "jitter_mm_<n>step" for each n, and "LVE_mm2": their LVE averaged over the step counts}``
        (the EMA parameters when the run keeps them), or None when the split has no clip with tokens,
        ``clips`` is 0 or the model is the offline one.
    """
    if not config.causal or clips < 1 or not data.split(split):
        return None
    candidates = [i for i in data.split(split) if data.clips[i]["tokens"]]
    if not candidates:
        return None
    steps = tuple(dict.fromkeys(step_counts or (1, config.sample_steps)))
    by_speaker: dict[str, list[int]] = {}
    for i in data.split(split):
        by_speaker.setdefault(data.clips[i]["speaker"], []).append(i)
    face = builtin_face(0)
    lips = face.regions["lips"]
    style_frames = 4 * config.style_frames
    items = []
    for j in spread(len(candidates), clips):
        i = candidates[int(j)]
        rec = data.record(i, ("motion", "tokens"))
        tokens = np.asarray(rec["tokens"], np.float32)[None]
        t = min(frames_for_tokens(tokens.shape[1], config.token_rate, config.fps), rec["motion"].shape[0])
        others = [o for o in by_speaker[data.clips[i]["speaker"]] if o != i]
        style = np.asarray(data.record(others[0], ("motion",))["motion"] if others else rec["motion"], np.float32)
        style = style[:style_frames]
        if t < 2 or style.shape[0] < config.style_min_frames:
            continue
        gt = np.asarray(rec["motion"], np.float32)[:t]
        items.append((tokens, style[None], np.asarray(face.vertices_seq(gt)), t))
    if not items:
        return None
    grids = {n: default_grid(config, n) for n in steps}

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = host_copy(ema_params if ema_params is not None else params)
        sums = {f"{m}_{n}step": 0.0 for n in steps for m in ("LVE_mm2", "MVE_mm", "jitter_mm")}
        frames = 0
        for k, (tokens, style, gt_vertices, t) in enumerate(items):
            style_vec = encode_style(use, config, style)
            for n in steps:
                out = stream(use, config, tokens, style_vec, jax.random.fold_in(key, k), ts=grids[n])
                vertices = np.asarray(face.vertices_seq(np.asarray(out, np.float32)[0][:t]))
                sums[f"LVE_mm2_{n}step"] += t * float(lve(vertices, gt_vertices, lips)) * 1e6
                sums[f"MVE_mm_{n}step"] += t * float(mve(vertices, gt_vertices)) * 1e3
                sums[f"jitter_mm_{n}step"] += t * float(jitter(vertices)) * 1e3
            frames += t
        out = {name: value / frames for name, value in sums.items()}
        out[SELECTION_METRIC] = float(np.mean([out[f"LVE_mm2_{n}step"] for n in steps]))
        return out

    return eval_fn
