"""Fitting with optimistix: face-model parameters from landmarks or vertices.

``fit_landmarks`` / ``fit_vertices`` solve for the 56-d head vector ``[exp 50 | jaw 3 | neck 3]``
per frame or jointly over a sequence (Levenberg-Marquardt or Gauss-Newton), with temporal smoothness,
an L2 prior, warm starts, topology variants, and failures that raise instead of returning a wrong fit.
:mod:`jaxtalk.fit.inversion` is the solve behind inverting a condition through a sampler (fixed noise);
the inversions themselves live with their models (``jaxtalk.models.toktalk.inversion.invert_style``,
``jaxtalk.models.freetalk.inversion.invert_intensity``), a layer above this one.
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
from jaxtalk.fit.inversion import InversionFailedError, InversionResult

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
]
