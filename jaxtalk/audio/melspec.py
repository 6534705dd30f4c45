"""Log-mel spectrogram front end in JAX (jit-able, batched over arbitrary leading axes).

Conventions (those of librosa's defaults and Whisper's front end, so features are familiar):

* Frames are centred: frame ``f`` is centred on sample ``f * hop_length``; the signal is padded by
  ``n_fft // 2`` on both sides (zeros by default), giving ``1 + samples // hop_length`` frames
  (100 frames/s at 16 kHz with ``hop_length=160``).
* Window: periodic Hann of ``win_length`` samples, zero-padded (centred) to ``n_fft``.
* Power spectrum ``|rfft|^2``, then a Slaney-style mel filterbank: the Slaney/Auditory-Toolbox mel
  scale (linear below 1 kHz, logarithmic above) with triangles normalised to unit area
  (``2 / (f_right - f_left)``), i.e. ``librosa.filters.mel(htk=False, norm="slaney")``.
* Natural log with a floor: ``log(max(mel, log_floor))``, ``log_floor = 1e-10`` by default, so digital
  silence maps to ``log(1e-10) ~= -23.03`` instead of ``-inf``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float

from jaxtalk.types import AUDIO_SAMPLE_RATE, Array

__all__ = ["log_mel", "mel_filterbank", "hz_to_mel", "mel_to_hz", "num_frames"]

_F_SP = 200.0 / 3.0  # Hz per mel in the linear part of the Slaney scale
_MIN_LOG_HZ = 1000.0
_MIN_LOG_MEL = _MIN_LOG_HZ / _F_SP  # 15 mel at 1 kHz
_LOG_STEP = np.log(6.4) / 27.0  # 27 mel per factor 6.4 in frequency above 1 kHz


def hz_to_mel(freq: np.ndarray | float | int | list | tuple) -> np.ndarray:
    """Slaney mel scale: ``f / (200/3)`` below 1 kHz, ``15 + 27 log(f/1000) / log(6.4)`` above."""
    freq = np.asarray(freq, dtype=np.float64)
    linear = freq / _F_SP
    log_part = _MIN_LOG_MEL + np.log(np.maximum(freq, _MIN_LOG_HZ) / _MIN_LOG_HZ) / _LOG_STEP
    return np.where(freq >= _MIN_LOG_HZ, log_part, linear)


def mel_to_hz(mel: np.ndarray | float | int | list | tuple) -> np.ndarray:
    """Inverse of ``hz_to_mel``."""
    mel = np.asarray(mel, dtype=np.float64)
    linear = mel * _F_SP
    log_part = _MIN_LOG_HZ * np.exp(_LOG_STEP * (np.maximum(mel, _MIN_LOG_MEL) - _MIN_LOG_MEL))
    return np.where(mel >= _MIN_LOG_MEL, log_part, linear)


@functools.lru_cache(maxsize=16)
def mel_filterbank(
    sample_rate: int = AUDIO_SAMPLE_RATE,
    n_fft: int = 400,
    n_mels: int = 80,
    f_min: float | int = 0.0,
    f_max: float | int | None = None,
) -> Float[np.ndarray, "freqs mels"]:
    """Slaney-style mel filterbank (float64, read-only, cached).

    Args:
        sample_rate: audio rate in Hz.
        n_fft: FFT size; the filterbank acts on its ``n_fft // 2 + 1`` rfft bins.
        n_mels: number of triangular filters.
        f_min: lowest filter edge in Hz.
        f_max: highest filter edge in Hz (default ``sample_rate / 2``).

    Returns:
        ``(n_fft // 2 + 1, n_mels)`` weights; column ``m`` is a triangle from mel point ``m`` to
        ``m + 2`` (``n_mels + 2`` points equally spaced on the mel scale), scaled to unit area in Hz.

    Raises:
        ValueError: for an invalid frequency range, or when a filter covers no FFT bin (too many
            mels for ``n_fft``), which would make that mel channel identically ``log_floor``.
    """
    nyquist = sample_rate / 2.0
    f_max = nyquist if f_max is None else float(f_max)
    if n_fft < 2 or n_mels < 1:
        raise ValueError(f"need n_fft >= 2 and n_mels >= 1, got n_fft={n_fft}, n_mels={n_mels}")
    if not 0.0 <= f_min < f_max <= nyquist:
        raise ValueError(
            f"need 0 <= f_min < f_max <= sample_rate/2 = {nyquist}, got f_min={f_min}, f_max={f_max}"
        )
    fft_freqs = np.arange(n_fft // 2 + 1) * (sample_rate / n_fft)
    edges = mel_to_hz(np.linspace(hz_to_mel(f_min), hz_to_mel(f_max), n_mels + 2))
    left, centre, right = edges[:-2], edges[1:-1], edges[2:]
    rising = (fft_freqs[:, None] - left[None, :]) / (centre - left)[None, :]
    falling = (right[None, :] - fft_freqs[:, None]) / (right - centre)[None, :]
    weights = np.maximum(0.0, np.minimum(rising, falling))
    weights *= (2.0 / (right - left))[None, :]
    empty = np.flatnonzero(weights.max(axis=0) <= 0.0)
    if empty.size:
        raise ValueError(
            f"n_mels={n_mels} is too many for n_fft={n_fft} at {sample_rate} Hz: mel filters "
            f"{empty.tolist()[:8]} cover no FFT bin; use fewer mels or a larger n_fft"
        )
    weights.setflags(write=False)
    return weights


def num_frames(samples: int, n_fft: int = 400, hop_length: int = 160, center: bool = True) -> int:
    """Number of log-mel frames for ``samples`` input samples (``1 + samples // hop`` if centred)."""
    if center:
        return 1 + samples // hop_length
    return 1 + (samples - n_fft) // hop_length


@functools.lru_cache(maxsize=16)
def _hann_window(win_length: int, n_fft: int) -> np.ndarray:
    # Periodic Hann (the STFT convention of librosa/torch), centred in an n_fft frame.
    n = np.arange(win_length)
    window = 0.5 - 0.5 * np.cos(2.0 * np.pi * n / win_length)
    left = (n_fft - win_length) // 2
    out = np.zeros(n_fft)
    out[left : left + win_length] = window
    return out


@functools.partial(
    jax.jit,
    static_argnames=(
        "sample_rate",
        "n_mels",
        "n_fft",
        "hop_length",
        "win_length",
        "f_min",
        "f_max",
        "center",
        "pad_mode",
        "log_floor",
    ),
)
def _log_mel(
    audio,
    *,
    sample_rate,
    n_mels,
    n_fft,
    hop_length,
    win_length,
    f_min,
    f_max,
    center,
    pad_mode,
    log_floor,
):
    batch_shape, samples = audio.shape[:-1], audio.shape[-1]
    x = audio.reshape(-1, samples)
    if center:
        pad = n_fft // 2
        x = jnp.pad(x, ((0, 0), (pad, pad)), mode=pad_mode)
    frames = num_frames(samples, n_fft, hop_length, center)
    # Static gather indices: (frames, n_fft). A strided view does not exist in XLA; the gather is
    # one fused op and costs n_fft / hop = 2.5x the signal in memory at the defaults.
    index = np.arange(frames)[:, None] * hop_length + np.arange(n_fft)[None, :]
    window = jnp.asarray(_hann_window(win_length, n_fft), dtype=x.dtype)
    framed = x[:, index] * window[None, None, :]  # (B, frames, n_fft)
    spectrum = jnp.fft.rfft(framed, n=n_fft, axis=-1)
    power = jnp.real(spectrum) ** 2 + jnp.imag(spectrum) ** 2
    weights = jnp.asarray(mel_filterbank(sample_rate, n_fft, n_mels, f_min, f_max), dtype=x.dtype)
    mel = jnp.matmul(power, weights, precision=jax.lax.Precision.HIGHEST)
    out = jnp.log(jnp.maximum(mel, log_floor))
    return out.reshape(*batch_shape, frames, n_mels)


def log_mel(
    audio: Float[Array | np.ndarray, "*batch samples"],
    sample_rate: int = AUDIO_SAMPLE_RATE,
    *,
    n_mels: int = 80,
    n_fft: int = 400,
    hop_length: int = 160,
    win_length: int | None = None,
    f_min: float | int = 0.0,
    f_max: float | int | None = None,
    center: bool = True,
    pad_mode: str = "constant",
    log_floor: float = 1e-10,
) -> Float[Array, "*batch frames n_mels"]:
    """Log-mel spectrogram of (batches of) mono signals; see the module docstring for conventions.

    Jitted (all keyword arguments are static). Works under an outer ``jit``/``vmap``; there the NaN
    check is skipped (a traced value cannot be inspected), and NaN input gives NaN frames.

    Args:
        audio: ``(*batch, samples)`` float signals (float32, or float64 with x64 enabled).
        sample_rate: audio rate in Hz.
        n_mels: mel channels.
        n_fft: FFT size (400 = 25 ms at 16 kHz).
        hop_length: frame step in samples (160 = 10 ms -> 100 frames/s at 16 kHz).
        win_length: Hann window length (default ``n_fft``; must be <= ``n_fft``).
        f_min: lowest mel filter edge in Hz.
        f_max: highest mel filter edge in Hz (default Nyquist).
        center: centre frame ``f`` on sample ``f * hop_length`` (pad ``n_fft // 2`` each side);
            otherwise frame ``f`` starts at sample ``f * hop_length``.
        pad_mode: ``"constant"`` (zeros, streaming-friendly) or ``"reflect"`` for centred frames.
        log_floor: ``log(max(mel, log_floor))``; keeps silence finite.

    Returns:
        ``(*batch, frames, n_mels)`` log-mel energies, ``frames = 1 + samples // hop_length`` when
        centred, ``1 + (samples - n_fft) // hop_length`` otherwise.

    Raises:
        ValueError: for an empty or NaN/inf signal, a signal too short for the framing, or invalid
            STFT/mel settings (names the value).
    """
    # Check finiteness on the host when the input is NumPy (no device round trip, no compile).
    host_finite = bool(np.all(np.isfinite(audio))) if isinstance(audio, np.ndarray) else None
    if not isinstance(audio, jax.core.Tracer):
        audio = jnp.asarray(audio)
    if audio.ndim < 1 or audio.shape[-1] == 0:
        raise ValueError(
            f"log_mel needs a (*batch, samples) signal with samples > 0, got {audio.shape}"
        )
    if not jnp.issubdtype(audio.dtype, jnp.floating):
        raise ValueError(f"log_mel needs a float signal, got dtype {audio.dtype}")
    if n_fft < 2 or hop_length < 1:
        raise ValueError(
            f"need n_fft >= 2 and hop_length >= 1, got n_fft={n_fft}, hop_length={hop_length}"
        )
    win_length = n_fft if win_length is None else win_length
    if not 1 <= win_length <= n_fft:
        raise ValueError(f"need 1 <= win_length <= n_fft={n_fft}, got win_length={win_length}")
    if pad_mode not in ("constant", "reflect"):
        raise ValueError(f"pad_mode must be 'constant' or 'reflect', got {pad_mode!r}")
    if not log_floor > 0:
        raise ValueError(f"log_floor must be > 0, got {log_floor!r}")
    samples = audio.shape[-1]
    if center and pad_mode == "reflect" and samples <= n_fft // 2:
        raise ValueError(
            f"reflect padding needs more than n_fft//2 = {n_fft // 2} samples, got {samples}"
        )
    if not center and samples < n_fft:
        raise ValueError(f"center=False needs at least n_fft = {n_fft} samples, got {samples}")
    # Validates the mel settings (and caches the bank) before tracing.
    mel_filterbank(
        int(sample_rate),
        int(n_fft),
        int(n_mels),
        float(f_min),
        None if f_max is None else float(f_max),
    )
    if host_finite is None and not isinstance(audio, jax.core.Tracer):
        host_finite = bool(jnp.all(jnp.isfinite(audio)))
    if host_finite is False:
        raise ValueError("log_mel: audio contains NaN or inf samples")
    return _log_mel(
        audio,
        sample_rate=int(sample_rate),
        n_mels=int(n_mels),
        n_fft=int(n_fft),
        hop_length=int(hop_length),
        win_length=int(win_length),
        f_min=float(f_min),
        f_max=None if f_max is None else float(f_max),
        center=bool(center),
        pad_mode=pad_mode,
        log_floor=float(log_floor),
    )
