"""Two-stage TokTalk training on SynthTalk with the shared training loop.

Stage 1 trains the decoder and style encoder on the base token stream ("A", 12.5 Hz x 64) with
:func:`~jaxtalk.models.toktalk.loss.cfm_loss`. Stage 2 adds an adapter for another stream ("B",
25 Hz x 48) and trains only it with :func:`~jaxtalk.models.toktalk.loss.adapter_loss`; the shared
loop's ``trainable`` predicate keeps every base parameter bitwise unchanged.

Examples are fixed-length windows cut from the clips (so every batch has one shape and the train step
compiles once); each window's reference style clip is a crop of ANOTHER clip of the same speaker
when there is one (the paper crops the target clip itself, which lets the style vector copy the
target; a different clip measures real style transfer).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from jaxtalk.data.batching import BatchIterator
from jaxtalk.data.standardize import fit_standardizer
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.loss import adapter_loss, cfm_loss
from jaxtalk.models.toktalk.model import fit_flow_scale, init_adapter, init_params
from jaxtalk.train import OptimConfig, TrainResult, train
from jaxtalk.types import PRNGKeyArray

__all__ = ["make_windows", "train_base", "train_adapter", "adapter_trainable", "base_trainable"]

PyTree = Any


def _fit_length(x: np.ndarray, n: int) -> np.ndarray:
    """Crop or edge-pad ``x`` along axis 0 to exactly ``n`` rows."""
    if x.shape[0] >= n:
        return x[:n]
    return np.concatenate([x, np.repeat(x[-1:], n - x.shape[0], axis=0)], axis=0)


def make_windows(
    corpus: Any,
    clips: Sequence[int],
    config: TokTalkConfig,
    *,
    window_frames: int,
    hop_frames: int | None = None,
    src_stream: str | None = None,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Fixed-length training windows from SynthTalk clips.

    Args:
        corpus: a ``SynthTalkCorpus``.
        clips: clip indices to cut.
        config: model settings (token rate/width, style clip length).
        window_frames: frames per window (spanning a whole number of base tokens).
        hop_frames: distance between window starts (default ``window_frames // 2``); a last window
            aligned to the clip's end is always added.
        src_stream: also cut this token stream (e.g. "B") as ``src_tokens`` for stage 2.
        seed: seed of the style-clip crops.

    Returns:
        Dict of stacked arrays: ``motion (N, T, D)``, ``tokens (N, Tt, speech_dim)``, ``style (N, S, D)``,
        ``mask (N, T)`` bool, ``clip (N,)`` and ``start (N,)``, plus ``src_tokens`` when asked.

    Raises:
        ValueError: empty ``clips``, a window that is not a whole number of tokens, or a stream whose
            width differs from ``config.speech_dim``.
    """
    if len(clips) == 0:
        raise ValueError("make_windows needs at least one clip")
    per_token = config.fps / config.token_rate
    if window_frames % per_token or window_frames < config.chunk_frames:
        raise ValueError(
            f"window_frames={window_frames} must span whole tokens ({per_token:g} frames each) and "
            f"at least one chunk ({config.chunk_frames})"
        )
    hop = hop_frames or max(window_frames // 2, 1)
    hop = int(np.ceil(hop / per_token) * per_token)
    tt = int(window_frames / per_token)
    rng = np.random.default_rng(seed)
    by_speaker: dict[int, list[int]] = {}
    for i in clips:
        by_speaker.setdefault(corpus.clips[i].speaker, []).append(i)
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("motion", "tokens", "style", "mask", "clip", "start")}
    if src_stream is not None:
        out["src_tokens"] = []
    s = config.style_frames
    for i in clips:
        motion = np.asarray(corpus.motion(i), np.float32)
        tokens = np.asarray(corpus.tokens(i, "A").embeddings, np.float32)
        if tokens.shape[1] != config.speech_dim:
            raise ValueError(f"stream A has width {tokens.shape[1]}, config.speech_dim={config.speech_dim}")
        src = None
        if src_stream is not None:
            stream = corpus.tokens(i, src_stream)
            src, src_per_frame = np.asarray(stream.embeddings, np.float32), stream.rate / config.fps
        n = motion.shape[0]
        # The last window ends at the clip's end; rounding its start UP to a token boundary may leave
        # one padded frame instead of dropping the clip's last frame.
        last = int(np.ceil(max(n - window_frames, 0) / per_token) * per_token)
        starts = sorted(set(range(0, last + 1, hop)) | {last})
        others = [j for j in by_speaker[corpus.clips[i].speaker] if j != i] or [i]
        for st in starts:
            length = min(window_frames, n - st)
            mask = np.arange(window_frames) < length
            seg = np.zeros((window_frames, motion.shape[1]), np.float32)
            seg[:length] = motion[st : st + length]
            t0 = int(round(st / per_token))
            out["motion"].append(seg)
            out["mask"].append(mask)
            out["tokens"].append(_fit_length(tokens[t0:], tt))
            if src is not None:
                s0 = int(round(st * src_per_frame))
                out["src_tokens"].append(_fit_length(src[s0:], int(round(window_frames * src_per_frame))))
            ref = np.asarray(corpus.motion(others[int(rng.integers(len(others)))]), np.float32)
            r0 = int(rng.integers(max(ref.shape[0] - s, 0) + 1))
            out["style"].append(_fit_length(ref[r0:], s))
            out["clip"].append(np.asarray(i))
            out["start"].append(np.asarray(st))
    return {k: np.stack(v) for k, v in out.items()}


def _model_batches(windows: dict[str, np.ndarray], batch_size: int, seed: int) -> BatchIterator:
    keys = ("motion", "tokens", "style", "mask") + (("src_tokens",) if "src_tokens" in windows else ())
    return BatchIterator({k: windows[k] for k in keys}, batch_size, seed=seed)


def train_base(
    config: TokTalkConfig,
    windows: dict[str, np.ndarray],
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    batch_size: int = 16,
    params: PyTree | None = None,
    seed: int = 0,
    **train_kwargs: Any,
) -> TrainResult:
    """Stage 1: train decoder + style encoder with the CFM loss.

    Args:
        config: model settings.
        windows: from :func:`make_windows`.
        optim: optimiser settings (``total_steps`` is the training length unless ``max_steps``).
        key: PRNG key (initialisation and the per-step keys).
        batch_size: windows per batch.
        params: initial parameters (default: fresh from ``key``, with the motion standardiser and the
            flow scale fitted on ``windows``).
        seed: data order seed.
        **train_kwargs: passed to :func:`jaxtalk.train.train` (``ckpt_dir``, ``eval_fn``, ``progress``...).

    Returns:
        The loop's :class:`~jaxtalk.train.TrainResult` (``state.params`` are the trained parameters).
    """
    k_init, k_train = jax.random.split(key)
    if params is None:
        params = init_params(config, k_init)
        # Standardise with the training motion's statistics (the flow adds unit-variance noise per
        # channel; raw jaw/neck spreads are ~100x smaller than expression ones).
        params["norm"] = fit_standardizer(windows["motion"], windows["mask"])
        params["norm"]["flow_scale"] = fit_flow_scale(params, config, windows["motion"], windows["mask"],
                                                      windows["style"])
    loss = functools.partial(cfm_loss, config=config)
    return train(loss, params, _model_batches(windows, batch_size, seed), optim, key=k_train,
                 trainable=base_trainable, metadata={"model": "toktalk", "stage": 1}, **train_kwargs)


def base_trainable(path: str, leaf: Any) -> bool:
    """The stage-1 ``trainable`` predicate: everything but the fitted standardiser ``norm/``."""
    return path.split("/", 1)[0] != "norm"


def adapter_trainable(path: str, leaf: Any) -> bool:
    """The stage-2 ``trainable`` predicate: only parameters under ``adapter/`` train."""
    return path.split("/", 1)[0] == "adapter"


def train_adapter(
    config: TokTalkConfig,
    base_params: PyTree,
    windows: dict[str, np.ndarray],
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    src_rate: float | int,
    flow_weight: float = 1.0,
    batch_size: int = 16,
    seed: int = 0,
    **train_kwargs: Any,
) -> TrainResult:
    """Stage 2: train a fresh adapter with the base model frozen.

    Args:
        config: model settings.
        base_params: stage-1 parameters (``decoder``, ``style``); left bitwise unchanged.
        windows: from :func:`make_windows` with ``src_stream`` set.
        optim: optimiser settings.
        key: PRNG key.
        src_rate: the source stream's token rate (Hz).
        flow_weight: lambda of the flow term.
        batch_size: windows per batch.
        seed: data order seed.
        **train_kwargs: passed to :func:`jaxtalk.train.train`.

    Returns:
        :class:`~jaxtalk.train.TrainResult`; ``state.params`` has the base parameters and the adapter.

    Raises:
        ValueError: windows without ``src_tokens``.
    """
    if "src_tokens" not in windows:
        raise ValueError("stage 2 needs windows made with src_stream (no 'src_tokens' array)")
    k_init, k_train = jax.random.split(key)
    params = {k: v for k, v in base_params.items() if k != "adapter"}
    params["adapter"] = init_adapter(config, k_init, int(windows["src_tokens"].shape[-1]))
    loss = functools.partial(adapter_loss, config=config, src_rate=float(src_rate), flow_weight=float(flow_weight))
    return train(loss, params, _model_batches(windows, batch_size, seed), optim, key=k_train,
                 trainable=adapter_trainable, metadata={"model": "toktalk", "stage": 2}, **train_kwargs)
