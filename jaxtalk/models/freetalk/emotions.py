"""FreeTalk's affect labels: the 11 EmoVOCA emotion categories plus neutral, and intensity checks.

ATS is conditioned on a discrete emotion category ``e`` and an intensity ``i``. Intensity enters the
model as a traced float (changing it never recompiles) that must lie in ``[1, num_intensities]``:
integer values are the dataset's discrete levels (MEAD has 3; neutral-only data uses 1, as in the
paper); the embedding is affine in the intensity (an emotion vector plus the intensity times an
emotion direction, see ``ats._AffectEmbedding``), so values in between are well defined.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from jaxtalk.types import Array, Float, Int

__all__ = ["EMOTIONS", "NUM_EMOTIONS", "NEUTRAL", "emotion_ids", "check_intensity"]

# Order is part of the trained parameters (row e of the emotion table): never reorder. It matches
# jaxtalk.data.synthtalk.EMOTIONS (a test checks this), so corpus labels map one to one.
EMOTIONS: tuple[str, ...] = (
    "neutral", "afraid", "ashamed", "angry", "disgust", "happy", "sad", "drunk", "ill",
    "suspicious", "pleased", "upset",
)
NUM_EMOTIONS = len(EMOTIONS)
NEUTRAL = 0


def emotion_ids(emotions: str | Sequence[str] | Any) -> Int[np.ndarray, " batch"]:
    """Map emotion names (or already integer ids) to ids into :data:`EMOTIONS`.

    Args:
        emotions: one name, a sequence of names, or an integer array of ids.

    Returns:
        ``(B,)`` int32 ids (``B = 1`` for a single name).

    Raises:
        ValueError: an unknown name (naming it and the known ones) or an id outside
            ``[0, NUM_EMOTIONS)``.
    """
    if isinstance(emotions, str):
        emotions = [emotions]
    arr = np.asarray(emotions)
    if arr.dtype.kind in "US":
        unknown = sorted({str(e) for e in arr.ravel() if str(e) not in EMOTIONS})
        if unknown:
            raise ValueError(f"unknown emotion name(s) {unknown}; known: {EMOTIONS}")
        arr = np.asarray([EMOTIONS.index(str(e)) for e in arr.ravel()]).reshape(arr.shape)
    elif arr.dtype.kind not in "iu":
        raise ValueError(f"emotions must be names or integer ids, got dtype {arr.dtype}")
    if arr.ndim != 1:
        raise ValueError(f"emotions must be one name or a 1-D sequence, got shape {arr.shape}")
    if arr.size and (arr.min() < 0 or arr.max() >= NUM_EMOTIONS):
        raise ValueError(f"emotion ids must lie in [0, {NUM_EMOTIONS}), got {arr.tolist()}")
    return arr.astype(np.int32)


def check_intensity(
    intensity: Float[Array, " batch"] | Any, num_intensities: int, batch: int
) -> Float[Array, " batch"] | Any:
    """Validate emotion intensities: finite and in ``[1, num_intensities]``; broadcast to the batch.

    Inside someone else's ``jit`` (a traced value) the range cannot be inspected and the value is
    returned as is; at the API boundary (a concrete value) it is checked.

    Args:
        intensity: a scalar or ``(B,)`` intensities (float or int).
        num_intensities: the highest level (static).
        batch: B.

    Returns:
        ``(B,)`` float32 intensities.

    Raises:
        ValueError: NaN/inf, a value outside ``[1, num_intensities]``, or a shape that is neither
            scalar nor ``(B,)``.
    """
    if isinstance(intensity, jax.core.Tracer):
        if intensity.ndim not in (0, 1):
            raise ValueError(f"intensity must be a scalar or (batch,), got shape {intensity.shape}")
        return jax.numpy.broadcast_to(intensity.astype(jax.numpy.float32), (batch,))
    arr = np.asarray(intensity, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full((batch,), float(arr))
    if arr.shape != (batch,):
        raise ValueError(f"intensity must be a scalar or shape ({batch},), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"intensity contains NaN or inf: {arr.tolist()}")
    if arr.min() < 1 or arr.max() > num_intensities:
        raise ValueError(
            f"emotion intensity must lie in [1, {num_intensities}], got {arr.tolist()}"
        )
    return jax.numpy.asarray(arr, dtype=jax.numpy.float32)
