"""SynthTalk's phone inventory: an acoustic recipe and a viseme target per phone.

Formant values are classic adult averages (Peterson & Barney style) for a reference vocal tract; a
speaker scales them by a vocal-tract factor. Viseme targets are offsets from the speaker's resting
face in the 56-d layout of ``jaxtalk.layout`` (expression units of order 1, jaw in radians).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from jaxtalk.layout import EXP_INDEX, JAW_OPEN_INDEX, PARAM_DIM

__all__ = [
    "PhoneRecipe",
    "PHONES",
    "PHONE_INDEX",
    "SILENCE",
    "VOWELS",
    "ONSETS",
    "CODAS",
    "recipe",
    "viseme_targets",
]


@dataclasses.dataclass(frozen=True)
class PhoneRecipe:
    """How one phone sounds and looks.

    Attributes:
        name: phone symbol.
        kind: "silence" | "vowel" | "stop" | "fricative" | "nasal" | "approximant".
        voiced: whether the glottal source is on.
        formants: resonance frequencies in Hz of the voiced part (reference vocal tract).
        bandwidths: their bandwidths in Hz.
        gain: amplitude of the voiced part relative to an open vowel.
        noise_band: (low, high) Hz of the frication / burst noise; None when there is none.
        noise_gain: amplitude of that noise.
        duration: typical duration in seconds at speaking rate 1.
        viseme: offsets from the resting face, by name in ``jaxtalk.layout.EXP_NAMES`` or "jaw".
    """

    name: str
    kind: str
    voiced: bool
    formants: tuple[float, ...] = ()
    bandwidths: tuple[float, ...] = ()
    gain: float = 0.0
    noise_band: tuple[float, float] | None = None
    noise_gain: float = 0.0
    duration: float = 0.08
    viseme: tuple[tuple[str, float], ...] = ()


_VOWEL_BW = (80.0, 100.0, 150.0)


def _v(name, f, gain, viseme, duration=0.11):
    return PhoneRecipe(name, "vowel", True, f, _VOWEL_BW, gain, None, 0.0, duration, viseme)


_RECIPES: tuple[PhoneRecipe, ...] = (
    PhoneRecipe("sil", "silence", False, duration=0.25),
    # Vowels: the jaw and lip shapes carry most of the visible speech signal.
    _v("a", (730.0, 1090.0, 2440.0), 1.0,
       (("jaw", 0.28), ("lip_part", 1.0), ("lower_lip_depress", 0.9), ("upper_lip_raise", 0.5),
        ("mouth_stretch", 0.3))),
    _v("e", (530.0, 1840.0, 2480.0), 0.9,
       (("jaw", 0.17), ("lip_spread", 1.2), ("lip_part", 0.8), ("lower_lip_depress", 0.4),
        ("mouth_stretch", 0.9), ("mouth_corner_up", 0.6))),
    _v("i", (280.0, 2250.0, 2900.0), 0.8,
       (("jaw", 0.07), ("lip_spread", 2.0), ("lip_part", 0.5), ("lip_tight", 0.4),
        ("mouth_stretch", 1.4), ("mouth_corner_up", 1.0))),
    _v("o", (570.0, 840.0, 2410.0), 0.95,
       (("jaw", 0.2), ("lip_round", 1.6), ("lip_funnel", 0.8), ("lip_part", 0.7),
        ("mouth_stretch", -0.6), ("mouth_corner_down", 0.4))),
    _v("u", (310.0, 870.0, 2240.0), 0.8,
       (("jaw", 0.09), ("lip_round", 2.2), ("lip_funnel", 1.0), ("lip_tight", 0.3),
        ("lip_part", 0.3), ("mouth_stretch", -0.9), ("mouth_corner_down", 0.8))),
    # Stops: closure then burst; the burst band tells the place of articulation apart.
    PhoneRecipe("p", "stop", False, (), (), 0.0, (500.0, 1500.0), 0.5, 0.09,
                (("lip_close", 2.2), ("jaw", 0.02), ("cheek_puff_l", 1.4), ("cheek_puff_r", 1.4),
                 ("lip_tight", 0.6), ("lip_part", -0.6))),
    PhoneRecipe("b", "stop", True, (250.0,), (120.0,), 0.12, (400.0, 1400.0), 0.35, 0.08,
                (("lip_close", 2.0), ("jaw", 0.03), ("cheek_puff_l", 1.0), ("cheek_puff_r", 1.0),
                 ("lip_tight", 0.4), ("lip_part", -0.6))),
    PhoneRecipe("m", "nasal", True, (250.0, 1100.0, 2300.0), (60.0, 200.0, 300.0), 0.45, None, 0.0,
                0.08, (("lip_close", 1.8), ("jaw", 0.02), ("lip_part", -0.6))),
    PhoneRecipe("f", "fricative", False, (), (), 0.0, (1500.0, 7500.0), 0.14, 0.1,
                (("lip_tuck", 2.0), ("jaw", 0.05), ("upper_lip_raise", 0.9),
                 ("lower_lip_depress", -0.5))),
    PhoneRecipe("v", "fricative", True, (300.0, 1200.0, 2300.0), (100.0, 150.0, 200.0), 0.3,
                (1500.0, 7500.0), 0.09, 0.08,
                (("lip_tuck", 1.8), ("jaw", 0.05), ("upper_lip_raise", 0.8))),
    PhoneRecipe("th", "fricative", False, (), (), 0.0, (3000.0, 7500.0), 0.1, 0.1,
                (("jaw", 0.1), ("lip_part", 0.6), ("lip_tight", 0.3), ("lip_spread", 0.3))),
    PhoneRecipe("t", "stop", False, (), (), 0.0, (3000.0, 7000.0), 0.5, 0.08,
                (("jaw", 0.09), ("lip_tight", 0.9), ("lip_part", 0.4), ("lip_spread", 0.3))),
    PhoneRecipe("d", "stop", True, (250.0,), (120.0,), 0.12, (2500.0, 6000.0), 0.35, 0.07,
                (("jaw", 0.11), ("lip_tight", 0.7), ("lip_part", 0.4), ("lip_spread", 0.3))),
    PhoneRecipe("s", "fricative", False, (), (), 0.0, (4500.0, 7800.0), 0.45, 0.11,
                (("jaw", 0.05), ("lip_spread", 1.0), ("lip_tight", 1.2), ("lip_part", 0.3),
                 ("mouth_stretch", 0.4))),
    PhoneRecipe("z", "fricative", True, (280.0, 1700.0, 2600.0), (100.0, 150.0, 200.0), 0.25,
                (4500.0, 7800.0), 0.3, 0.09,
                (("jaw", 0.06), ("lip_spread", 0.9), ("lip_tight", 1.0), ("lip_part", 0.3),
                 ("mouth_stretch", 0.3))),
    PhoneRecipe("n", "nasal", True, (250.0, 1600.0, 2600.0), (60.0, 200.0, 300.0), 0.45, None, 0.0,
                0.07, (("jaw", 0.09), ("lip_tight", 0.5), ("lip_part", 0.4))),
    PhoneRecipe("l", "approximant", True, (360.0, 1300.0, 2700.0), (80.0, 120.0, 200.0), 0.6, None,
                0.0, 0.07, (("jaw", 0.13), ("lip_part", 0.6), ("upper_lip_raise", 0.4))),
    PhoneRecipe("k", "stop", False, (), (), 0.0, (1500.0, 3000.0), 0.5, 0.09,
                (("jaw", 0.13), ("lip_part", 0.5), ("mouth_stretch", 0.2))),
    PhoneRecipe("g", "stop", True, (250.0,), (120.0,), 0.12, (1200.0, 2600.0), 0.35, 0.08,
                (("jaw", 0.13), ("lip_part", 0.5))),
    PhoneRecipe("sh", "fricative", False, (), (), 0.0, (2000.0, 5000.0), 0.45, 0.11,
                (("jaw", 0.07), ("lip_funnel", 2.0), ("lip_round", 1.0), ("upper_lip_raise", 0.9),
                 ("lip_part", 0.4))),
    PhoneRecipe("w", "approximant", True, (300.0, 650.0, 2200.0), (80.0, 100.0, 200.0), 0.6, None,
                0.0, 0.07, (("jaw", 0.05), ("lip_round", 2.2), ("lip_funnel", 0.6),
                            ("lip_tight", 0.5))),
    PhoneRecipe("r", "approximant", True, (350.0, 1250.0, 1650.0), (80.0, 120.0, 150.0), 0.6, None,
                0.0, 0.07, (("jaw", 0.09), ("lip_round", 0.9), ("lip_funnel", 0.9))),
)

PHONES: tuple[str, ...] = tuple(r.name for r in _RECIPES)
PHONE_INDEX: dict[str, int] = {p: i for i, p in enumerate(PHONES)}
SILENCE: int = PHONE_INDEX["sil"]
VOWELS: np.ndarray = np.array([PHONE_INDEX[p] for p in "aeiou"], dtype=np.int32)
# Simple CV(C) phonotactics: any consonant may open a syllable; glides and /h/-like sounds do not
# close one.
ONSETS: np.ndarray = np.array(
    [i for i, r in enumerate(_RECIPES) if r.kind not in ("silence", "vowel")], dtype=np.int32
)
CODAS: np.ndarray = np.array(
    [PHONE_INDEX[p] for p in ("p", "b", "m", "f", "v", "th", "t", "d", "s", "z", "n", "l", "k", "g",
                              "sh")],
    dtype=np.int32,
)
for _a in (VOWELS, ONSETS, CODAS):
    _a.setflags(write=False)


def recipe(phone: int | str) -> PhoneRecipe:
    """The recipe of a phone given by index into ``PHONES`` or by symbol.

    Raises:
        ValueError: for an unknown phone.
    """
    if isinstance(phone, str):
        if phone not in PHONE_INDEX:
            raise ValueError(f"unknown phone {phone!r}; known: {PHONES}")
        return _RECIPES[PHONE_INDEX[phone]]
    if not 0 <= int(phone) < len(_RECIPES):
        raise ValueError(f"phone index {phone} out of range [0, {len(_RECIPES)})")
    return _RECIPES[int(phone)]


@functools.cache
def viseme_targets() -> np.ndarray:
    """Viseme offsets of every phone as a read-only ``(num_phones, 56)`` float64 table."""
    table = np.zeros((len(_RECIPES), PARAM_DIM))
    for i, r in enumerate(_RECIPES):
        for name, value in r.viseme:
            table[i, JAW_OPEN_INDEX if name == "jaw" else EXP_INDEX[name]] = value
    table.setflags(write=False)
    return table
