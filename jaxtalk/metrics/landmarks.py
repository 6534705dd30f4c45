"""FreeTalk ATS's landmark columns: lip error over the mouth landmarks, mean landmark error, jitter.

One function, shared by ``jaxtalk eval`` and the ATS run's sampled validation, so the number a run
selects its checkpoint by is the number a user later measures.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Float

from jaxtalk.metrics.vertex import jitter, lve, mve

__all__ = ["MOUTH_LANDMARKS", "landmark_metrics"]

# The mouth in the 68-point (iBUG / dlib) layout: outer lip 48-59, inner lip 60-67.
MOUTH_LANDMARKS = np.arange(48, 68)


def landmark_metrics(pred: Float[np.ndarray, "frames 68 3"], gt: Float[np.ndarray, "frames 68 3"]) -> dict[str, float]:
    """ATS's columns for one ``(T, 68, 3)`` landmark displacement track (metres) against the truth.

    Returns:
        ``{"LVE_mm2"`` (max over the mouth landmarks 48-67 of the squared error per frame, averaged),
        ``"LE_mm"`` (mean landmark error), ``"jitter_mm"`` (mean landmark acceleration)}``.
    """
    return {"LVE_mm2": float(lve(pred, gt, MOUTH_LANDMARKS)) * 1e6, "LE_mm": float(mve(pred, gt)) * 1e3,
            "jitter_mm": float(jitter(pred)) * 1e3}
