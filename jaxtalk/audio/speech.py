"""Speech features on the motion timeline, the log-mel front ends that ``prepare`` and the models share.

* :func:`audio_features`: whole-clip features, four 10 ms log-mel frames stacked per 40 ms motion
  frame (80 x 4 = 320 per frame at 25 fps): FreeTalk's stand-in for resampled HuBERT features,
  already on the motion timeline as the paper's resampled HuBERT track is.
* :func:`turn_speech_features`: per-turn features following TIMAR's per-chunk tokenisation (Sec. 3.1:
  "each chunk is encoded independently ... so that no future information is exposed"): the audio of
  every 1-s turn becomes an 80-band log-mel spectrogram on its own, interpolated to the turn's 25
  motion frames.

They live below the models because ``jaxtalk.data.features`` computes them once in ``prepare`` and
the models compute the same features at inference.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.audio.framerate import resample_features
from jaxtalk.audio.melspec import log_mel
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS, Float, Shaped

__all__ = ["MEL_FRAMES_PER_FRAME", "AUDIO_FEATURE_DIM", "TURN_SPEECH_DIM", "audio_features", "turn_speech_features"]

_HOP = 160  # 10 ms at 16 kHz
_BUCKET_SAMPLES = 5 * AUDIO_SAMPLE_RATE
MEL_FRAMES_PER_FRAME = AUDIO_SAMPLE_RATE // _HOP // MOTION_FPS  # 4
AUDIO_FEATURE_DIM = 80 * MEL_FRAMES_PER_FRAME  # 320
TURN_SPEECH_DIM = 80
_MEL_RATE = 100


# Mel frames per log-mel call (60 s): a longer clip is computed in pieces, so memory stays bounded.
_CHUNK_MEL_FRAMES = 6000
_HALF_WINDOW = 200  # n_fft // 2 of log_mel's default 400-sample (25 ms) frames


def _log_mel_frames(x: np.ndarray) -> np.ndarray:
    """``(1 + samples // 160, n_mels)`` centred log-mel frames of ``x`` (zeros beyond its ends).

    Frame ``f`` reads samples ``[160 f - 200, 160 f + 200)`` only, so a long clip is cut into pieces
    of :data:`_CHUNK_MEL_FRAMES` frames, each computed uncentred from its own samples plus 200 on
    either side: the same frames as one call, in bounded memory.
    """
    frames = 1 + x.size // _HOP
    if frames <= _CHUNK_MEL_FRAMES:
        # Zero-pad to a whole bucket so clips of many lengths share one compiled log-mel program. The
        # STFT pads with zeros anyway (pad_mode "constant"), so frames of the real signal are unchanged.
        total = -(-x.size // _BUCKET_SAMPLES) * _BUCKET_SAMPLES
        return np.asarray(log_mel(np.pad(x, (0, total - x.size))))[:frames]
    piece = (_CHUNK_MEL_FRAMES - 1) * _HOP + 2 * _HALF_WINDOW  # samples of one piece: one compiled program
    padded = np.pad(x, (_HALF_WINDOW, _HALF_WINDOW + _CHUNK_MEL_FRAMES * _HOP))
    out = None
    for f0 in range(0, frames, _CHUNK_MEL_FRAMES):
        mel = np.asarray(log_mel(padded[f0 * _HOP:f0 * _HOP + piece], center=False))
        if out is None:
            out = np.empty((frames, mel.shape[1]), np.float32)
        n = min(_CHUNK_MEL_FRAMES, frames - f0)
        out[f0:f0 + n] = mel[:n]
    return out


def audio_features(audio: Float[np.ndarray, " samples"], num_frames: int) -> Float[np.ndarray, "frames 320"]:
    """Per-motion-frame audio features: four 10 ms log-mel frames stacked per 40 ms motion frame.

    Mel frame ``f`` is centred on sample ``160 f``, so motion frame ``t`` (samples ``[640 t,
    640 (t + 1))``) gets mel frames ``4t .. 4t + 3``; missing frames at the end repeat the last one.

    Args:
        audio: ``(samples,)`` mono 16 kHz signal.
        num_frames: T motion frames wanted.

    Returns:
        ``(T, 320)`` float32.

    Raises:
        ValueError: empty or non-finite audio, or ``num_frames < 1``.
    """
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    x = np.asarray(audio, np.float32)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"audio must be a non-empty 1-D signal, got shape {x.shape}")
    mel = _log_mel_frames(x)
    need = num_frames * MEL_FRAMES_PER_FRAME
    if mel.shape[0] < need:
        mel = np.concatenate([mel, np.repeat(mel[-1:], need - mel.shape[0], axis=0)])
    return mel[:need].reshape(num_frames, AUDIO_FEATURE_DIM).astype(np.float32)


@functools.partial(jax.jit, static_argnames=("frames_per_turn", "samples_per_turn"))
def _features(chunks: jax.Array, frames_per_turn: int, samples_per_turn: int) -> jax.Array:
    mel = log_mel(chunks, AUDIO_SAMPLE_RATE, n_mels=TURN_SPEECH_DIM)  # (turns, mel_frames, 80)
    fps = frames_per_turn * AUDIO_SAMPLE_RATE / samples_per_turn
    return jax.vmap(lambda m: resample_features(m, _MEL_RATE, fps, num_frames=frames_per_turn))(mel)


def turn_speech_features(
    # Loose annotation: the checks below raise a ValueError naming the problem (e.g. 2-D audio).
    audio: Shaped[np.ndarray, ...], num_turns: int, *, frames_per_turn: int = MOTION_FPS
) -> Float[np.ndarray, "frames 80"]:
    """Per-turn log-mel features at the motion rate, each turn computed from its own audio only.

    Args:
        audio: 16 kHz mono audio with at least ``num_turns`` seconds.
        num_turns: whole turns to featurise.
        frames_per_turn: motion frames per 1-s turn (25).

    Returns:
        ``(num_turns * frames_per_turn, 80)`` float32.

    Raises:
        ValueError: audio too short, not 1-D, NaN, or ``num_turns < 1``.
    """
    audio = np.asarray(audio, np.float32)
    if audio.ndim != 1:
        raise ValueError(f"audio must be 1-D (samples,), got shape {audio.shape}")
    if num_turns < 1:
        raise ValueError(f"num_turns must be >= 1, got {num_turns}")
    spt = AUDIO_SAMPLE_RATE * frames_per_turn // MOTION_FPS
    if audio.shape[0] < num_turns * spt:
        raise ValueError(f"audio has {audio.shape[0]} samples, fewer than {num_turns} turns x {spt}")
    if not np.all(np.isfinite(audio)):
        raise ValueError("audio contains NaN or inf")
    chunks = audio[: num_turns * spt].reshape(num_turns, spt)
    feats = _features(jnp.asarray(chunks), frames_per_turn, spt)
    return np.asarray(feats, np.float32).reshape(num_turns * frames_per_turn, TURN_SPEECH_DIM)
