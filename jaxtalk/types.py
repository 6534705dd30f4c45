"""Shape-annotated array aliases used across jaxtalk's public API (jaxtyping).

Dimension names are shared so that, under the jaxtyping runtime checker used in the test suite,
a function annotated with ``Params56`` in and ``Verts`` out checks that ``frames`` agrees.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, Shaped

__all__ = [
    "COMPUTE_DTYPES",
    "check_compute_dtype",
    "Array",
    "Bool",
    "Float",
    "Int",
    "PRNGKeyArray",
    "Shaped",
    "Params56",
    "Verts",
    "Landmarks",
    "Features",
    "Mask2D",
    "StreamLike",
    "PARAM_DIM",
    "EXP_DIM",
    "EXP_SLICE",
    "JAW_SLICE",
    "NECK_SLICE",
    "MOTION_FPS",
    "AUDIO_SAMPLE_RATE",
    "NUM_LANDMARKS",
]

# FLAME-like head vector in DualTalk's layout: [exp 50 | jaw 3 | neck 3] (axis-angle).
EXP_DIM = 50
PARAM_DIM = 56
EXP_SLICE = slice(0, 50)
JAW_SLICE = slice(50, 53)
NECK_SLICE = slice(53, 56)

MOTION_FPS = 25
AUDIO_SAMPLE_RATE = 16_000
NUM_LANDMARKS = 68

Params56 = Float[Array, "frames 56"]
Verts = Float[Array, "frames verts 3"]
Landmarks = Float[Array, "frames 68 3"]
Features = Float[Array, "frames dim"]
Mask2D = Bool[Array, "queries keys"]

# An input stream (JAX or NumPy, any shape) of a public entry point that validates the shape itself,
# naming the stream in its error (TIMAR's and the DualTalk baseline's conversation streams).
StreamLike = Shaped[Array, "..."] | Shaped[np.ndarray, "..."]


# The compute dtypes a model config accepts (``compute_dtype``; :mod:`jaxtalk.nn.precision` applies it).
COMPUTE_DTYPES = ("float32", "bfloat16")


def check_compute_dtype(name: str, owner: str = "config") -> None:
    """Raise ValueError unless ``name`` is one of :data:`COMPUTE_DTYPES`.

    Args:
        name: the setting's value.
        owner: the config's name for the message.
    """
    if name not in COMPUTE_DTYPES:
        raise ValueError(f"{owner}.compute_dtype must be one of {', '.join(COMPUTE_DTYPES)}, got {name!r}")
