"""Semantic layout of the 56-d head vector ``[exp 50 | jaw 3 | neck 3]`` for the built-in face.

The real FLAME expression space is a PCA basis with no fixed meaning per dimension. jaxtalk's built-in
procedural face gives its 50 expression components named, localised meanings so that SynthTalk can
drive them by rule and tests can ask region-specific questions (does audio predict the mouth? does it
fail to predict blinks?). The FLAME loader keeps the real model's basis, where these names do not apply.

Every index here is into the 56-d vector.
"""

from __future__ import annotations

import numpy as np

from jaxtalk.types import EXP_SLICE, JAW_SLICE, NECK_SLICE, PARAM_DIM

__all__ = [
    "EXP_NAMES",
    "EXP_INDEX",
    "GROUPS",
    "group_indices",
    "PARAM_DIM",
    "EXP_SLICE",
    "JAW_SLICE",
    "NECK_SLICE",
]

# Named expression components of the built-in face, in order. The last 22 are smooth, non-local
# "residual" modes (like FLAME's higher PCA components): speakers' resting expression and slow idle
# drift live there.
_NAMED = [
    # mouth (driven by visemes: audio-predictable)
    "lip_close",        # 0  bilabial press (p, b, m)
    "lip_round",        # 1  pucker / rounding (o, u, w)
    "lip_spread",       # 2  lip width (i, e)
    "lip_funnel",       # 3  funnel (sh)
    "upper_lip_raise",  # 4
    "lower_lip_depress",  # 5
    "lip_part",         # 6  lip separation beyond what the jaw gives
    "lip_tuck",         # 7  lower lip under upper teeth (f, v)
    "lip_tight",        # 8  tension on alveolars / dentals
    "mouth_corner_up",  # 9  smile corners (emotion)
    "mouth_corner_down",  # 10 frown corners (emotion)
    "mouth_stretch",    # 11 horizontal stretch (fear, effort)
    # brows
    "brow_inner_up_l",  # 12
    "brow_inner_up_r",  # 13
    "brow_outer_up_l",  # 14
    "brow_outer_up_r",  # 15
    "brow_down_l",      # 16
    "brow_down_r",      # 17
    # eyes
    "blink_l",          # 18 stochastic: no model can predict these from audio
    "blink_r",          # 19
    "eye_wide_l",       # 20
    "eye_wide_r",       # 21
    # cheeks and nose
    "cheek_raise_l",    # 22
    "cheek_raise_r",    # 23
    "cheek_puff_l",     # 24
    "cheek_puff_r",     # 25
    "nose_wrinkle_l",   # 26
    "nose_wrinkle_r",   # 27
]
EXP_NAMES: tuple[str, ...] = tuple(_NAMED + [f"residual_{k:02d}" for k in range(50 - len(_NAMED))])
assert len(EXP_NAMES) == 50
EXP_INDEX: dict[str, int] = {name: i for i, name in enumerate(EXP_NAMES)}

# Groups of the 56-d vector. "mouth" includes the jaw rotation; "blink" is the unpredictable part.
GROUPS: dict[str, np.ndarray] = {
    "exp": np.arange(0, 50),
    "jaw": np.arange(50, 53),
    "neck": np.arange(53, 56),
    "mouth_exp": np.arange(0, 12),
    "mouth": np.concatenate([np.arange(0, 12), np.arange(50, 53)]),
    "brow": np.arange(12, 18),
    "blink": np.arange(18, 20),
    "eye": np.arange(18, 22),
    "cheek": np.arange(22, 26),
    "nose": np.arange(26, 28),
    "upper_face": np.arange(12, 28),
    "residual": np.arange(28, 50),
}
for _g in GROUPS.values():
    _g.setflags(write=False)

# Jaw rotation: axis-angle about the x axis (pitch) opens the mouth; index 50 is that component.
JAW_OPEN_INDEX = 50


def group_indices(name: str) -> np.ndarray:
    """Indices into the 56-d vector of a named group (see ``GROUPS``).

    Raises:
        KeyError: with the list of known names, for an unknown group.
    """
    try:
        return GROUPS[name]
    except KeyError:
        raise KeyError(f"unknown parameter group {name!r}; known: {sorted(GROUPS)}") from None
