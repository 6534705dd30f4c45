"""Fitting with optimistix: face-model parameters from landmarks or vertices.

``fit_landmarks`` / ``fit_vertices`` solve for the 56-d head vector ``[exp 50 | jaw 3 | neck 3]``
per frame or jointly over a sequence (Levenberg-Marquardt or Gauss-Newton), with temporal smoothness,
an L2 prior, warm starts, topology variants, and failures that raise instead of returning a wrong fit.
``invert_style`` / ``invert_intensity`` recover a TokTalk style vector or a FreeTalk emotion intensity
from a target clip by optimistix minimisation through the samplers (fixed noise).
"""

from __future__ import annotations

from jaxtalk.fit.banded import FrameBandedSolver, block_tridiagonal_solve
from jaxtalk.fit.face_fit import (
    FitConfig,
    FitFailedError,
    FitResult,
    fit_landmarks,
    fit_vertices,
    identifiable_params,
    result_name,
)
from jaxtalk.fit.inversion import (
    InversionFailedError,
    InversionResult,
    ats_noise,
    intensity_loss,
    invert_intensity,
    invert_style,
    sample_ats_from_noise,
    style_loss,
)

__all__ = [
    "FitConfig",
    "FitFailedError",
    "FitResult",
    "FrameBandedSolver",
    "block_tridiagonal_solve",
    "fit_landmarks",
    "fit_vertices",
    "identifiable_params",
    "result_name",
    "InversionFailedError",
    "InversionResult",
    "ats_noise",
    "intensity_loss",
    "invert_intensity",
    "invert_style",
    "sample_ats_from_noise",
    "style_loss",
]
