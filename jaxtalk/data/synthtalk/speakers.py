"""Speakers and their styles.

A style fixes everything that is the same across one speaker's clips: voice (f0, vocal-tract length),
articulation amplitude and smoothing, speaking rate, head sway, how they react as listeners, and a
resting face. Training speakers draw the scalar style knobs from the "train" ranges below;
out-of-distribution speakers draw them from bands strictly outside those ranges. A speaker either
speaks through SynthTalk's source-filter synthesiser (``espeak`` is None) or with a fixed eSpeak NG
voice (``EspeakVoice``, drawn by ``espeak_voice.sample_voice``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxtalk.layout import GROUPS, JAW_OPEN_INDEX, NECK_SLICE, PARAM_DIM

__all__ = ["SpeakerStyle", "EspeakVoice", "STYLE_RANGES", "DYADIC_RANGES", "OOD_KNOBS", "sample_style"]

# (low, high) of each scalar knob for in-distribution speakers.
STYLE_RANGES: dict[str, tuple[float, float]] = {
    "articulation": (0.8, 1.2),     # scale of viseme offsets
    "smoothing": (0.018, 0.032),    # s, time constant of the coarticulation spring
    "rate": (0.85, 1.15),           # speaking-rate factor (higher = faster)
    "sway_amp": (0.02, 0.045),      # rad, head sway amplitude
    "sway_freq": (0.15, 0.35),      # Hz
    "lead": (0.04, 0.08),           # s, motion leads sound by this much
    "f0": (95.0, 230.0),            # Hz, base pitch
    "brow_gain": (0.6, 1.2),        # brow raise per pitch accent
    "nod_gain": (0.6, 1.4),         # nod per accent / per reaction
    "blink_rate": (0.2, 0.5),       # blinks per second (Poisson)
    "react_lag": (0.3, 0.8),        # s, listener nod after the other's phrase ends
    "mirror_gain": (0.3, 0.7),      # fraction of the other's emotion mirrored
    "mirror_lag": (0.6, 1.2),       # s
}
# How a speaker takes part in long-range dyadic behaviour (``dyadic.py``), drawn after every other
# knob so that adding them left each speaker's other draws as they were. Not in ``knobs()``.
DYADIC_RANGES: dict[str, tuple[float, float]] = {
    "mimic_lag": (2.0, 4.0),        # s, a head gesture of the partner is repeated this much later
    "mimic_gain": (0.5, 0.8),       # fraction of the partner's head movement repeated
}
# Knobs pushed outside their training range for out-of-distribution speakers: (low band, high band).
OOD_KNOBS: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "articulation": ((0.5, 0.65), (1.35, 1.55)),
    "smoothing": ((0.010, 0.014), (0.040, 0.05)),
    "rate": ((0.65, 0.75), (1.25, 1.4)),
    "sway_amp": ((0.008, 0.013), (0.06, 0.075)),
    "sway_freq": ((0.06, 0.1), (0.45, 0.6)),
}


@dataclasses.dataclass(frozen=True)
class EspeakVoice:
    """A speaker's eSpeak NG voice: the same in every clip of that speaker.

    Attributes:
        language: eSpeak language ("en-us", "de", ...).
        variant: eSpeak voice variant ("m3", "f2", ...).
        wpm: speaking rate in words per minute with a neutral emotion.
        pitch: eSpeak base pitch (0-100) with a neutral emotion.
        pitch_range: eSpeak pitch range (0-100) with a neutral emotion at arousal 1.
    """

    language: str
    variant: str
    wpm: float
    pitch: float
    pitch_range: float

    @property
    def name(self) -> str:
        """eSpeak's voice name, ``language+variant``."""
        return f"{self.language}+{self.variant}"


@dataclasses.dataclass(frozen=True)
class SpeakerStyle:
    """One speaker's style (see ``STYLE_RANGES`` for the meaning and range of each knob).

    Attributes:
        formant_scale: vocal-tract factor multiplying every formant (shorter tract = higher).
        jaw_asym: sideways jaw rotation per radian of opening.
        rest: resting 56-d head vector, shape ``(56,)``.
        espeak: the speaker's eSpeak voice, or None for a source-filter speaker.
    """

    articulation: float
    smoothing: float
    rate: float
    sway_amp: float
    sway_freq: float
    lead: float
    f0: float
    brow_gain: float
    nod_gain: float
    blink_rate: float
    react_lag: float
    mirror_gain: float
    mirror_lag: float
    formant_scale: float
    jaw_asym: float
    mimic_lag: float
    mimic_gain: float
    rest: np.ndarray = dataclasses.field(compare=False, repr=False)
    espeak: EspeakVoice | None = None

    def knobs(self) -> np.ndarray:
        """The scalar knobs of ``STYLE_RANGES`` in that order, shape ``(13,)`` float64."""
        return np.array([getattr(self, k) for k in STYLE_RANGES], dtype=np.float64)

    def to_dict(self) -> dict[str, float | list[float] | dict]:
        """JSON-friendly form (``rest`` as a list; ``espeak`` as a dict, only for an eSpeak speaker)."""
        out: dict[str, float | list[float] | dict] = {
            f.name: float(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name not in ("rest", "espeak")
        }
        out["rest"] = [float(x) for x in self.rest]
        if self.espeak is not None:
            out["espeak"] = dataclasses.asdict(self.espeak)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> SpeakerStyle:
        """Inverse of ``to_dict``."""
        kw = {k: float(v) for k, v in d.items() if k not in ("rest", "espeak")}
        espeak = EspeakVoice(**d["espeak"]) if d.get("espeak") is not None else None
        return cls(**kw, rest=np.asarray(d["rest"], dtype=np.float64), espeak=espeak)


def _resting_face(rng: np.random.Generator) -> np.ndarray:
    rest = np.zeros(PARAM_DIM)
    # Named components get a mild personal offset; the smooth residual modes carry most of a
    # person's resting shape (as FLAME's higher PCA components do). Eyelids rest open.
    rest[:28] = rng.normal(0.0, 0.25, 28)
    # Lips at rest differ less between people than brows or cheeks do.
    rest[GROUPS["mouth_exp"]] *= 0.2
    rest[GROUPS["blink"]] = rng.normal(0.0, 0.05, 2)
    rest[GROUPS["residual"]] = rng.normal(0.0, 0.5, len(GROUPS["residual"]))
    rest[JAW_OPEN_INDEX] = rng.uniform(0.01, 0.04)
    rest[NECK_SLICE] = rng.normal(0.0, 0.04, 3)
    return rest


def sample_style(rng: np.random.Generator, *, ood: bool = False) -> SpeakerStyle:
    """Draw a speaker style.

    Args:
        rng: NumPy generator (consumed).
        ood: draw the ``OOD_KNOBS`` from outside their training range (each knob independently
            below or above it).

    Returns:
        A ``SpeakerStyle``.
    """
    knobs = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in STYLE_RANGES.items()}
    if ood:
        for k, bands in OOD_KNOBS.items():
            lo, hi = bands[int(rng.integers(2))]
            knobs[k] = float(rng.uniform(lo, hi))
    # Higher voices come from shorter vocal tracts: tie the formant scale to f0 plus a personal part.
    rel = (knobs["f0"] - 95.0) / (230.0 - 95.0)
    formant_scale = float(0.95 + 0.12 * rel + rng.uniform(-0.02, 0.02))
    jaw_asym = float(rng.uniform(-0.08, 0.08))
    rest = _resting_face(rng)
    dyadic = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in DYADIC_RANGES.items()}
    return SpeakerStyle(**knobs, formant_scale=formant_scale, jaw_asym=jaw_asym, **dyadic, rest=rest)
