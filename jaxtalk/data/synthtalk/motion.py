"""Head motion at 25 fps in the 56-d layout ``[exp 50 | jaw 3 | neck 3]`` caused by a timeline.

Deterministic parts (the oracle): viseme targets blended by a zero-phase critically damped spring
(coarticulation in both directions) and shifted so motion leads sound by the speaker's lead; brow
raises and nods on pitch accents; a slight head lift while speaking; the emotion's face offset; as a
listener, nods after the other's phrases end and a lagged mirror of the other's emotion (both causal
in the other's past). Stochastic parts: Poisson blinks, head sway with a random phase plus smooth
noise, and smooth idle drift on the non-articulatory expression dims. The oracle replaces each
stochastic part by its expectation, which makes it the mean-squared-error-optimal predictor given
script, style and emotion.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy import signal

from jaxtalk.data.synthtalk.phones import viseme_targets
from jaxtalk.data.synthtalk.script import Timeline
from jaxtalk.data.synthtalk.speakers import SpeakerStyle
from jaxtalk.layout import EXP_INDEX, GROUPS, JAW_OPEN_INDEX, NECK_SLICE, PARAM_DIM

__all__ = [
    "MotionParts",
    "ARTICULATORS",
    "articulation",
    "prosody",
    "listener_reaction",
    "stochastic",
    "compose",
]

_CONTROL_RATE = 100  # Hz, internal rate of the articulation targets (phones can be 50 ms long)
_JAW_SLOWNESS = 1.4  # the jaw is heavier than the lips
# Articulatory dims: everything visemes drive except the emotional mouth corners / stretch.
ARTICULATORS: np.ndarray = np.concatenate([np.arange(0, 9), GROUPS["cheek"][2:], GROUPS["jaw"]])
# Dims a listener mirrors from the other's emotion (corners, brows, eyes, cheek raise, nose; no
# blinks, no articulators).
_MIRRORED = np.concatenate([np.arange(9, 18), np.arange(20, 24), np.arange(26, 28)])
# Idle drift lives off the mouth so a silent mouth stays still.
_DRIFT_DIMS = np.concatenate([np.arange(12, 18), np.arange(20, 24), np.arange(26, 50)])
_BLINK_KERNEL = np.array([0.35, 0.85, 1.0, 0.85, 0.55, 0.3, 0.12])
_BLINK_AMPLITUDE = 1.8
_NECK_PITCH, _NECK_YAW, _NECK_ROLL = NECK_SLICE.start, NECK_SLICE.start + 1, NECK_SLICE.start + 2


@dataclasses.dataclass(frozen=True)
class MotionParts:
    """A channel's motion and its oracle, both ``(frames, 56)`` float32."""

    motion: np.ndarray
    oracle: np.ndarray


def _frame_times(num_frames: int, fps: int) -> np.ndarray:
    return np.arange(num_frames) / fps


@functools.lru_cache(maxsize=1024)
def _spring(tau: float, rate: float | int) -> tuple[np.ndarray, np.ndarray]:
    # Critically damped second-order system = two identical first-order low-passes in cascade.
    pole = np.exp(-1.0 / (tau * rate))
    return np.array([(1.0 - pole) ** 2]), np.array([1.0, -2.0 * pole, pole * pole])


def _nod(t: np.ndarray) -> np.ndarray:
    # A damped down-up head nod starting at t = 0 (zero before), about half a second long.
    tt = np.maximum(t, 0.0)
    return np.where(t >= 0, np.sin(2.0 * np.pi * tt / 0.5) * np.exp(-tt / 0.2), 0.0)


def articulation(timeline: Timeline, style: SpeakerStyle, num_frames: int, fps: int = 25) -> np.ndarray:
    """Mouth and jaw offsets from the phones, ``(num_frames, 56)`` float64.

    Targets are sampled at 100 Hz, smoothed forward and backward by a critically damped spring with
    the speaker's time constant (jaw 1.4x slower), and read ``style.lead`` seconds ahead of each
    frame, so the face anticipates the sound.
    """
    n_ctrl = num_frames * (_CONTROL_RATE // fps)
    t = np.arange(n_ctrl) / _CONTROL_RATE + style.lead
    idx = np.clip(np.searchsorted(timeline.ends, t, side="right"), 0, len(timeline.phones) - 1)
    targets = viseme_targets()[timeline.phones[idx]] * style.articulation  # (n_ctrl, 56)
    out = np.empty_like(targets)
    b, a = _spring(style.smoothing, _CONTROL_RATE)
    # filtfilt pads by reflection; silence at both clip ends makes that harmless.
    out[:] = signal.filtfilt(b, a, targets, axis=0, padtype="constant")
    bj, aj = _spring(style.smoothing * _JAW_SLOWNESS, _CONTROL_RATE)
    out[:, JAW_OPEN_INDEX] = signal.filtfilt(bj, aj, targets[:, JAW_OPEN_INDEX], padtype="constant")
    out[:, JAW_OPEN_INDEX + 1] = style.jaw_asym * out[:, JAW_OPEN_INDEX]
    out[:, JAW_OPEN_INDEX + 2] = -0.5 * style.jaw_asym * out[:, JAW_OPEN_INDEX]
    return out[:: _CONTROL_RATE // fps]


def prosody(timeline: Timeline, style: SpeakerStyle, num_frames: int, fps: int = 25) -> np.ndarray:
    """Brow raises and nods on pitch accents and a head lift while speaking, ``(num_frames, 56)``."""
    t = _frame_times(num_frames, fps)
    out = np.zeros((num_frames, PARAM_DIM))
    if timeline.accents.size:
        d = t[:, None] - timeline.accents[None, :]
        s = timeline.accent_strengths[None, :]
        bump = (s * np.exp(-0.5 * ((d + 0.03) / 0.11) ** 2)).sum(1)
        g = style.brow_gain
        for name, w in (("brow_inner_up_l", 1.0), ("brow_inner_up_r", 1.0),
                        ("brow_outer_up_l", 0.75), ("brow_outer_up_r", 0.7),
                        ("eye_wide_l", 0.3), ("eye_wide_r", 0.3)):
            out[:, EXP_INDEX[name]] = 1.2 * g * w * bump
        out[:, _NECK_PITCH] += 0.035 * style.nod_gain * (s * _nod(d + 0.05)).sum(1)
    # Head lifts a little and turns slightly while talking (smoothed voice activity).
    b, a = _spring(0.25, fps)
    active = signal.filtfilt(b, a, timeline.speaking(t).astype(np.float64), padtype="constant")
    out[:, _NECK_PITCH] -= 0.025 * active
    out[:, _NECK_YAW] += 0.012 * style.nod_gain * active
    return out


def listener_reaction(other: Timeline | None, other_emotion: np.ndarray, style: SpeakerStyle,
                      num_frames: int, fps: int = 25) -> np.ndarray:
    """How a listener reacts to the other speaker, causally, ``(num_frames, 56)`` float64.

    Frame ``f`` depends only on the other's timeline before ``f / fps`` (every filter here is causal
    and every response starts after its cause).

    Args:
        other: the other speaker's timeline, or None for a monologue (no reaction).
        other_emotion: ``(56,)`` the other's emotion face offset.
        style: the listener.
        num_frames: frames to produce.
        fps: frame rate.
    """
    out = np.zeros((num_frames, PARAM_DIM))
    if other is None:
        return out
    t = _frame_times(num_frames, fps)
    # Nods after each of the other's turns (not their backchannels) ends.
    ends = other.phrase_ends[~other.backchannel]
    if ends.size:
        d = t[:, None] - (ends[None, :] + style.react_lag)
        out[:, _NECK_PITCH] += 0.05 * style.nod_gain * _nod(d).sum(1)
    # Emotion contagion: the other's emotion as shown while talking, accumulated causally
    # (1 s time constant), delayed by the mirror lag, then eased in (0.4 s).
    shown = signal.lfilter(*_first_order(1.0, fps), other.speaking(t).astype(np.float64))
    lag = int(round(style.mirror_lag * fps))
    shown = np.concatenate([np.zeros(min(lag, num_frames)), shown[: max(num_frames - lag, 0)]])
    shown = signal.lfilter(*_first_order(0.4, fps), shown)
    out[:, _MIRRORED] = style.mirror_gain * shown[:, None] * other_emotion[None, _MIRRORED]
    return out


@functools.lru_cache(maxsize=64)
def _first_order(tau: float, rate: float | int) -> tuple[np.ndarray, np.ndarray]:
    pole = np.exp(-1.0 / (tau * rate))
    return np.array([1.0 - pole]), np.array([1.0, -pole])


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], tau: float, fps: int) -> np.ndarray:
    """Unit-variance stationary noise low-passed by a critically damped spring (time constant tau)."""
    b, a = _spring(tau, fps)
    warm = int(8 * tau * fps) + 1
    x = signal.lfilter(b, a, rng.standard_normal((shape[0] + warm, shape[1])), axis=0)[warm:]
    # Stationary variance of the filter output for unit white input = sum of h^2.
    h = signal.lfilter(b, a, np.r_[1.0, np.zeros(40 * warm)])
    return x / np.sqrt(np.sum(h * h))


def stochastic(rng: np.random.Generator, style: SpeakerStyle, num_frames: int,
               fps: int = 25) -> tuple[np.ndarray, np.ndarray]:
    """Blinks, head sway and idle drift.

    Returns:
        ``(sample (num_frames, 56), expectation (56,))``: one draw and its expected value per dim.
    """
    out = np.zeros((num_frames, PARAM_DIM))
    k = len(_BLINK_KERNEL)
    p = style.blink_rate / fps
    # Start k frames early so blinks in progress at frame 0 appear: the process is stationary.
    events = (rng.random(num_frames + k) < p) * rng.uniform(0.75, 1.25, num_frames + k)
    blinks = np.convolve(events, _BLINK_KERNEL)[k: k + num_frames] * _BLINK_AMPLITUDE
    out[:, GROUPS["blink"]] = blinks[:, None] * np.array([1.0, 0.95])
    expect = np.zeros(PARAM_DIM)
    expect[GROUPS["blink"]] = p * _BLINK_KERNEL.sum() * _BLINK_AMPLITUDE * np.array([1.0, 0.95])

    t = _frame_times(num_frames, fps)
    phases = rng.uniform(0.0, 2.0 * np.pi, 3)
    sway_noise = _smooth_noise(rng, (num_frames, 3), 0.6, fps)
    amp = style.sway_amp
    for j, (rel_amp, rel_freq) in zip((_NECK_PITCH, _NECK_YAW, _NECK_ROLL),
                                      ((0.5, 0.8), (1.0, 1.0), (0.6, 1.3))):
        out[:, j] = rel_amp * amp * np.sin(2.0 * np.pi * style.sway_freq * rel_freq * t + phases[j - _NECK_PITCH])
    out[:, NECK_SLICE] += 0.5 * amp * sway_noise

    drift = _smooth_noise(rng, (num_frames, len(_DRIFT_DIMS)), 0.08, fps)
    scale = np.where(_DRIFT_DIMS >= GROUPS["residual"][0], 0.15, 0.12)
    out[:, _DRIFT_DIMS] += drift * scale
    return out, expect


def compose(style: SpeakerStyle, emotion_offset: np.ndarray, parts: list[np.ndarray],
            noise: np.ndarray, noise_mean: np.ndarray) -> MotionParts:
    """Sum the parts over the resting face, add noise (or its mean for the oracle), clip the jaw.

    Args:
        style: the speaker (resting face).
        emotion_offset: ``(56,)`` the speaker's own emotion offset.
        parts: deterministic ``(frames, 56)`` components.
        noise: ``(frames, 56)`` stochastic sample; ``noise_mean (56,)`` its expectation.

    Returns:
        ``MotionParts`` with float32 arrays; jaw opening clipped to [0, 0.4] rad.
    """
    det = style.rest[None, :] + emotion_offset[None, :] + sum(parts)
    motion = det + noise
    oracle = det + noise_mean[None, :]
    for m in (motion, oracle):
        m[:, JAW_OPEN_INDEX] = np.clip(m[:, JAW_OPEN_INDEX], 0.0, 0.4)
    return MotionParts(motion.astype(np.float32), oracle.astype(np.float32))
