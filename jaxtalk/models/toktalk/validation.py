"""Validation that samples TokTalk as its users do: streamed, on fixed held-out clips, scored in vertices.

The flow-matching loss on validation windows does not track what users measure: it can keep falling
while the streamed lip error of held-out clips rises (docs/design-decisions.md).
:func:`streamed_validation` gives the training loop what ``jaxtalk eval`` reports, for the run to select
its best checkpoint by: each evaluation streams a fixed, evenly spread set of clips of the split chunk
by chunk (:func:`~jaxtalk.models.toktalk.streaming.stream`) at each of the run's sampler step counts,
with the same keys every time, and scores them on the built-in face (:func:`~jaxtalk.face.builtin_face`)
like ``jaxtalk eval``: LVE (mm^2, lips), MVE (mm) and jitter (mm/frame^2), frame-weighted over the clips.

:func:`real_voice_validation` adds what SynthTalk cannot show: how the mouth follows real speech. Each
evaluation streams the first :data:`REAL_VOICE_RECORDINGS` recordings of a ``--real-voice`` folder
(:func:`jaxtalk.data.recordings.read_recordings`, read once before training) as ``jaxtalk stream`` does
with its defaults, at :data:`REAL_VOICE_STEPS` sampler step: the run's tokenizer, the run's default
style clip (the training clip saved as ``style.npy``, :func:`jaxtalk.runs.default_style_clip`: real
recordings have no speaker in the data, and it is the style a user streams in), the seed 0. The
predicted jaw is measured as ``jaxtalk eval --real-voice`` measures it
(:func:`~jaxtalk.data.recordings.recording_sync`, averaged by :func:`~jaxtalk.data.recordings.mean_row`).
A run may select its best checkpoint by ``real_corr`` instead of the streamed lip error
(:data:`SELECTABLE`, :func:`selection_mode`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jaxtyping import Float

from jaxtalk.data.recordings import Recording, mean_row, recording_sync, sync_row
from jaxtalk.face import builtin_face
from jaxtalk.layout import JAW_OPEN_INDEX
from jaxtalk.metrics import jitter, lve, mve
from jaxtalk.metrics.speech_sync import style_rest_jaw
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.live import frames_for_audio
from jaxtalk.models.toktalk.model import encode_style, frames_for_tokens
from jaxtalk.models.toktalk.sampling import default_grid
from jaxtalk.models.toktalk.streaming import stream
from jaxtalk.train.loop import EvalFn
from jaxtalk.train.recipes import VAL_CLIPS, host_copy, spread
from jaxtalk.types import PRNGKeyArray

__all__ = ["streamed_validation", "real_voice_validation", "selection_mode", "plan_voice_validation",
           "SELECTION_METRIC", "SELECTABLE",
           "REAL_VOICE_METRICS", "REAL_VOICE_TRACKED", "REAL_VOICE_RECORDINGS", "REAL_VOICE_STEPS"]

# The metric a TokTalk run selects its best checkpoint by unless told otherwise: the streamed lip
# error, averaged over the run's sampler step counts.
SELECTION_METRIC = "LVE_mm2"
# The metrics a run may select its best checkpoint by, and which way is better.
SELECTABLE = {"LVE_mm2": "min", "real_corr": "max"}
# The real-voice metrics: the mean over the tracked recordings of the predicted jaw's correlation with
# the tracked jaw, of the loudness follower's (a constant of the folder, for reference) and of the best
# lag; and over every recording, the predicted jaw's mean in silence less the style clip's rest jaw.
REAL_VOICE_TRACKED = ("real_corr", "real_loudness_corr", "real_best_lag")
REAL_VOICE_METRICS = (*REAL_VOICE_TRACKED, "real_silence_minus_rest")
# Recordings streamed at each evaluation (the folder's first, in name order): each costs a stream of
# its whole length at every evaluation.
REAL_VOICE_RECORDINGS = 8
# Sampler steps of the real-voice streams: the fastest live setting, and the one whose lip error the
# streamed validation tracks too.
REAL_VOICE_STEPS = 1
# The seed of the real-voice streams: `jaxtalk stream`'s default, so that a logged value is what
# `jaxtalk stream RUN RECORDING --sample-steps 1` gives with that checkpoint's parameters.
_STREAM_SEED = 0


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


def selection_mode(select: str, recordings: Sequence[Recording] | None) -> str:
    """Check the metric a run is asked to select its best checkpoint by; return its mode.

    Args:
        select: a key of :data:`SELECTABLE`.
        recordings: the real voices streamed at each evaluation (None: none).

    Returns:
        ``"min"`` or ``"max"`` (which way is better).

    Raises:
        ValueError: an unknown metric, or a real-voice metric without real voices with tracked motion.
    """
    if select not in SELECTABLE:
        raise ValueError(f"--select {select}: not a metric a TokTalk run selects by; choose one of "
                         f"{', '.join(SELECTABLE)}")
    if select in REAL_VOICE_TRACKED:
        if recordings is None:
            raise ValueError(f"--select {select} measures the streamed jaw on real recordings: add --real-voice "
                             "FOLDER (recordings with their tracked motion as STEM.npz)")
        if not any(r.tracked_jaw is not None for r in recordings[:REAL_VOICE_RECORDINGS]):
            where = f" of {recordings[0].path.parent}" if recordings else ""
            raise ValueError(f"--select {select} compares the predicted jaw with tracked motion, and none of the "
                             f"recordings{where} streamed at each evaluation has any: put each one's tracked motion "
                             f"beside it as STEM.npz, or select {SELECTION_METRIC}")
    return SELECTABLE[select]


def plan_voice_validation(folder: Any, recordings: Sequence[Recording] | None, select: str | None,
                          echo: Callable[[str], None]) -> None:
    """``jaxtalk train --real-voice FOLDER --select METRIC`` before anything is opened (TokTalk's
    :attr:`jaxtalk.runs.ModelSpec.voice_validation`): ``select`` checked against the recordings
    (:func:`selection_mode`), and what each evaluation will stream said.

    Args:
        folder: the ``--real-voice`` folder (None: not given).
        recordings: its recordings, read (None: no ``--real-voice``).
        select: the ``--select`` metric (None: not given).
        echo: where the line goes.

    Raises:
        ValueError: see :func:`selection_mode`.
    """
    if select is not None:
        selection_mode(select, recordings)
    if recordings is not None:
        chosen = recordings[:REAL_VOICE_RECORDINGS]
        tracked = sum(r.tracked_jaw is not None for r in chosen)
        first = f"the first {len(chosen)} of {len(recordings)}" if len(recordings) > len(chosen) else f"{len(chosen)}"
        echo(f"real voices: each evaluation streams {first} recordings of {folder} ({tracked} with tracked "
             f"motion) at {REAL_VOICE_STEPS} sampler step in the run's default style")


def real_voice_validation(
    config: TokTalkConfig,
    recordings: Sequence[Recording],
    tokenizer: Any,
    style: Float[np.ndarray, "frames 56"],
) -> EvalFn:
    """An ``eval_fn`` for the training loop that streams real recordings and measures the predicted jaw.

    The first :data:`REAL_VOICE_RECORDINGS` recordings are tokenized once with ``tokenizer`` and, at every
    evaluation, streamed chunk by chunk (:func:`~jaxtalk.models.toktalk.streaming.stream`, what ``jaxtalk
    stream`` computes through the live path) at :data:`REAL_VOICE_STEPS` sampler step with the key of
    seed 0, each cut to its audio's frames (:func:`~jaxtalk.models.toktalk.live.frames_for_audio`).

    Args:
        config: the model config (a causal one: only those stream).
        recordings: the recordings (:func:`jaxtalk.data.recordings.read_recordings`).
        tokenizer: the VQ tokenizer the run's data was prepared with (the one the run saves).
        style: ``(S, 56)`` reference motion, its first ``4 * style_frames`` frames encoded at each
            evaluation (the run's default style clip, :func:`jaxtalk.runs.default_style_clip`).

    Returns:
        ``eval_fn(params, ema_params, step) -> {"real_silence_minus_rest"}`` plus, when a recording has
        tracked motion, ``"real_corr", "real_loudness_corr", "real_best_lag"`` (see
        :data:`REAL_VOICE_METRICS`; NaN where no recording gives a value), scored on the EMA parameters
        when the run keeps them.

    Raises:
        ValueError: a non-causal config, no recordings, a style clip shorter than ``style_min_frames``.
    """
    if not config.causal:
        raise ValueError("--real-voice streams the recordings chunk by chunk; this TokTalk config is the offline "
                         "(non-causal) one, which does not stream: train a causal one (--set causal=true)")
    if not recordings:
        raise ValueError("real_voice_validation needs at least one recording")
    style = np.asarray(style, np.float32)[: 4 * config.style_frames]
    if style.ndim != 2 or style.shape[0] < config.style_min_frames:
        raise ValueError(f"the style clip has shape {style.shape}: it needs at least {config.style_min_frames} frames")
    rest = style_rest_jaw(style[:, JAW_OPEN_INDEX])
    chosen = list(recordings[:REAL_VOICE_RECORDINGS])
    items = []
    for rec in chosen:
        tokens = np.asarray(tokenizer.encode(rec.audio).embeddings, np.float32)
        items.append((rec, tokens[None], frames_for_audio(config, tokens.shape[0], rec.audio.shape[0])))
    tracked = any(rec.tracked_jaw is not None for rec in chosen)
    grid = default_grid(config, REAL_VOICE_STEPS)
    key = jax.random.key(_STREAM_SEED)

    def value(v: float | None) -> float:
        return float("nan") if v is None else float(v)

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = host_copy(ema_params if ema_params is not None else params)
        style_vec = encode_style(use, config, style[None])
        rows = []
        for rec, tokens, frames in items:
            motion = np.asarray(stream(use, config, tokens, style_vec, key, ts=grid), np.float32)[0, :frames]
            rows.append(sync_row(rec.name, "no" if rec.tracked_jaw is None else "yes", recording_sync(rec, motion)))
        mean = mean_row(rows)
        out = {"real_silence_minus_rest": value(mean["jaw_silence"]) - rest}
        if tracked:
            out.update(real_corr=value(mean["corr"]), real_loudness_corr=value(mean["loudness_corr"]),
                       real_best_lag=value(mean["best_lag"]))
        return out

    return eval_fn
