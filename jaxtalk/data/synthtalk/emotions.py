"""The 11 EmoVOCA emotion categories plus neutral: what each does to the face and to the voice.

Intensity 1-3 scales both effects (MEAD's three levels); the face offset is added to the resting
face, and the voice changes pitch, pitch range, speaking rate, loudness and breathiness, so audio
carries the emotion as well as the label does.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxtalk.layout import EXP_INDEX, JAW_OPEN_INDEX, NECK_SLICE, PARAM_DIM

__all__ = ["EMOTIONS", "VoiceChange", "emotion_index", "intensity_scale", "face_offset",
           "voice_change"]

EMOTIONS: tuple[str, ...] = (
    "neutral", "afraid", "ashamed", "angry", "disgust", "happy", "sad", "drunk", "ill",
    "suspicious", "pleased", "upset",
)

# Full-intensity face offsets. Names from jaxtalk.layout; "jaw" opens the mouth, "neck_pitch" /
# "neck_roll" tilt the head (radians).
_FACE: dict[str, dict[str, float]] = {
    "neutral": {},
    "afraid": {"brow_inner_up_l": 1.2, "brow_inner_up_r": 1.2, "brow_outer_up_l": 0.8,
               "brow_outer_up_r": 0.8, "eye_wide_l": 1.5, "eye_wide_r": 1.5, "mouth_stretch": 1.0,
               "jaw": 0.04},
    "ashamed": {"brow_inner_up_l": 0.6, "brow_inner_up_r": 0.6, "mouth_corner_down": 0.6,
                "lip_tight": 0.5, "eye_wide_l": -0.4, "eye_wide_r": -0.4, "neck_pitch": 0.08},
    "angry": {"brow_down_l": 1.5, "brow_down_r": 1.5, "lip_tight": 0.8, "nose_wrinkle_l": 0.4,
              "nose_wrinkle_r": 0.4, "eye_wide_l": 0.4, "eye_wide_r": 0.4, "mouth_corner_down": 0.4},
    "disgust": {"nose_wrinkle_l": 1.5, "nose_wrinkle_r": 1.3, "upper_lip_raise": 0.9,
                "brow_down_l": 0.6, "brow_down_r": 0.6, "mouth_corner_down": 0.5,
                "cheek_raise_l": 0.4, "cheek_raise_r": 0.4},
    "happy": {"mouth_corner_up": 1.5, "cheek_raise_l": 1.2, "cheek_raise_r": 1.2,
              "mouth_stretch": 0.3, "brow_outer_up_l": 0.2, "brow_outer_up_r": 0.2},
    "sad": {"brow_inner_up_l": 1.2, "brow_inner_up_r": 1.2, "mouth_corner_down": 1.2,
            "brow_outer_up_l": -0.3, "brow_outer_up_r": -0.3, "lip_tight": 0.2, "neck_pitch": 0.05},
    "drunk": {"eye_wide_l": -0.8, "eye_wide_r": -0.8, "brow_outer_up_l": -0.4,
              "brow_outer_up_r": -0.4, "mouth_corner_up": 0.3, "jaw": 0.05, "neck_roll": 0.05},
    "ill": {"brow_inner_up_l": 0.5, "brow_inner_up_r": 0.5, "eye_wide_l": -0.6, "eye_wide_r": -0.6,
            "mouth_corner_down": 0.5, "cheek_puff_l": -0.3, "cheek_puff_r": -0.3},
    "suspicious": {"brow_down_l": 0.9, "brow_down_r": 0.2, "eye_wide_l": -0.5, "eye_wide_r": -0.3,
                   "lip_tight": 0.6, "cheek_raise_l": 0.3, "neck_roll": -0.03},
    "pleased": {"mouth_corner_up": 0.9, "cheek_raise_l": 0.6, "cheek_raise_r": 0.6,
                "brow_inner_up_l": 0.1, "brow_inner_up_r": 0.1},
    "upset": {"brow_down_l": 0.8, "brow_down_r": 0.8, "brow_inner_up_l": 0.6,
              "brow_inner_up_r": 0.6, "mouth_corner_down": 1.0, "lip_tight": 0.6},
}


@dataclasses.dataclass(frozen=True)
class VoiceChange:
    """Multiplicative voice changes of one emotion at a given intensity (1.0 = unchanged)."""

    pitch: float = 1.0
    pitch_range: float = 1.0
    rate: float = 1.0
    energy: float = 1.0
    breathiness: float = 0.0  # additive aspiration-noise level


# Full-intensity (pitch, pitch range, rate, energy, breathiness).
_VOICE: dict[str, tuple[float, float, float, float, float]] = {
    "neutral": (1.0, 1.0, 1.0, 1.0, 0.0),
    "afraid": (1.25, 1.2, 1.15, 0.95, 0.08),
    "ashamed": (0.93, 0.7, 0.88, 0.7, 0.03),
    "angry": (1.1, 1.3, 1.1, 1.5, 0.0),
    "disgust": (0.95, 0.9, 0.9, 1.1, 0.02),
    "happy": (1.15, 1.4, 1.08, 1.2, 0.0),
    "sad": (0.9, 0.6, 0.85, 0.75, 0.04),
    "drunk": (0.95, 1.3, 0.75, 1.0, 0.02),
    "ill": (0.92, 0.6, 0.85, 0.65, 0.08),
    "suspicious": (1.0, 0.8, 0.92, 0.9, 0.0),
    "pleased": (1.06, 1.15, 1.0, 1.05, 0.0),
    "upset": (1.08, 1.25, 1.05, 1.25, 0.02),
}
assert set(_FACE) == set(EMOTIONS) == set(_VOICE)
_MOUTH_EMOTION = [EXP_INDEX[n] for n in ("mouth_corner_up", "mouth_corner_down", "mouth_stretch",
                                          "lip_tight", "upper_lip_raise")]


def emotion_index(emotion: str) -> int:
    """Index of an emotion name in ``EMOTIONS``.

    Raises:
        ValueError: for an unknown emotion.
    """
    if emotion not in EMOTIONS:
        raise ValueError(f"unknown emotion {emotion!r}; known: {EMOTIONS}")
    return EMOTIONS.index(emotion)


def intensity_scale(intensity: int) -> float:
    """Fraction of the full effect at intensity 1, 2 or 3 (0.45, 0.75, 1.0).

    Raises:
        ValueError: for an intensity outside 1-3.
    """
    if intensity not in (1, 2, 3):
        raise ValueError(f"emotion intensity must be 1, 2 or 3, got {intensity!r}")
    return (0.45, 0.75, 1.0)[intensity - 1]


def face_offset(emotion: str, intensity: int) -> np.ndarray:
    """Offset of the 56-d head vector for an emotion at an intensity, shape ``(56,)`` float64."""
    emotion_index(emotion)
    s = intensity_scale(intensity)
    out = np.zeros(PARAM_DIM)
    for name, value in _FACE[emotion].items():
        if name == "jaw":
            out[JAW_OPEN_INDEX] = value
        elif name == "neck_pitch":
            out[NECK_SLICE.start] = value
        elif name == "neck_roll":
            out[NECK_SLICE.start + 2] = value
        else:
            out[EXP_INDEX[name]] = value
    # Mouth corners also carry speech; keep the emotional share of their motion moderate.
    out[_MOUTH_EMOTION] *= 0.2
    return s * out


def voice_change(emotion: str, intensity: int) -> VoiceChange:
    """Voice changes of an emotion at an intensity (interpolated from neutral)."""
    emotion_index(emotion)
    s = intensity_scale(intensity)
    pitch, prange, rate, energy, breath = _VOICE[emotion]
    return VoiceChange(1 + s * (pitch - 1), 1 + s * (prange - 1), 1 + s * (rate - 1),
                       1 + s * (energy - 1), s * breath)
