"""Per-clip model inputs computed once by ``jaxtalk prepare``: the audio feature streams every model
reads, landmark displacements, and token embeddings.

Audio features come in two alignments, both at the 25-fps motion rate:

* ``speech (T, D)``: computed over the whole clip (FreeTalk's ATS and offline uses). With log-mel
  this is four 10 ms frames of 80 bands stacked per 40 ms motion frame (``D = 320``).
* ``turn_speech (turns * 25, D)``: each 1-s turn computed from that turn's audio ALONE (TIMAR's
  per-chunk tokenisation), so no future audio reaches a past turn. With log-mel ``D = 80``.

With a pretrained encoder (``hubert:PATH`` / ``wav2vec2:PATH``, a local Hugging Face folder) the
whole-clip stream is the encoder's 50 Hz features resampled to 25 fps. The per-turn stream is
computed turn by turn: with wav2vec 2.0 in TIMAR's order (each turn's CNN features interpolated to
its 25 frames with ``align_corners=True``, then the projection and the transformer at 25 Hz, as the
public TIMAR code's ``SpeechEncoder``); with HuBERT resampled after the transformer. Each turn's
waveform is normalised on its own when the checkpoint asks for it (``do_normalize``), as a stream
must. The public TIMAR code's data loader normalises the whole recording instead, a step that reads
the future audio: ``wav2vec2+recording:PATH`` (or ``hubert+recording:PATH``) prepares the per-turn
stream that way, for offline evaluation as the published numbers were measured; the whole-clip
stream is the same either way.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

__all__ = ["AudioFeatures", "parse_audio_features", "same_encoder", "normalize_recording", "SAMPLES_PER_FRAME", "TURN_FRAMES",
           "WAVEFORM_NORMS"]

SAMPLES_PER_FRAME = AUDIO_SAMPLE_RATE // MOTION_FPS  # 640
TURN_FRAMES = MOTION_FPS  # one 1-s turn
# Turns are featurised in blocks of this many (the last one padded with silent turns and cropped):
# one compiled program serves clips of every length, and each turn is still computed on its own.
TURN_BLOCK = 16
# Where a pretrained encoder's waveform normalisation (``do_normalize``) is taken over, for the
# per-turn stream: each turn on its own (streamable), or the whole recording (the public TIMAR loader).
WAVEFORM_NORMS = ("turn", "recording")
# Hugging Face's Wav2Vec2FeatureExtractor adds this to the variance (``zero_mean_unit_var_norm``).
NORMALIZE_EPS = 1e-7


def normalize_recording(audio: np.ndarray) -> np.ndarray:
    """A whole recording at zero mean and unit variance, as Hugging Face's feature extractor with
    ``do_normalize`` gives it to the encoder (``(x - mean) / sqrt(var + 1e-7)``, in float32)."""
    x = np.asarray(audio, np.float32)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"expected a non-empty mono waveform, got shape {x.shape}")
    return ((x - x.mean()) / np.sqrt(x.var() + NORMALIZE_EPS)).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class AudioFeatures:
    """An audio front end: ``kind`` is ``logmel``, ``hubert`` or ``wav2vec2`` (``path`` for the latter
    two); ``waveform_norm`` (one of :data:`WAVEFORM_NORMS`) says over what a pretrained encoder's
    waveform normalisation runs in the per-turn stream."""

    kind: str = "logmel"
    path: str | None = None
    waveform_norm: str = "turn"

    def __post_init__(self) -> None:
        if self.waveform_norm not in WAVEFORM_NORMS:
            raise ValueError(f"waveform_norm must be one of {WAVEFORM_NORMS}, got {self.waveform_norm!r}")
        if self.waveform_norm != "turn" and self.path is None:
            raise ValueError("log-mel features have no waveform normalisation to take over the recording")

    @property
    def spec(self) -> str:
        """The command-line spelling (``logmel``, ``hubert:PATH`` or ``wav2vec2+recording:PATH``)."""
        if self.path is None:
            return self.kind
        return f"{self.kind}{'+recording' if self.waveform_norm == 'recording' else ''}:{self.path}"

    @property
    def encoder(self) -> tuple[str, str | None]:
        """What the features are made with, whatever the waveform normalisation: a run trained on one
        spec evaluates on data prepared with another of the same encoder."""
        return self.kind, self.path

    def fingerprint(self) -> str | None:
        """What identifies the encoder's weights on disk (:func:`jaxtalk.audio.encoders.checkpoint_fingerprint`:
        their files' sizes and modification times), so that prepared features of other weights in the
        same folder are not taken for these; None for log-mel.

        Raises:
            FileNotFoundError: the checkpoint's files are gone.
        """
        if self.path is None:
            return None
        from jaxtalk.audio.encoders.loader import checkpoint_fingerprint

        return checkpoint_fingerprint(self.path)

    @functools.cached_property
    def _encoder(self) -> Any:
        from jaxtalk.audio.encoders import SpeechEncoder

        return SpeechEncoder.from_pretrained(self.path)

    def speech(self, audio: np.ndarray, num_frames: int) -> np.ndarray:
        """Whole-clip features ``(num_frames, D)`` float32 of ``audio`` (16 kHz, any length)."""
        if self.kind == "logmel":
            from jaxtalk.audio.speech import audio_features

            return audio_features(audio, num_frames)
        feats = np.asarray(self._encoder.features_at(_fit(audio, num_frames * SAMPLES_PER_FRAME), MOTION_FPS))
        return _fit(feats, num_frames).astype(np.float32)

    def turn_speech(self, audio: np.ndarray, num_turns: int) -> np.ndarray:
        """Per-turn features ``(num_turns * 25, D)``: each 1-s turn from its own audio only."""
        if self.kind == "logmel":
            from jaxtalk.audio.speech import turn_speech_features

            spt = TURN_FRAMES * SAMPLES_PER_FRAME
            blocks = -(-num_turns // TURN_BLOCK)
            padded = np.zeros(blocks * TURN_BLOCK * spt, np.float32)
            padded[: num_turns * spt] = audio[: num_turns * spt]
            feats = [turn_speech_features(padded[b * TURN_BLOCK * spt:(b + 1) * TURN_BLOCK * spt], TURN_BLOCK)
                     for b in range(blocks)]
            return np.concatenate(feats)[: num_turns * TURN_FRAMES]
        spt = TURN_FRAMES * SAMPLES_PER_FRAME
        encoder = self._encoder
        if self.waveform_norm == "recording" and encoder.normalize:
            # The whole recording normalised once, then each turn encoded as it is.
            audio = normalize_recording(audio)
            encoder = dataclasses.replace(encoder, normalize=False)
        if self.kind == "wav2vec2":
            # TIMAR's order (the public code's SpeechEncoder): per 1-s turn, the CNN features linearly
            # interpolated (align_corners=True) to the turn's 25 frames, THEN the feature projection
            # and the transformer, which therefore runs at 25 Hz.
            turns = [np.asarray(encoder.interpolated_features(_fit(audio[k * spt:(k + 1) * spt], spt),
                                                              num_frames=TURN_FRAMES))
                     for k in range(num_turns)]
        else:
            turns = [_fit(np.asarray(encoder.features_at(audio[k * spt:(k + 1) * spt], MOTION_FPS)), TURN_FRAMES)
                     for k in range(num_turns)]
        return np.concatenate(turns).astype(np.float32)


def _fit(x: np.ndarray, n: int) -> np.ndarray:
    """Crop, or zero-pad (audio) / edge-pad (features), ``x`` to ``n`` rows."""
    x = np.asarray(x)
    if x.shape[0] >= n:
        return x[:n]
    if x.ndim == 1:
        return np.pad(x, (0, n - x.shape[0]))
    return np.concatenate([x, np.repeat(x[-1:], n - x.shape[0], axis=0)])


def same_encoder(spec: str | None, other: str | None) -> bool:
    """Whether two feature specs name the same front end, whatever their waveform normalisation
    (``wav2vec2:PATH`` and ``wav2vec2+recording:PATH`` do): a run trained on per-turn features
    evaluates on data prepared the public loader's way. Reads nothing from disk."""
    def encoder(text: str | None) -> tuple[str, str] | None:
        if text is None:
            return None
        kind, _, path = text.partition(":")
        return kind.partition("+")[0], path

    return encoder(spec) == encoder(other)


def parse_audio_features(spec: str) -> AudioFeatures:
    """``logmel`` | ``hubert:PATH`` | ``wav2vec2:PATH`` -> :class:`AudioFeatures` (``PATH`` made absolute,
    so that its :attr:`~AudioFeatures.spec` names the same folder from anywhere); ``+recording`` after
    the kind (``wav2vec2+recording:PATH``) normalises each recording's waveform as a whole for the
    per-turn stream (offline only; see the module docstring).

    An encoder's folder is checked here, before any audio is read: it holds ``config.json`` of a
    model of that kind and the weights (``model.safetensors``, or what
    :func:`jaxtalk.audio.encoders.weight_files` accepts).

    Raises:
        ValueError: an unknown kind, an encoder without a folder, or a ``config.json`` that is not a
            checkpoint of that kind.
        FileNotFoundError: the encoder folder, its ``config.json`` or its weights do not exist.
    """
    kind, _, path = spec.partition(":")
    if kind == "logmel" and not path:
        return AudioFeatures()
    kind, plus, norm = kind.partition("+")
    if plus and norm not in WAVEFORM_NORMS:
        raise ValueError(f"unknown waveform normalisation {norm!r} in {spec!r}; expected {kind}+recording:PATH")
    norm = norm or "turn"
    if kind == "logmel" and plus:
        raise ValueError(f"{spec!r}: log-mel features have no waveform normalisation; use logmel")
    if kind not in ("hubert", "wav2vec2"):
        raise ValueError(f"unknown audio features {spec!r}; expected logmel, hubert:PATH or wav2vec2:PATH")
    if not path:
        raise ValueError(f"{kind} features need a local checkpoint folder: {kind}:PATH")
    folder = Path(path)
    wanted = "a Hugging Face folder with config.json and model.safetensors"
    if not folder.is_dir():
        raise FileNotFoundError(f"{kind} checkpoint folder not found: {path!r} ({wanted})")
    config = folder / "config.json"
    if not config.is_file():
        raise FileNotFoundError(f"{kind} checkpoint folder {path!r} has no config.json; expected {wanted}")
    try:
        model_type = json.loads(config.read_text()).get("model_type")
    except (ValueError, UnicodeDecodeError, AttributeError) as err:
        raise ValueError(f"{str(config)!r} is not a Hugging Face config ({err})") from None
    if model_type != kind:
        other = f"; use {model_type}:{path}" if model_type in ("hubert", "wav2vec2") else ""
        raise ValueError(f"{kind}:{path} names a checkpoint of model_type {model_type!r} ({config}), not {kind}{other}")
    from jaxtalk.audio.encoders.loader import weight_files

    weight_files(folder)  # no weights: the loader's message lists what the folder holds
    return AudioFeatures(kind, str(folder.absolute()), norm)
