"""Long-range dyadic behaviour in conversations: delayed mimicry and a shared conversational mood.

Both act over several seconds, so what a speaker does now depends on what happened turns ago, which
is what gives conversational context (TIMAR's history of past turns) something to explain:

* **Delayed mimicry** (head): a speaker repeats the partner's head movement (nods, tilts, sway)
  ``style.mimic_lag`` = 2-4 s later, attenuated by ``style.mimic_gain`` = 0.5-0.8 (times the global
  :attr:`DyadicEffects.mimicry`). People mirror their partner's posture and gestures with a lag of
  seconds rather than instantly; here the repeated movement is the partner's realised neck motion
  minus their static pose, mimicry included, so the echo of an echo decays by the product of gains.
* **Shared mood** (upper face): each conversation turn is spoken with an arousal (louder, with a
  wider pitch range, or quieter and flatter; ``conversation.py`` draws it per turn and the audio
  carries it). Both speakers' arousal while speaking drives one mood, a causal first-order average
  with time constant :attr:`DyadicEffects.mood_tau` (5 s, i.e. over the last few turns), which raises
  both speakers' brows, widens their eyes and lifts their cheeks in proportion
  (:attr:`DyadicEffects.mood`). A model must hear the arousal of past turns to know the mood.

Causality: frame ``f`` of a speaker depends on the partner only through the partner's frames before
``f`` (mimicry reads ``f - lag``; the mood reads the partner's voice one frame late). Monologues have
neither effect. The terms are computed from the partner's REALISED motion and voice, so they enter a
speaker's motion and oracle identically (like the articulators): the oracle stays the expectation of
the motion given everything observable in the conversation.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import signal

from jaxtalk.data.synthtalk.script import Timeline
from jaxtalk.data.synthtalk.speakers import SpeakerStyle
from jaxtalk.layout import EXP_INDEX, NECK_SLICE, PARAM_DIM

__all__ = ["DyadicEffects", "DEFAULT_EFFECTS", "MOOD_FACE", "mood_drive", "shared_mood", "mood_offset",
           "mimicry"]


@dataclasses.dataclass(frozen=True)
class DyadicEffects:
    """Strengths of the long-range dyadic effects (0 turns an effect off).

    Attributes:
        mimicry: factor on every speaker's ``mimic_gain``.
        mood: upper-face offset per unit of mood (see :data:`MOOD_FACE`).
        mood_tau: s, time constant of the mood's causal average.
    """

    mimicry: float = 1.0
    mood: float = 4.0
    mood_tau: float = 5.0

    def __post_init__(self) -> None:
        if self.mimicry < 0 or self.mood < 0 or not self.mood_tau > 0:
            raise ValueError(f"dyadic strengths must be >= 0 and mood_tau > 0: {self}")


DEFAULT_EFFECTS = DyadicEffects()

# The face of arousal, per unit of mood: brows up, eyes wide, cheeks raised.
MOOD_FACE = np.zeros(PARAM_DIM)
for _name, _w in (("brow_inner_up_l", 1.0), ("brow_inner_up_r", 1.0), ("brow_outer_up_l", 0.8),
                  ("brow_outer_up_r", 0.8), ("brow_down_l", -0.4), ("brow_down_r", -0.4),
                  ("eye_wide_l", 0.7), ("eye_wide_r", 0.7), ("cheek_raise_l", 0.5), ("cheek_raise_r", 0.5)):
    MOOD_FACE[EXP_INDEX[_name]] = _w


def mood_drive(timeline: Timeline, num_frames: int, fps: int = 25) -> np.ndarray:
    """Log-arousal while speaking (0 in silence), ``(num_frames,)`` float64."""
    t = np.arange(num_frames) / fps
    return np.where(timeline.speaking(t), np.log(timeline.arousal_at(t)), 0.0)


def shared_mood(own: Timeline, other: Timeline, num_frames: int, fps: int = 25, *,
                tau: float = DEFAULT_EFFECTS.mood_tau, start: np.ndarray | int = 0) -> np.ndarray:
    """One speaker's view of the conversation's mood, ``(num_frames,)`` float64.

    A causal first-order average (time constant ``tau``) of the speaker's own log-arousal while
    speaking plus the partner's, one frame late.

    Args:
        own, other: the speaker's and the partner's timelines.
        num_frames: frames to produce.
        fps: frame rate.
        tau: time constant (s).
        start: frames (scalar, or ``(num_frames,)`` per frame) before which nothing is heard: the
            mood as estimated from a window of visible turns only (0: the generator's true mood).
    """
    other_drive = mood_drive(other, num_frames, fps)
    drive = mood_drive(own, num_frames, fps) + np.concatenate([[0.0], other_drive[:-1]])
    b, a = [1.0 - np.exp(-1.0 / (tau * fps))], [1.0, -np.exp(-1.0 / (tau * fps))]
    start = np.clip(np.broadcast_to(np.asarray(start, np.int64), (num_frames,)), 0, None)
    if np.any(start > np.arange(num_frames)):
        raise ValueError("a frame's window start lies after the frame")
    out = np.empty(num_frames)
    # One causal filter run per distinct window start (a turn boundary), begun at that start.
    for s0 in np.unique(start):
        sel = start == s0
        out[sel] = signal.lfilter(b, a, drive[int(s0):])[np.flatnonzero(sel) - int(s0)]
    return out


def mood_offset(mood: np.ndarray, effects: DyadicEffects = DEFAULT_EFFECTS) -> np.ndarray:
    """The face of a mood, ``(frames, 56)`` float64."""
    return effects.mood * mood[:, None] * MOOD_FACE[None, :]


def mimicry(realised: tuple[np.ndarray, np.ndarray], static: tuple[np.ndarray, np.ndarray],
            styles: tuple[SpeakerStyle, SpeakerStyle], fps: int = 25,
            effects: DyadicEffects = DEFAULT_EFFECTS) -> tuple[np.ndarray, np.ndarray]:
    """Each speaker's delayed repetition of the other's head movement, two ``(frames, 56)`` arrays.

    Speaker s's term at frame f is ``gain_s * (dev_o(f - lag_s) + mimic_o(f - lag_s))``, where
    ``dev_o`` is the partner's neck motion without mimicry minus their static pose. Solved in blocks
    of the shorter lag: every block reads only frames of earlier blocks, so the mutual recursion is
    exact.

    Args:
        realised: both speakers' ``(frames, 56)`` motion without mimicry.
        static: both speakers' ``(56,)`` static pose (rest + emotion offset).
        styles: both speakers (``mimic_lag``, ``mimic_gain``).
        fps: frame rate.
        effects: global strengths.
    """
    n = realised[0].shape[0]
    dev = [realised[s][:, NECK_SLICE] - static[s][None, NECK_SLICE] for s in (0, 1)]
    lags = [max(1, int(round(st.mimic_lag * fps))) for st in styles]
    gains = [effects.mimicry * st.mimic_gain for st in styles]
    mim = [np.zeros((n, 3)), np.zeros((n, 3))]
    block = min(lags)
    for b0 in range(0, n, block):
        f = np.arange(b0, min(b0 + block, n))
        for s in (0, 1):
            o = 1 - s
            src = f - lags[s]
            ok = src >= 0  # src < b0 for every f in the block: only already-final frames are read
            mim[s][f[ok]] = gains[s] * (dev[o][src[ok]] + mim[o][src[ok]])
    out = []
    for s in (0, 1):
        m = np.zeros((n, PARAM_DIM))
        m[:, NECK_SLICE] = mim[s]
        out.append(m)
    return out[0], out[1]
