"""FreeTalk's affect labels: emotion vocabularies (EmoVOCA's 11 categories plus neutral, MEAD's 8) and
intensity checks.

ATS is conditioned on a discrete emotion category ``e`` and an intensity ``i``. The vocabulary is a
setting of the model (``ATSConfig.emotions``): row ``e`` of the emotion table is the ``e``-th name of
the vocabulary the model was trained with, so a MEAD model and an EmoVOCA model each know their own
labels. Intensity enters the
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

__all__ = ["EMOTIONS", "MEAD_EMOTIONS", "VOCABULARIES", "NUM_EMOTIONS", "NEUTRAL", "emotion_ids",
           "parse_vocabulary", "check_intensity"]

# Order is part of the trained parameters (row e of the emotion table): never reorder. It matches
# jaxtalk.data.synthtalk.EMOTIONS (a test checks this), so corpus labels map one to one.
EMOTIONS: tuple[str, ...] = (
    "neutral", "afraid", "ashamed", "angry", "disgust", "happy", "sad", "drunk", "ill",
    "suspicious", "pleased", "upset",
)
NUM_EMOTIONS = len(EMOTIONS)
NEUTRAL = 0
# MEAD's eight (Wang et al. 2020), neutral first like every vocabulary here.
MEAD_EMOTIONS: tuple[str, ...] = (
    "neutral", "angry", "contempt", "disgusted", "fear", "happy", "sad", "surprised",
)
# Named vocabularies (``--set emotions=mead``).
VOCABULARIES: dict[str, tuple[str, ...]] = {"emovoca": EMOTIONS, "mead": MEAD_EMOTIONS}


def parse_vocabulary(value: str | tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """An emotion vocabulary from a name (``emovoca``, ``mead``), a comma-separated list or a sequence.

    Raises:
        ValueError: fewer than one name, repeated or empty names, or a first name other than
            ``neutral`` (id 0 is the neutral face everywhere: data without labels, the baseline).
    """
    if isinstance(value, str):
        names = VOCABULARIES.get(value.strip().lower()) or tuple(n.strip() for n in value.split(","))
    else:
        names = tuple(str(n) for n in value)
    if not names or any(not n for n in names):
        raise ValueError(f"an emotion vocabulary needs non-empty names, got {value!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"emotion vocabulary has repeated names: {names}")
    if names[0] != "neutral":
        raise ValueError(f"an emotion vocabulary starts with 'neutral' (id {NEUTRAL}), got {names}")
    return names


def emotion_ids(
    emotions: str | Sequence[str] | Any, vocabulary: Sequence[str] = EMOTIONS
) -> Int[np.ndarray, " batch"]:
    """Map emotion names (or already integer ids) to ids into ``vocabulary``.

    Args:
        emotions: one name, a sequence of names, or an integer array of ids.
        vocabulary: the model's emotion names (default EmoVOCA's, :data:`EMOTIONS`).

    Returns:
        ``(B,)`` int32 ids (``B = 1`` for a single name).

    Raises:
        ValueError: an unknown name (naming it and the known ones) or an id outside
            ``[0, len(vocabulary))``.
    """
    vocabulary = tuple(vocabulary)
    if isinstance(emotions, str):
        emotions = [emotions]
    arr = np.asarray(emotions)
    if arr.dtype.kind in "US":
        unknown = sorted({str(e) for e in arr.ravel() if str(e) not in vocabulary})
        if unknown:
            raise ValueError(f"unknown emotion name(s) {unknown}; this model knows: {', '.join(vocabulary)}")
        arr = np.asarray([vocabulary.index(str(e)) for e in arr.ravel()]).reshape(arr.shape)
    elif arr.dtype.kind not in "iu":
        raise ValueError(f"emotions must be names or integer ids, got dtype {arr.dtype}")
    if arr.ndim != 1:
        raise ValueError(f"emotions must be one name or a 1-D sequence, got shape {arr.shape}")
    if arr.size and (arr.min() < 0 or arr.max() >= len(vocabulary)):
        raise ValueError(f"emotion ids must lie in [0, {len(vocabulary)}), got {arr.tolist()}")
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
