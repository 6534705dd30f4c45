"""Audio file input/output and sample-rate conversion (NumPy + soundfile + SciPy, host side).

Everything here runs on the host: reading files is I/O, and polyphase resampling of a whole clip is a
one-off preprocessing step, so there is nothing to gain from tracing it.
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np
import soundfile as sf
from jaxtyping import Float
from scipy.signal import resample_poly

from jaxtalk.types import AUDIO_SAMPLE_RATE

__all__ = ["load_audio", "save_audio", "resample_audio", "check_audio", "rational_ratio", "AUDIO_SUFFIXES"]

# The audio files the commands take (what soundfile reads, by suffix).
AUDIO_SUFFIXES = (".wav", ".flac", ".ogg", ".aiff", ".aif")

# Largest down factor of the rational resampling ratio. Common pairs (44.1k, 48k, 22.05k, 8k -> 16k)
# reduce to small terms; any integer rate up to 32768 Hz is converted exactly, and other ratios are
# approximated to ~1e-9 relative. The cost: the polyphase filter has ~20 * max(up, down) taps, so an odd
# rate such as 16001 Hz takes ~0.1 s per second of audio instead of ~1 ms.
_MAX_RATIO_DENOMINATOR = 2**15

# A clip whose peak absolute amplitude is at or below this is "silent" (full scale is 1.0). -120 dBFS
# is below the quantisation step of 16-bit audio (~3e-5), so only digital silence is rejected.
_SILENCE_PEAK = 1e-6

# One analysis window of the default log-mel front end (400 samples at 16 kHz).
_DEFAULT_MIN_DURATION = 0.025


def rational_ratio(src_rate: float | int, dst_rate: float | int) -> tuple[int, int]:
    """The (up, down) pair with up / down ~= dst_rate / src_rate used by polyphase resampling.

    Args:
        src_rate: input rate in Hz (> 0).
        dst_rate: output rate in Hz (> 0).

    Returns:
        ``(up, down)``, coprime positive integers: exact for integer rates up to 32768 Hz (and
        others whose ratio has small terms), otherwise the best approximation with down <= 32768.

    Raises:
        ValueError: for a non-positive or non-finite rate.
    """
    for name, rate in (("src_rate", src_rate), ("dst_rate", dst_rate)):
        if not np.isfinite(rate) or rate <= 0:
            raise ValueError(f"{name} must be a positive finite number of Hz, got {rate!r}")
    # Go through str() so that 22050.0 and 29.97 become exact decimals, not binary float expansions.
    ratio = Fraction(str(float(dst_rate))) / Fraction(str(float(src_rate)))
    ratio = ratio.limit_denominator(_MAX_RATIO_DENOMINATOR)
    if ratio.numerator == 0:  # dst far below src: limit_denominator rounded to zero
        ratio = Fraction(1, _MAX_RATIO_DENOMINATOR)
    return ratio.numerator, ratio.denominator


def resample_audio(
    audio: Float[np.ndarray, " samples"], src_rate: float | int, dst_rate: float | int
) -> Float[np.ndarray, " new_samples"]:
    """Resample a mono signal with a polyphase anti-aliasing FIR filter.

    Uses ``scipy.signal.resample_poly`` with ``up / down`` a rational approximation of
    ``dst_rate / src_rate`` (see ``rational_ratio``) and its default Kaiser-window (beta 5) low-pass
    at the lower of the two Nyquist frequencies, so content above the new Nyquist is attenuated
    rather than aliased.

    Args:
        audio: ``(samples,)`` signal.
        src_rate: its rate in Hz.
        dst_rate: the wanted rate in Hz.

    Returns:
        ``(ceil(samples * up / down),)`` float32 signal (a copy even when the rates are equal).

    Raises:
        ValueError: for a non-positive rate or an input that is not one-dimensional.
    """
    audio = np.asarray(audio)
    if audio.ndim != 1:
        raise ValueError(f"resample_audio expects a 1-D signal, got shape {audio.shape}")
    up, down = rational_ratio(src_rate, dst_rate)
    if up == down:
        return audio.astype(np.float32, copy=True)
    # Filter in float64: the FIR has hundreds of taps and float32 accumulation would add ~1e-6 noise.
    out = resample_poly(audio.astype(np.float64), up, down)
    return out.astype(np.float32)


def check_audio(
    audio: np.ndarray,
    sample_rate: float | int,
    *,
    min_duration: float | int = _DEFAULT_MIN_DURATION,
    allow_silence: bool = False,
    name: str = "audio",
) -> None:
    """Validate a mono signal: 1-D, non-empty, finite, long enough, and (by default) not silent.

    Args:
        audio: the signal to check, ``(samples,)``.
        sample_rate: its rate in Hz (used for the duration check and messages).
        min_duration: shortest accepted duration in seconds.
        allow_silence: accept an all-silent signal.
        name: how the signal is called in error messages (e.g. its file path).

    Raises:
        ValueError: naming ``name`` and the offending property.
    """
    if audio.ndim != 1:
        raise ValueError(
            f"{name}: expected mono audio of shape (samples,), got shape {audio.shape}"
        )
    if audio.size == 0:
        raise ValueError(f"{name}: audio is empty (0 samples)")
    finite = np.isfinite(audio)
    if not finite.all():
        bad = int(np.argmin(finite))
        raise ValueError(
            f"{name}: audio contains {int((~finite).sum())} NaN/inf samples (first at index {bad})"
        )
    duration = audio.size / sample_rate
    if duration < min_duration:
        raise ValueError(
            f"{name}: audio is too short: {audio.size} samples = {duration * 1e3:.2f} ms at "
            f"{sample_rate} Hz, need at least {min_duration * 1e3:.2f} ms"
        )
    if not allow_silence:
        peak = float(np.max(np.abs(audio)))
        if peak <= _SILENCE_PEAK:
            raise ValueError(
                f"{name}: audio is silent (peak |x| = {peak:.3g} <= {_SILENCE_PEAK:g}): no speech to animate"
            )


def load_audio(
    path: str | os.PathLike,
    target_rate: int = AUDIO_SAMPLE_RATE,
    *,
    min_duration: float | int = _DEFAULT_MIN_DURATION,
    allow_silence: bool = False,
) -> Float[np.ndarray, " samples"]:
    """Read a WAV/FLAC (any format soundfile reads) as mono float32 at ``target_rate``.

    Integer PCM (16/24/32-bit) is scaled to [-1, 1) by soundfile; float files are read as stored.
    Multi-channel audio is averaged to mono (the average keeps a signal duplicated on both channels
    unchanged). Other rates are converted with ``resample_audio`` (polyphase FIR).

    Args:
        path: the audio file.
        target_rate: output sample rate in Hz (default 16 kHz, jaxtalk's audio rate).
        min_duration: shortest accepted duration in seconds (default one 25 ms analysis window).
        allow_silence: accept a file that is entirely digital silence.

    Returns:
        ``(samples,)`` float32 mono signal at ``target_rate``.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: if the file cannot be decoded, or the audio is empty, contains NaN/inf, is
            shorter than ``min_duration``, or is silent (unless ``allow_silence``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"audio file not found: {str(path)!r}")
    if not isinstance(target_rate, (int, np.integer)) or target_rate <= 0:
        raise ValueError(f"target_rate must be a positive integer of Hz, got {target_rate!r}")
    try:
        data, rate = sf.read(str(path), dtype="float32", always_2d=True)
    except (sf.LibsndfileError, RuntimeError, TypeError) as err:
        raise ValueError(f"{str(path)!r}: cannot decode audio file ({err})") from err
    name = repr(str(path))
    if data.size == 0:
        raise ValueError(f"{name}: audio is empty (0 samples)")
    mono = data.mean(axis=1, dtype=np.float32) if data.shape[1] > 1 else data[:, 0]
    # Validate before resampling: the FIR filter would smear a NaN over the whole clip.
    check_audio(mono, rate, min_duration=min_duration, allow_silence=allow_silence, name=name)
    if rate != target_rate:
        mono = resample_audio(mono, rate, target_rate)
    return np.ascontiguousarray(mono, dtype=np.float32)


def save_audio(
    path: str | os.PathLike,
    audio: Float[np.ndarray, " samples"],
    sample_rate: int = AUDIO_SAMPLE_RATE,
    *,
    subtype: str | None = None,
) -> Path:
    """Write a mono signal to a WAV/FLAC file (format from the suffix).

    Args:
        path: output file; ``.wav`` or ``.flac`` (any suffix soundfile knows).
        audio: ``(samples,)`` signal in [-1, 1].
        sample_rate: its rate in Hz.
        subtype: soundfile subtype, e.g. ``"PCM_16"`` or ``"FLOAT"``; default: soundfile's default
            for the format (16-bit PCM for WAV and FLAC).

    Returns:
        The path written.

    Raises:
        ValueError: for a non 1-D, empty or non-finite signal.
    """
    audio = np.asarray(audio)
    check_audio(audio, sample_rate, min_duration=0.0, allow_silence=True, name=str(path))
    path = Path(path)
    sf.write(str(path), audio.astype(np.float32), int(sample_rate), subtype=subtype)
    return path
