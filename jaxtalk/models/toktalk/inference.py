"""TokTalk animating speech for ``jaxtalk sample`` and ``jaxtalk stream`` (the spec's
:class:`~jaxtalk.runs.SpeechAnimator`).

The speech is audio, turned into tokens by the tokenizer the run's data was prepared with, or token
embeddings ``(tokens, speech_dim)`` at the model's token rate from a ``.npy`` (e.g. your own audio-LLM
tokens); the style is ``--style`` or the training clip saved with the run. Offline, the whole sequence
is sampled in one call, or in minute-long windows for longer inputs (:func:`~jaxtalk.models.toktalk.sample_long`);
streamed, it goes through the live path :class:`~jaxtalk.models.toktalk.live.LiveModel` chunk by chunk.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.audio.io import AUDIO_SUFFIXES
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.runs import SpeechConditions

__all__ = ["TOKEN_INPUT", "read_speech", "sample_speech", "stream_speech", "step_frames", "rest_note"]

# The input a TokTalk run takes besides audio: its suffix, and what such a file holds.
TOKEN_INPUT = (".npy", "a .npy of token embeddings")


def _tokenizer(run: Any) -> Any:
    """The run's tokenizer, which audio needs (a run trained on the data's own token files has none)."""
    tokenizer = run.tokenizer()
    if tokenizer is None:
        config = run.config
        raise ValueError(f"{run.run_dir} was trained on the data's own token files and has no tokenizer for "
                         f"audio: pass a .npy of token embeddings ({config.speech_dim} wide at {config.token_rate:g} Hz)")
    return tokenizer


def _style(run: Any, conditions: SpeechConditions) -> np.ndarray:
    """The reference motion ``(S, 56)``: the conditions', else the training clip saved with the run."""
    style = np.asarray(run.default_style() if conditions.style is None else conditions.style, np.float32)
    if style.shape[0] < run.config.style_min_frames:
        raise ValueError(f"style clip {conditions.style_file} has {style.shape[0]} frames, fewer than "
                         f"{run.config.style_min_frames}")
    return style


def read_speech(run: Any, path: str | Path) -> np.ndarray:
    """An input file as TokTalk takes it: an audio file's 16-kHz waveform (a run without a tokenizer is
    refused before the audio is read), or a ``.npy``'s ``(tokens, speech_dim)`` token embeddings.

    Raises:
        ValueError: audio for a run without a tokenizer; token embeddings of another width, none, or NaN.
    """
    from jaxtalk.audio import load_audio
    from jaxtalk.files import load_npy

    path = Path(path)
    if path.suffix.lower() in AUDIO_SUFFIXES:
        _tokenizer(run)
        return load_audio(path)
    config = run.config
    tokens = load_npy(path, what="token file")
    if tokens.ndim != 2 or tokens.shape[1] != config.speech_dim or tokens.shape[0] < 1:
        raise ValueError(f"{str(path)!r}: token embeddings must have shape (tokens, {config.speech_dim}) "
                         f"at {config.token_rate:g} Hz, got {tokens.shape}")
    if not np.all(np.isfinite(tokens)):
        raise ValueError(f"{str(path)!r}: token embeddings contain NaN or inf")
    return tokens.astype(np.float32)


def sample_speech(run: Any, speech: np.ndarray, conditions: SpeechConditions) -> tuple[np.ndarray, np.ndarray | None]:
    """``(params (T, 56), the audio or None)``: ``speech`` (a waveform, or token embeddings) sampled offline,
    cut to the audio's frames."""
    import jax

    from jaxtalk.models.toktalk.live import frames_for_audio
    from jaxtalk.models.toktalk.sampling import sample_long

    config = run.config
    key = jax.random.key(conditions.seed)
    audio = speech if speech.ndim == 1 else None
    tokens = speech if audio is None else np.asarray(_tokenizer(run).encode(audio).embeddings, np.float32)
    style = _style(run, conditions)[None, : 4 * config.style_frames]
    frames = frames_for_audio(config, tokens.shape[0], None if audio is None else audio.shape[0])
    # Window by window past a minute: the decoder's attention is O(frames^2) in memory.
    motion = sample_long(run.params, config, tokens[None], style, key, cfg_scale=conditions.cfg_scale,
                         sample_steps=conditions.sample_steps, temperature=conditions.temperature)[:, :frames]
    return np.asarray(motion, np.float32)[0], audio


def stream_speech(run: Any, speech: np.ndarray, conditions: SpeechConditions, on_chunk: Callable[..., None],
                  echo: Callable[[str], None]) -> tuple[np.ndarray, np.ndarray | None, float]:
    """``(params (T, 56), the audio or None, seconds per chunk)``: ``speech`` streamed through the live path
    chunk by chunk. Audio goes in piece by piece, each piece what completes the next chunk (up to the
    chunk's end plus the tokenizer's look-ahead), as it would live; token embeddings a chunk's tokens at a
    time."""
    import jax

    from jaxtalk.models.toktalk.live import LiveModel
    from jaxtalk.models.toktalk.streaming import tokens_per_chunk

    config = run.config
    key = jax.random.key(conditions.seed)
    if speech.ndim == 1:
        _tokenizer(run)
    live = LiveModel.from_run(run, style=_style(run, conditions), cfg_scale=conditions.cfg_scale,
                              sample_steps=conditions.sample_steps, temperature=conditions.temperature)
    chunk_s, ct = live.chunk_frames / live.fps, tokens_per_chunk(config)
    stream = live.open(key)
    outs = []
    if speech.ndim == 2:  # token embeddings
        n = -(-speech.shape[0] // ct)
        for i in range(n):
            t0 = time.perf_counter()
            out = stream.push_tokens(speech[i * ct:(i + 1) * ct])
            outs.append(np.concatenate([out, stream.finish()]) if i == n - 1 else out)
            on_chunk(n, time.perf_counter() - t0, chunk_s)
        return np.asarray(np.concatenate(outs), np.float32), None, chunk_s
    audio = speech
    echo(f"note: each chunk also waits for {1e3 * live.lookahead_samples / live.sample_rate:.1f} ms of "
         "audio past its end (the tokenizer's centred STFT): a live chunk's latency is that plus the times "
         "below")
    n = -(-max(math.ceil(audio.shape[0] * config.token_rate / live.sample_rate), 1) // ct)
    pos = done = 0
    while pos + stream.samples_needed <= audio.shape[0]:  # each piece completes one chunk
        t0, need = time.perf_counter(), stream.samples_needed
        outs.append(stream.push(audio[pos:pos + need]))
        on_chunk(n, time.perf_counter() - t0, chunk_s)
        pos, done = pos + need, done + 1
    t0 = time.perf_counter()  # the rest of the audio, then the utterance's end: the last chunk(s)
    outs.append(np.concatenate([stream.push(audio[pos:]), stream.finish()]))
    on_chunk(n, time.perf_counter() - t0, chunk_s, max(n - done, 1))
    return np.asarray(np.concatenate(outs), np.float32), audio, chunk_s


def step_frames(config: TokTalkConfig) -> int:
    """Frames TokTalk animates at a time at the least: any number (its last chunk is cut to the audio)."""
    return 1


def rest_note(run: Any) -> str:
    """Where the run's jaw should rest in silence: it streams in its default style, and that clip's rest
    (:func:`~jaxtalk.metrics.speech_sync.style_rest_jaw`) is the target."""
    from jaxtalk.layout import JAW_OPEN_INDEX
    from jaxtalk.metrics.speech_sync import style_rest_jaw

    return f"the style clip rests at {style_rest_jaw(np.asarray(run.default_style())[:, JAW_OPEN_INDEX]):.3f} rad"
