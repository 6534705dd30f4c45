"""Recording conditions for training audio: what a real microphone, room and line do to clean speech.

A model trained on clean studio-level speech hears a user's laptop microphone, a reverberant room or a
phone call as unfamiliar sound. :func:`record` passes clean audio through a random recording chain,
drawn from a NumPy generator (the same generator state gives the same bytes):

1. room: reverberation by a synthetic impulse response (exponentially decaying noise with a given
   RT60, its direct path first), mixed in at a random wet level;
2. line: band-limiting, either a telephone band (300-3400 Hz) or a low-pass at 4-8 kHz (cheap
   microphones, narrow-band codecs), as Butterworth filters;
3. codec: 8-bit mu-law companding (G.711's quantisation noise), sometimes;
4. level: a gain of -24 to +6 dB (a quiet laptop to a close headset);
5. background: steady noise (white, pink or brown) at -75 to -38 dBFS, over the whole clip, silences
   included: the silence a model hears in a real room is rarely digital zero. A fifth of the chains
   add none: noise-gated calls and studio recordings do reach digital silence, and a model that never
   heard it reads it as something new (a model trained with noise under every clip opened the jaw on
   a -90 dBFS dither 0.035 rad away from where it held it in background noise).

Only the waveform changes: a clip's motion stays its target. The chain is causal and time-invariant
(a filter and a fixed noise), so it neither moves nor stretches the speech in time.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float
from scipy import signal

__all__ = ["RecordingChain", "draw_chain", "apply_chain", "record"]


@dataclasses.dataclass(frozen=True)
class RecordingChain:
    """One drawn recording chain (see the module docstring for each stage).

    Attributes:
        rt60: reverberation time in seconds (0: no room).
        wet: the reverberant part's level relative to the direct sound.
        band: ``"full"``, ``"phone"`` (300-3400 Hz) or ``"lowpass"``.
        cutoff: the low-pass corner in Hz (``band == "lowpass"``).
        mulaw: 8-bit mu-law companding on or off.
        gain_db: level change in dB.
        noise: ``"white"``, ``"pink"``, ``"brown"`` or ``"none"`` (no background noise).
        noise_dbfs: the background noise's RMS level in dBFS.
        seed: seed of the impulse response's and the noise's samples.
    """

    rt60: float
    wet: float
    band: str
    cutoff: float
    mulaw: bool
    gain_db: float
    noise: str
    noise_dbfs: float
    seed: int


def draw_chain(rng: np.random.Generator) -> RecordingChain:
    """Draw a recording chain: about half of the rooms reverberate, a third of the lines are narrow,
    a sixth of the chains compand, every chain has a gain, four in five a background noise."""
    room = rng.random() < 0.5
    band_draw = rng.random()
    band = "phone" if band_draw < 0.15 else "lowpass" if band_draw < 0.35 else "full"
    chain = RecordingChain(
        rt60=float(rng.uniform(0.15, 0.7)) if room else 0.0,
        wet=float(rng.uniform(0.1, 0.5)) if room else 0.0,
        band=band,
        cutoff=float(rng.uniform(4000.0, 7000.0)),
        mulaw=bool(rng.random() < 0.15),
        gain_db=float(rng.uniform(-24.0, 6.0)),
        noise=("white", "pink", "brown")[int(rng.integers(3))],
        noise_dbfs=float(rng.uniform(-75.0, -38.0)),
        seed=int(rng.integers(2**31)),
    )
    # Drawn last, so the other stages of a chain are the ones drawn before there was a "none".
    return dataclasses.replace(chain, noise="none") if rng.random() < 0.2 else chain


def _coloured_noise(rng: np.random.Generator, n: int, colour: str) -> np.ndarray:
    white = rng.standard_normal(n)
    if colour == "white":
        return white
    # Pink (1/f) and brown (1/f^2) by shaping the spectrum of white noise.
    spectrum = np.fft.rfft(white)
    f = np.fft.rfftfreq(n)
    f[0] = f[1] if n > 1 else 1.0
    spectrum /= np.sqrt(f) if colour == "pink" else f
    return np.fft.irfft(spectrum, n)


def _impulse_response(rng: np.random.Generator, rt60: float, sample_rate: int) -> np.ndarray:
    n = max(int(rt60 * sample_rate), 1)
    t = np.arange(n) / sample_rate
    tail = rng.standard_normal(n) * np.exp(-6.9078 * t / rt60)  # -60 dB at rt60
    return tail / np.sqrt(np.sum(tail ** 2))


def apply_chain(audio: Float[np.ndarray, " samples"], sample_rate: int,
                chain: RecordingChain) -> Float[np.ndarray, " samples"]:
    """Pass ``audio`` through ``chain`` (same length, float32, clipped to [-1, 1]).

    Raises:
        ValueError: for a non-1-D or non-finite signal, a sample rate too low for the chain's band, or
            an unknown band or noise.
    """
    x = np.asarray(audio, np.float64)
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ValueError(f"audio must be a finite 1-D waveform, got shape {x.shape}")
    if sample_rate < 8000:
        raise ValueError(f"recording chains need a sample rate of at least 8000 Hz, got {sample_rate}")
    if chain.noise not in ("white", "pink", "brown", "none"):
        raise ValueError(f"unknown noise {chain.noise!r}: white, pink, brown or none")
    rng = np.random.default_rng(chain.seed)
    n = x.shape[0]
    if chain.rt60 > 0 and n:
        ir = _impulse_response(rng, chain.rt60, sample_rate)
        x = x + chain.wet * signal.fftconvolve(x, ir)[:n]
    nyquist = sample_rate / 2
    if chain.band == "phone":
        sos = signal.butter(4, [300.0, min(3400.0, 0.95 * nyquist)], btype="bandpass", fs=sample_rate, output="sos")
        x = signal.sosfilt(sos, x)
    elif chain.band == "lowpass" and chain.cutoff < 0.95 * nyquist:
        x = signal.sosfilt(signal.butter(6, chain.cutoff, fs=sample_rate, output="sos"), x)
    elif chain.band not in ("full", "lowpass"):
        raise ValueError(f"unknown band {chain.band!r}: full, phone or lowpass")
    if chain.mulaw:
        mu = 255.0
        y = np.sign(x) * np.log1p(mu * np.minimum(np.abs(x), 1.0)) / np.log1p(mu)
        y = np.round((y + 1.0) * 127.5) / 127.5 - 1.0  # 8 bits
        x = np.sign(y) * ((1.0 + mu) ** np.abs(y) - 1.0) / mu
    x = x * 10 ** (chain.gain_db / 20)
    if n and chain.noise != "none":
        noise = _coloured_noise(rng, n, chain.noise)
        rms = np.sqrt(np.mean(noise ** 2))
        if rms > 0:
            x = x + noise * (10 ** (chain.noise_dbfs / 20) / rms)
    return np.clip(x, -1.0, 1.0).astype(np.float32)


def record(audio: Float[np.ndarray, " samples"], sample_rate: int,
           rng: np.random.Generator) -> Float[np.ndarray, " samples"]:
    """``audio`` as a random recording chain (:func:`draw_chain` from ``rng``) records it."""
    return apply_chain(audio, sample_rate, draw_chain(rng))
