"""Live speech -> motion: the streaming engine fed by audio (or tokens) as it arrives.

:class:`LiveModel` holds what every stream of one run shares: parameters, config, the run's tokenizer,
the style vector, the time grid and the guidance weight. :meth:`LiveModel.open` starts one stream
(:class:`LiveStream`) with its own carried :class:`~jaxtalk.models.toktalk.streaming.StreamState`:
:meth:`LiveStream.push` takes audio of any length and returns the frames it completes, a chunk of
``chunk_frames`` as soon as the audio its tokens read has arrived (the chunk's end plus the tokenizer's
look-ahead, :attr:`LiveModel.lookahead_samples`); :meth:`LiveStream.finish` ends the utterance.

What a stream returns is exactly ``stream(params, config, tokenizer.encode(audio).embeddings, style,
key)`` over all the audio pushed (the tokenizer stream gives ``encode``'s tokens, see
:class:`~jaxtalk.audio.tokenizer.TokenizerStream`; the last chunk is completed by repeating the last token
and cropped to the audio's length). ``jaxtalk stream`` and ``jaxtalk serve`` both animate through it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.checks import check_temperature
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.model import encode_style, frames_for_tokens
from jaxtalk.models.toktalk.streaming import init_stream, stream_step, tokens_per_chunk
from jaxtalk.samplers import cosine_grid
from jaxtalk.types import AUDIO_SAMPLE_RATE, Float, PRNGKeyArray

__all__ = ["LiveModel", "LiveStream", "frames_for_audio", "live_model"]

PyTree = Any


def frames_for_audio(config: TokTalkConfig, num_tokens: int, samples: int | None) -> int:
    """Frames an utterance gives: its tokens' span, but no longer than its audio (the tokenizer rounds the
    token count up: 5.0 s of audio at 12.5 Hz tokens covers 126 frames, the audio 125)."""
    frames = frames_for_tokens(num_tokens, config.token_rate, config.fps)
    if samples is not None:
        frames = min(frames, round(samples / AUDIO_SAMPLE_RATE * config.fps))
    return frames


@dataclasses.dataclass(frozen=True, eq=False)
class LiveModel:
    """A TokTalk model ready to animate live speech (shared by every stream; see the module docstring).

    Attributes:
        params: the model parameters.
        config: the (causal) model config.
        tokenizer: the run's :class:`~jaxtalk.audio.VQTokenizer` (None: the run takes token files only,
            and streams take tokens, :meth:`LiveStream.push_tokens`).
        style: ``(1, style_vector_dim)`` style vector.
        cfg_scale: guidance weight (None: the config's).
        ts: the time grid (None: the config's cosine grid).
        temperature: scale of the starting noise (None: the config's).
    """

    params: PyTree
    config: TokTalkConfig
    tokenizer: Any
    style: Any
    cfg_scale: float | None = None
    ts: Any = None
    temperature: float | None = None

    @classmethod
    def from_run(cls, run: Any, *, style: np.ndarray | None = None, cfg_scale: float | None = None,
                 sample_steps: int | None = None, temperature: float | None = None) -> LiveModel:
        """The live model of a loaded TokTalk run (:func:`jaxtalk.runs.load_run`).

        Args:
            run: the loaded run.
            style: ``(S, 56)`` reference motion (default: the training clip saved with the run); its first
                ``4 * style_frames`` frames are encoded once.
            cfg_scale: guidance weight (default: the config's).
            sample_steps: Euler steps on the cosine grid (default: the config's).
            temperature: scale of the starting noise (default: the config's).

        Raises:
            ValueError: a style clip shorter than ``style_min_frames`` or NaN; bad ``sample_steps``
                or ``temperature``.
        """
        config = run.config
        if sample_steps is not None and sample_steps < 1:
            raise ValueError(f"sample_steps must be >= 1, got {sample_steps}")
        clip = np.asarray(run.default_style() if style is None else style, np.float32)
        if clip.ndim != 2 or clip.shape[0] < config.style_min_frames:
            raise ValueError(f"the style clip has shape {clip.shape}: it needs (frames, {config.param_dim}) with at "
                             f"least {config.style_min_frames} frames")
        vector = encode_style(run.params, config, clip[None, : 4 * config.style_frames])
        ts = None if sample_steps is None else jnp.asarray(cosine_grid(sample_steps), jnp.float32)
        if temperature is not None:
            check_temperature(temperature)
        return cls(run.params, config, run.tokenizer(), vector, cfg_scale, ts, temperature)

    @property
    def fps(self) -> int:
        """Motion frames per second."""
        return self.config.fps

    @property
    def sample_rate(self) -> int:
        """Audio samples per second a stream takes."""
        return AUDIO_SAMPLE_RATE if self.tokenizer is None else int(self.tokenizer.sample_rate)

    @property
    def chunk_frames(self) -> int:
        """Frames generated per model step."""
        return self.config.chunk_frames

    @property
    def chunk_samples(self) -> int:
        """Audio samples one chunk spans."""
        return round(self.chunk_frames * self.sample_rate / self.fps)

    @property
    def lookahead_samples(self) -> int:
        """Samples past a chunk's end that its last token reads (0 without a tokenizer)."""
        return 0 if self.tokenizer is None else round(self.tokenizer.lookahead_s * self.sample_rate)

    def describe(self) -> dict[str, Any]:
        """The stream's timing, as ``jaxtalk serve`` announces it."""
        return {"model": "toktalk", "fps": self.fps, "sample_rate": self.sample_rate, "chunk_frames": self.chunk_frames,
                "chunk_samples": self.chunk_samples, "lookahead_samples": self.lookahead_samples,
                "sample_steps": int(self.config.sample_steps if self.ts is None else len(self.ts) - 1)}

    def open(self, key: PRNGKeyArray) -> LiveStream:
        """A new stream whose starting noise comes from ``key`` (:func:`~jaxtalk.models.toktalk.stream_noise`)."""
        return LiveStream(self, key)


def live_model(run: Any, **options: Any) -> LiveModel:
    """:meth:`LiveModel.from_run` (the run registry's ``live`` entry for TokTalk)."""
    return LiveModel.from_run(run, **options)


class LiveStream:
    """One live stream (see the module docstring): feed audio with :meth:`push` (or tokens with
    :meth:`push_tokens`), end the utterance with :meth:`finish`; the stream then starts a new one from
    the same key.

    Attributes:
        model: the :class:`LiveModel`.
        frames: frames returned so far in this utterance.
    """

    def __init__(self, model: LiveModel, key: PRNGKeyArray):
        self.model = model
        self._key = key
        self._chunk_tokens = tokens_per_chunk(model.config)
        self._tokens = None if model.tokenizer is None else model.tokenizer.stream(self._chunk_tokens)
        self._reset()

    def _reset(self) -> None:
        self._state = init_stream(self.model.config, self._key)
        self._pending = np.zeros((0, self.model.config.speech_dim), np.float32)
        self._token_count = 0
        self.frames = 0

    @property
    def samples(self) -> int:
        """Audio samples pushed in this utterance."""
        return 0 if self._tokens is None else self._tokens.samples

    @property
    def samples_needed(self) -> int:
        """More samples before :meth:`push` returns the next chunk."""
        self._require_tokenizer()
        return self._tokens.samples_needed

    def _require_tokenizer(self) -> None:
        if self._tokens is None:
            raise ValueError("this run was trained on the data's own token files and has no tokenizer for audio: "
                             "push token embeddings (push_tokens)")

    def push(self, audio: Float[np.ndarray, "..."]) -> Float[np.ndarray, "frames param"]:
        """Add mono audio at :attr:`LiveModel.sample_rate`; returns the ``(n * chunk_frames, 56)`` frames it
        completes (possibly none).

        Raises:
            ValueError: a run without a tokenizer; audio that is not 1-D or has NaN/inf (nothing added).
        """
        self._require_tokenizer()
        _, tokens = self._tokens.push(audio)
        return self._generate(tokens)

    def push_tokens(self, tokens: Float[np.ndarray, "..."]) -> Float[np.ndarray, "frames param"]:
        """Add ``(n, speech_dim)`` token embeddings at the model's token rate; returns the frames of every
        chunk they complete.

        Raises:
            ValueError: tokens of the wrong width, NaN/inf.
        """
        tokens = np.asarray(tokens, np.float32)
        width = self.model.config.speech_dim
        if tokens.ndim != 2 or tokens.shape[1] != width:
            raise ValueError(f"token embeddings must have shape (tokens, {width}), got {tokens.shape}")
        if not np.all(np.isfinite(tokens)):
            raise ValueError("token embeddings contain NaN or inf")
        return self._generate(tokens)

    def finish(self) -> Float[np.ndarray, "frames param"]:
        """The utterance's last frames: its remaining tokens (the last chunk completed by repeating the
        last token), cropped to :func:`frames_for_audio`. The stream then starts a new utterance."""
        samples = None
        if self._tokens is not None and self._tokens.samples:
            samples = self._tokens.samples
            _, tokens = self._tokens.finish()
            self._pending = np.concatenate([self._pending, tokens])
            self._token_count += tokens.shape[0]
        out = np.zeros((0, self.model.config.param_dim), np.float32)
        if self._pending.shape[0]:
            pad = -self._pending.shape[0] % self._chunk_tokens
            tokens = np.concatenate([self._pending, np.repeat(self._pending[-1:], pad, axis=0)])
            out = self._steps(tokens)
        limit = frames_for_audio(self.model.config, self._token_count, samples)
        out = out[: max(limit - self.frames, 0)]
        self._reset()
        return out

    def _generate(self, tokens: np.ndarray) -> np.ndarray:
        self._token_count += tokens.shape[0]
        tokens = np.concatenate([self._pending, tokens])
        whole = tokens.shape[0] - tokens.shape[0] % self._chunk_tokens
        self._pending = tokens[whole:]
        out = self._steps(tokens[:whole])
        self.frames += out.shape[0]
        return out

    def _steps(self, tokens: np.ndarray) -> np.ndarray:
        m, ct = self.model, self._chunk_tokens
        outs = [np.zeros((0, m.config.param_dim), np.float32)]
        for i in range(0, tokens.shape[0], ct):  # one host call per chunk, as chunks arrive live
            self._state, out = stream_step(m.params, m.config, self._state, tokens[None, i:i + ct], m.style,
                                           cfg_scale=m.cfg_scale, ts=m.ts, temperature=m.temperature)
            outs.append(np.asarray(jax.block_until_ready(out), np.float32)[0])
        return np.concatenate(outs)
