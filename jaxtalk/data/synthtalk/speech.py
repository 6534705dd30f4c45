"""Source-filter speech synthesis at 16 kHz for one speaker's timeline.

A Rosenberg glottal pulse train (differentiated for lip radiation) at a per-utterance f0 contour
(speaker base x emotion, declination over each phrase, pitch accents) drives a Klatt-style cascade of
formant resonators; fricatives are band-passed noise, stops are a closure (a voice bar when voiced)
followed by a burst and aspiration, nasals carry a low murmur resonance. Each phone is rendered on
its own slice with its own fixed filters and the slices are overlap-added with complementary
raised-cosine cross-fades, so there is no per-sample Python loop. A timeline spoken by an eSpeak
speaker is rendered by eSpeak instead (``espeak_voice.render``).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import signal

from jaxtalk.data.synthtalk import espeak_voice
from jaxtalk.data.synthtalk.emotions import VoiceChange
from jaxtalk.data.synthtalk.phones import PHONE_INDEX, recipe
from jaxtalk.data.synthtalk.script import Timeline
from jaxtalk.data.synthtalk.speakers import SpeakerStyle

__all__ = ["f0_contour", "glottal_source", "synthesize"]

_XFADE = 0.008    # s, half-width of the cross-fade between neighbouring phones
_PREROLL = 0.01   # s, filter warm-up before a slice so resonators do not start from rest
_STOP_CLOSURE = 0.6  # fraction of a stop spent in closure before the burst
_LEVEL = 0.08     # overall output scale (open vowel RMS of order 0.1)
# F2 loci by place of articulation: a vowel next to a consonant has its F2 pulled toward the locus
# and its F1 lowered (acoustic coarticulation), so the vowel itself tells which consonant is near,
# as in real speech (labials pull F2 down, velars up).
_F2_LOCUS = {"p": 750.0, "b": 750.0, "m": 800.0, "f": 1000.0, "v": 1000.0, "th": 1500.0,
             "t": 1800.0, "d": 1800.0, "s": 1800.0, "z": 1800.0, "n": 1750.0, "l": 1300.0,
             "k": 2300.0, "g": 2300.0, "sh": 2000.0, "w": 650.0, "r": 1250.0}
_LOCUS = np.full(len(PHONE_INDEX), np.nan)
for _p, _f in _F2_LOCUS.items():
    _LOCUS[PHONE_INDEX[_p]] = _f
_LABIALS = frozenset(PHONE_INDEX[p] for p in ("p", "b", "m", "f", "v", "w"))
_PULL = 0.15  # fraction of the way to each neighbouring locus


def f0_contour(timeline: Timeline, style: SpeakerStyle, voice: VoiceChange,
               times: np.ndarray) -> np.ndarray:
    """Fundamental frequency in Hz at the given times, ``(len(times),)`` float64.

    Each phrase declines from +8% to -10% of the base (scaled by the emotion's pitch range), pitch
    accents add Gaussian bumps of up to +25%, backchannels stay low and flat.
    """
    base = style.f0 * voice.pitch
    rel = np.zeros_like(times)
    for s, e, bc, a in zip(timeline.phrase_starts, timeline.phrase_ends, timeline.backchannel,
                           timeline.phrase_arousal):
        inside = (times >= s) & (times < e)
        frac = (times[inside] - s) / max(e - s, 1e-3)
        # An aroused phrase has a wider pitch range (x 1.0 leaves a monologue's contour bitwise as it was).
        rel[inside] = -0.05 if bc else (0.08 - 0.18 * frac) * a
    if timeline.accents.size:
        d = times[:, None] - timeline.accents[None, :]
        strength = timeline.accent_strengths * timeline.arousal_at(timeline.accents)
        rel += (0.25 * strength[None, :] * np.exp(-0.5 * (d / 0.06) ** 2)).sum(1)
    return base * (1.0 + voice.pitch_range * rel)


def glottal_source(f0: np.ndarray, sample_rate: int) -> np.ndarray:
    """Differentiated Rosenberg pulse train following an f0 track, unit-ish amplitude.

    Args:
        f0: ``(samples,)`` Hz per sample.
        sample_rate: samples per second.
    Returns:
        ``(samples,)`` float64.
    """
    phase = np.cumsum(f0 / sample_rate) % 1.0
    open_, close = 0.4, 0.16
    pulse = np.where(
        phase < open_, 0.5 * (1.0 - np.cos(np.pi * phase / open_)),
        np.where(phase < open_ + close, np.cos(0.5 * np.pi * (phase - open_) / close), 0.0),
    )
    # Radiation at the lips differentiates the flow; scale so the per-sample derivative does not
    # depend on the pitch period length.
    return np.diff(pulse, prepend=0.0) * (sample_rate / (np.pi * f0 / open_)) * 0.5


@functools.lru_cache(maxsize=4096)
def _cascade(formants: tuple[float, ...], bandwidths: tuple[float, ...], scale: float,
             sample_rate: int) -> tuple[np.ndarray, np.ndarray]:
    # Klatt resonators with unit gain at DC, cascaded into one (b, a) pair.
    b, a = np.ones(1), np.ones(1)
    for f, bw in zip(formants, bandwidths):
        r = np.exp(-np.pi * bw / sample_rate)
        c1 = 2.0 * r * np.cos(2.0 * np.pi * f * scale / sample_rate)
        c2 = -r * r
        b = b * (1.0 - c1 - c2)
        a = np.polymul(a, [1.0, -c1, -c2])
    return b, a


@functools.lru_cache(maxsize=256)
def _band(low: float, high: float, sample_rate: int) -> tuple[np.ndarray, np.ndarray]:
    high = min(high, 0.49 * sample_rate)
    b, a = signal.butter(2, [low, high], btype="bandpass", fs=sample_rate)
    return b, a


def _coarticulated_formants(phone: int, prev: int, nxt: int) -> tuple[float, ...]:
    r = recipe(phone)
    if r.kind != "vowel":
        return r.formants
    f = np.array(r.formants)
    for nb in (prev, nxt):
        if nb in _LABIALS:
            # Closing or rounding the lips lengthens the tract: every formant drops.
            f *= 0.86
        elif not np.isnan(_LOCUS[nb]):
            f[1] += _PULL * (_LOCUS[nb] - r.formants[1])
            f[0] *= 0.94
    return tuple(round(float(x), 1) for x in f)


def _render_phone(phone: int, prev: int, nxt: int, lo: int, hi: int, s: int, e: int,
                  source: np.ndarray, noise: np.ndarray, style: SpeakerStyle, voice: VoiceChange,
                  sample_rate: int) -> np.ndarray:
    """Samples ``[lo, hi)`` of one phone whose nominal extent is ``[s, e)`` (neighbours prev/nxt)."""
    r = recipe(phone)
    out = np.zeros(hi - lo)
    if r.kind == "silence":
        return out
    warm = min(lo, int(_PREROLL * sample_rate))
    t = np.arange(lo, hi)
    if r.voiced and r.formants:
        x = source[lo - warm:hi]
        if voice.breathiness > 0:
            x = x + voice.breathiness * noise[lo - warm:hi]
        b, a = _cascade(_coarticulated_formants(phone, prev, nxt), r.bandwidths, style.formant_scale,
                        sample_rate)
        out += r.gain * signal.lfilter(b, a, x)[warm:]
    if r.noise_band is not None:
        b, a = _band(*r.noise_band, sample_rate)
        shaped = signal.lfilter(b, a, noise[lo - warm:hi])[warm:]
        if r.kind == "stop":
            burst_at = s + _STOP_CLOSURE * (e - s)
            dt = (t - burst_at) / sample_rate
            # Burst: sharp onset, ~8 ms decay; voiceless stops add ~30 ms aspiration.
            env = np.where(dt >= 0, np.exp(-dt / 0.008) + (0.0 if r.voiced else 0.3 * np.exp(-dt / 0.03)),
                           0.0)
            out += r.noise_gain * env * shaped * 4.0
        else:
            out += r.noise_gain * shaped * 4.0
    return out


def synthesize(timeline: Timeline, style: SpeakerStyle, voice: VoiceChange,
               rng: np.random.Generator, sample_rate: int = 16_000) -> np.ndarray:
    """Render a timeline as speech.

    Args:
        timeline: phones and prosody of one speaker's channel.
        style: the speaker (f0, vocal tract).
        voice: emotion's voice changes (pitch, range, energy, breathiness; rate is already in the
            timeline's durations).
        rng: NumPy generator for the noise sources (consumed).
        sample_rate: output rate in Hz.

    Returns:
        ``(round(duration * sample_rate),)`` float32 mono audio in [-1, 1].
    """
    if any(s is not None for s in timeline.phrase_speech):
        return espeak_voice.render(timeline, voice, rng, sample_rate)
    n = int(round(timeline.duration * sample_rate))
    # Pitch moves slowly: evaluate the contour at 200 Hz and interpolate to the sample grid.
    control = np.arange(int(timeline.duration * 200) + 2) / 200.0
    f0 = np.interp(np.arange(n) / sample_rate, control, f0_contour(timeline, style, voice, control))
    source = glottal_source(f0, sample_rate)
    noise = rng.standard_normal(n)
    audio = np.zeros(n)
    h = int(_XFADE * sample_rate)
    starts = np.round(timeline.starts * sample_rate).astype(np.int64)
    ends = np.round(timeline.ends * sample_rate).astype(np.int64)
    ph = timeline.phones
    prevs = np.concatenate([[ph[0]], ph[:-1]])
    nexts = np.concatenate([ph[1:], [ph[-1]]])
    # Each phone as loud as its phrase's arousal (1 in monologues).
    gains = timeline.arousal_at(0.5 * (timeline.starts + timeline.ends))
    for phone, prev, nxt, s, e, gain in zip(ph, prevs, nexts, starts.tolist(), ends.tolist(), gains.tolist()):
        if recipe(int(phone)).kind == "silence" or e <= s:
            continue
        lo, hi = max(s - h, 0), min(e + h, n)
        seg = _render_phone(int(phone), int(prev), int(nxt), lo, hi, s, e, source, noise, style,
                            voice, sample_rate)
        # Complementary raised-cosine ramps centred on each boundary: neighbours sum to one.
        t = np.arange(lo, hi)
        w = _ramp((t - s) / h) * _ramp((e - t) / h)
        audio[lo:hi] += (w * seg) * gain
    audio *= _LEVEL * voice.energy
    # A faint noise floor: real recordings are never digitally silent.
    audio += 1e-4 * noise[::-1]
    return np.clip(audio, -1.0, 1.0).astype(np.float32)


def _ramp(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.sin(0.5 * np.pi * np.clip(x, -1.0, 1.0)))
