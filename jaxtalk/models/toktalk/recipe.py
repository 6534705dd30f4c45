"""TokTalk's recipes: windows of a prepared dataset, and the one way each stage is trained.

A window is ``window_frames`` motion frames (a whole number of base tokens) with the aligned tokens,
its padding mask, and a reference style clip (``TokTalkConfig.style_source``): a crop of the target
clip itself (the paper's, and the ``paper`` preset's) or of ANOTHER clip of the same speaker in the
same split when there is one (the other presets': the style vector cannot copy the target, so training
measures real style transfer). The CLI, the demo, the experiments and the tests
train through these entry points:

* :func:`train` (stage 1): the decoder and style encoder on the dataset's base token stream with the
  CFM loss (:func:`~jaxtalk.models.toktalk.loss.loss`).
* :func:`train_adapter` (stage 2): a fresh adapter from another token stream (e.g. SynthTalk's "B",
  25 Hz x 48) onto the base stream, with every base parameter frozen (bitwise unchanged) and
  :func:`~jaxtalk.models.toktalk.loss.adapter_loss`. ``prepare`` stores one token stream per clip,
  so the source stream is given beside the dataset, per clip name (:class:`AdapterWindows`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxtalk.data.batching import fit_length, window_starts
from jaxtalk.data.loader import PreparedData
from jaxtalk.data.recordings import Recording
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.runs import RunSettings, fit_run
from jaxtalk.train import OptimConfig
from jaxtalk.train.recipes import VAL_CLIPS, RecipeResult, TrainSettings, merged_eval, spread
from jaxtalk.types import PRNGKeyArray

__all__ = ["DEFAULTS", "TokTalkWindows", "AdapterWindows", "default_window", "check_data", "base_trainable",
           "adapter_trainable", "train", "train_adapter"]

# The small model's training settings on 2 CPU cores (the demo's): a short EMA suits runs of ~1k steps.
DEFAULTS = TrainSettings(lr=2e-3, ema_decay=0.99, warmup_steps=100)

PyTree = Any


def default_window(config: TokTalkConfig) -> int:
    """Training window in frames: 100 (4 s) for chunks up to 20 frames, else five chunks."""
    return 100 if config.chunk_frames <= 20 else 5 * config.chunk_frames


def check_data(config: TokTalkConfig, data: PreparedData) -> None:
    """Raise ValueError unless ``data`` carries tokens of the config's width and rate."""
    m = data.manifest
    if not m.get("token_dim"):
        raise ValueError(f"{data.root} has no token stream: prepare it with --tokens vq (or clip token files)")
    if m["token_dim"] != config.speech_dim or float(m["token_rate"]) != float(config.token_rate):
        raise ValueError(
            f"{data.root} has tokens of width {m['token_dim']} at {m['token_rate']:g} Hz but the model expects "
            f"{config.speech_dim} at {config.token_rate:g} Hz (--set speech_dim=... token_rate=...)"
        )


def base_trainable(path: str, leaf: Any) -> bool:
    """Stage 1's ``trainable`` predicate: everything but the fitted standardiser ``norm/``."""
    return path.split("/", 1)[0] != "norm"


def adapter_trainable(path: str, leaf: Any) -> bool:
    """Stage 2's ``trainable`` predicate: only parameters under ``adapter/`` train."""
    return path.split("/", 1)[0] == "adapter"


@dataclasses.dataclass(frozen=True)
class TokTalkWindows:
    """TokTalk's window recipe (see the module docstring).

    Attributes:
        config: the model config (token rate, style clip length).
        window_frames: frames per window (a whole number of tokens, at least one chunk).
        hop_frames: distance between window starts (default half a window); the last window of a
            clip is flush with its end.
        seed: seed of the style-clip choices.
    """

    config: TokTalkConfig
    window_frames: int
    hop_frames: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        per_token = self.config.fps / self.config.token_rate
        if self.window_frames % per_token or self.window_frames < self.config.chunk_frames:
            raise ValueError(
                f"window_frames={self.window_frames} must span whole tokens ({per_token:g} frames each) "
                f"and at least one chunk ({self.config.chunk_frames})"
            )

    @property
    def per_token(self) -> int:
        return int(self.config.fps / self.config.token_rate)

    def table(self, data: PreparedData, split: str) -> np.ndarray:
        """Rows ``(clip, start, style_clip, style_start)``."""
        clips = [i for i in data.split(split) if data.clips[i]["tokens"]]
        rng = np.random.default_rng(self.seed)
        by_speaker: dict[str, list[int]] = {}
        for i in clips:
            by_speaker.setdefault(data.clips[i]["speaker"], []).append(i)
        rows = []
        s = self.config.style_frames
        for i in clips:
            if self.config.style_source == "target":
                others = [i]
            else:
                others = [j for j in by_speaker[data.clips[i]["speaker"]] if j != i] or [i]
            for st in window_starts(data.clips[i]["frames"], self.window_frames, self.hop_frames or self.window_frames // 2,
                                    align=self.per_token):
                ref = others[int(rng.integers(len(others)))]
                r0 = int(rng.integers(max(data.clips[ref]["frames"] - s, 0) + 1))
                rows.append((i, st, ref, r0))
        return np.asarray(rows, np.int64).reshape(-1, 4)

    def example(self, data: PreparedData, row: np.ndarray) -> dict[str, np.ndarray]:
        i, st, ref, r0 = (int(v) for v in row)
        w = self.window_frames
        rec = data.record(i, ("motion", "tokens"), frames=(st, st + w))
        motion, tokens = rec["motion"], rec["tokens"]
        length = motion.shape[0]
        seg = np.zeros((w, motion.shape[1]), np.float32)
        seg[:length] = motion
        style = data.record(ref, ("motion",), frames=(r0, r0 + self.config.style_frames))["motion"]
        # A reference clip shorter than style_frames is zero-padded and masked: edge-padding would
        # repeat its last pose and weight the anchor pose (the clip's mean) towards it.
        style_clip = np.zeros((self.config.style_frames, motion.shape[1]), np.float32)
        style_clip[:len(style)] = style
        return {
            "motion": seg,
            "tokens": fit_length(tokens[st // self.per_token:], w // self.per_token),
            "style": style_clip,
            "style_mask": np.arange(self.config.style_frames) < len(style),
            "mask": np.arange(w) < length,
        }


def train(
    config: TokTalkConfig,
    data: PreparedData,
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    run: RunSettings = RunSettings(),
    params: PyTree | None = None,
    val_clips: int = VAL_CLIPS,
    real_voice: str | Path | Sequence[Recording] | None = None,
    select: str | None = None,
) -> RecipeResult:
    """Train the base model (decoder + style encoder) on ``data``'s training split with the CFM loss.

    Args:
        config: model settings (token width and rate must match the data's).
        data: a prepared dataset with a token stream.
        optim: optimiser settings (``total_steps`` is the length unless ``run.steps``).
        key: PRNG key (initialisation, per-step keys).
        run: the run's settings (:class:`~jaxtalk.runs.RunSettings`: steps, batch, seed, where the run
            goes, the loop's settings); ``run.seed`` also chooses the style clips, ``run.window_frames``
            defaults to :func:`default_window`. Each evaluation (every ``run.eval_every`` steps and at
            the end) computes the loss on up to :data:`~jaxtalk.train.recipes.VAL_WINDOWS` windows of
            the ``val`` split and streams ``val_clips`` of its clips at 1 and ``config.sample_steps``
            steps (:func:`~jaxtalk.models.toktalk.validation.streamed_validation`: LVE, MVE, jitter); the
            best checkpoint is the one of the lowest streamed LVE (the validation loss when nothing
            streams), or of the metric ``select`` names.
        params: initial parameters (default: fresh, with the motion standardiser fitted on the
            training split and the flow scale on its first windows).
        val_clips: clips streamed at each evaluation (0: the validation loss only).
        real_voice: a folder of real recordings (with their tracked motion as ``STEM.npz``), or the
            recordings already read (:func:`jaxtalk.data.recordings.read_recordings`): each evaluation
            also streams the first :data:`~jaxtalk.models.toktalk.validation.REAL_VOICE_RECORDINGS` of
            them as ``jaxtalk stream`` does, at 1 sampler step in the run's default style clip, with the
            tokenizer the data was prepared with, and records ``real_corr``, ``real_loudness_corr``,
            ``real_best_lag`` (with tracked motion) and ``real_silence_minus_rest``
            (:func:`~jaxtalk.models.toktalk.validation.real_voice_validation`). None: no real voices.
        select: the metric the best checkpoint is chosen by: ``LVE_mm2`` (the lowest) or ``real_corr``
            (the highest; needs ``real_voice`` with tracked motion). None: a resumed run's own, else
            ``LVE_mm2``.

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult` (``extra``: the window size).

    Raises:
        ValueError: data without the config's tokens; with ``real_voice``: a bad folder (see
            ``read_recordings``), data prepared without a tokenizer for audio, an offline config; an
            unknown ``select`` or one whose recordings are missing (a resumed run selected by
            ``real_corr`` needs ``real_voice`` again).
    """
    from jaxtalk.models.toktalk.loss import make_loss_fn
    from jaxtalk.models.toktalk.model import fit_flow_scale, init_params

    check_data(config, data)
    real_eval, best_metric, best_mode = _real_voice_selection(config, data, real_voice, select, run.ckpt_path)
    window = run.window_frames or default_window(config)
    recipe = TokTalkWindows(config, window, hop_frames=window // 4, seed=run.seed)
    k_init, k_train, k_eval = jax.random.split(key, 3)
    if params is None:
        params = init_params(config, k_init)
        params["norm"] = {k: np.asarray(v) for k, v in data.motion_stats().items()}
        table = recipe.table(data, "train")
        first = [recipe.example(data, table[j]) for j in spread(len(table), 256)]
        stacked = {k: np.stack([e[k] for e in first]) for k in ("motion", "mask", "style", "style_mask")}
        params["norm"]["flow_scale"] = fit_flow_scale(params, config, stacked["motion"], stacked["mask"], stacked["style"],
                                                      style_mask=stacked["style_mask"])
    from jaxtalk.models.toktalk.validation import SELECTION_METRIC, streamed_validation

    # The best checkpoint is the one users would pick: by default the lowest streamed lip error on val
    # clips (the validation loss when no val clip streams).
    sample_eval = streamed_validation(config, data, "val", key=jax.random.fold_in(k_eval, 1), clips=val_clips)
    if best_metric == SELECTION_METRIC and sample_eval is None:
        best_metric = None
    return fit_run(recipe, data, make_loss_fn(config), params, optim, config=config, key=k_train, eval_key=k_eval,
                   run=run, metadata={"model": "toktalk", "stage": 1}, extra={"window_frames": recipe.window_frames},
                   sample_eval=merged_eval(sample_eval, real_eval), best_metric=best_metric, best_mode=best_mode,
                   trainable=base_trainable)


def _real_voice_selection(config: TokTalkConfig, data: PreparedData,
                          real_voice: str | Path | Sequence[Recording] | None, select: str | None,
                          ckpt_dir: Path | None) -> tuple[Any, str, str]:
    """``(real-voice eval_fn or None, best metric, its mode)`` of :func:`train`, every setting checked
    before anything is trained."""
    from jaxtalk.data.recordings import read_recordings
    from jaxtalk.models.toktalk.validation import (REAL_VOICE_TRACKED, SELECTION_METRIC, real_voice_validation,
                                                   selection_mode)
    from jaxtalk.runs import default_style_clip
    from jaxtalk.train.checkpoint import read_best

    recordings = read_recordings(real_voice) if isinstance(real_voice, (str, Path)) else real_voice
    saved = read_best(ckpt_dir) if ckpt_dir is not None else None
    if saved is not None and saved["metric"] in REAL_VOICE_TRACKED and recordings is None:
        # A resumed run keeps its selection (train.recipes.evaluation), which needs the recordings again.
        raise ValueError(f"this run selects its best checkpoint by {saved['metric']} on real recordings "
                         f"({ckpt_dir}/best): resume it with --real-voice FOLDER")
    if select is None:
        select = saved["metric"] if saved is not None and saved["metric"] in REAL_VOICE_TRACKED else SELECTION_METRIC
    mode = selection_mode(select, recordings)
    if recordings is None:
        return None, select, mode
    tokenizer = data.tokenizer()
    if tokenizer is None:
        raise ValueError(f"--real-voice: {data.root} was prepared from its own token files and has no tokenizer "
                         "to turn the recordings into tokens; prepare the data with --tokens vq")
    return real_voice_validation(config, recordings, tokenizer, default_style_clip(data, config)), select, mode


@dataclasses.dataclass(frozen=True, eq=False)
class AdapterWindows(TokTalkWindows):
    """Stage 2's window recipe: :class:`TokTalkWindows` plus the source stream's tokens of the window.

    Attributes:
        src_tokens: per clip name, the source stream's token embeddings ``(Ts, src_dim)`` at
            ``src_rate`` (clips without an entry give no window).
        src_rate: the source stream's token rate (Hz).
    """

    src_tokens: Mapping[str, np.ndarray] = dataclasses.field(kw_only=True)
    src_rate: float = dataclasses.field(kw_only=True)

    def table(self, data: PreparedData, split: str) -> np.ndarray:
        rows = super().table(data, split)
        return rows[[data.clips[int(i)]["name"] in self.src_tokens for i in rows[:, 0]]].reshape(-1, 4)

    def example(self, data: PreparedData, row: np.ndarray) -> dict[str, np.ndarray]:
        out = super().example(data, row)
        src = np.asarray(self.src_tokens[data.clips[int(row[0])]["name"]], np.float32)
        per_frame = self.src_rate / self.config.fps
        out["src_tokens"] = fit_length(src[int(round(int(row[1]) * per_frame)):],
                                        int(round(self.window_frames * per_frame)))
        return out


def train_adapter(
    config: TokTalkConfig,
    data: PreparedData,
    optim: OptimConfig,
    *,
    base_params: PyTree,
    src_tokens: Mapping[str, np.ndarray],
    src_rate: float,
    flow_weight: float = 1.0,
    key: PRNGKeyArray,
    run: RunSettings = RunSettings(),
) -> RecipeResult:
    """Stage 2: train a fresh adapter from another token stream with the base model frozen.

    Arguments as :func:`train` (no validation sampling: the best checkpoint is the one of the lowest
    validation loss), plus:

    Args:
        base_params: stage-1 parameters (``decoder``, ``style``, ``norm``); left bitwise unchanged
            (an ``adapter`` entry in them is replaced by a fresh one).
        src_tokens: per clip name of ``data``, the source stream's token embeddings ``(Ts, src_dim)``
            (e.g. SynthTalk's stream "B": ``{clip_name(i): corpus.tokens(i, "B").embeddings}``).
        src_rate: the source stream's token rate (Hz).
        flow_weight: lambda of the flow term of :func:`~jaxtalk.models.toktalk.loss.adapter_loss`.

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``state.params`` hold the base parameters and the
        adapter; ``extra``: the window size, the source rate and width.

    Raises:
        ValueError: no source tokens for any clip of ``data``, or source tokens of unequal widths.
    """
    from jaxtalk.models.toktalk.model import init_adapter

    check_data(config, data)
    widths = {int(np.shape(v)[-1]) for v in src_tokens.values()}
    if not any(c["name"] in src_tokens for c in data.clips) or len(widths) != 1:
        raise ValueError(f"src_tokens must give tokens of one width for clips of {data.root} "
                         f"(widths {sorted(widths)}, {sum(c['name'] in src_tokens for c in data.clips)} clips named)")
    window = run.window_frames or default_window(config)
    recipe = AdapterWindows(config, window, hop_frames=window // 4, seed=run.seed, src_tokens=src_tokens,
                            src_rate=float(src_rate))
    k_init, k_train, k_eval = jax.random.split(key, 3)
    src_dim = widths.pop()
    params = {k: v for k, v in base_params.items() if k != "adapter"}
    params["adapter"] = init_adapter(config, k_init, src_dim)
    loss = functools.partial(_adapter_loss, config, float(src_rate), float(flow_weight))
    extra = {"window_frames": recipe.window_frames, "adapter": {"src_rate": float(src_rate), "src_dim": src_dim}}
    return fit_run(recipe, data, loss, params, optim, config=config, key=k_train, eval_key=k_eval, run=run,
                   metadata={"model": "toktalk", "stage": 2}, extra=extra, trainable=adapter_trainable)


def _adapter_loss(config: TokTalkConfig, src_rate: float, flow_weight: float, params: PyTree, batch: dict,
                  key: PRNGKeyArray) -> tuple[Any, dict[str, Any]]:
    from jaxtalk.models.toktalk.loss import adapter_loss

    return adapter_loss(params, config, batch, key, src_rate=src_rate, flow_weight=flow_weight)
