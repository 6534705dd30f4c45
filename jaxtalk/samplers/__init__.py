"""Samplers as pure functions: time grids and DDPM tables (``schedules``), the Euler flow-matching
sampler (``flow``) and DDPM/DDIM (``diffusion``).

Each sampler is ``init`` + a pure ``step`` scanned with ``jax.lax.scan`` over a time grid (an array)
and pre-split PRNG keys; the model enters as ``apply_fn(x, t, cond)``.
"""

from __future__ import annotations

from jaxtalk.samplers.diffusion import ClipGroup, sample_ddim, sample_ddpm
from jaxtalk.samplers.flow import as_model, guided_apply, sample_euler
from jaxtalk.samplers.schedules import (
    DiffusionSchedule,
    RespacedSchedule,
    cosine_grid,
    make_schedule,
    respace,
    space_timesteps,
    uniform_grid,
)

__all__ = [
    "ClipGroup",
    "as_model",
    "DiffusionSchedule",
    "RespacedSchedule",
    "cosine_grid",
    "guided_apply",
    "make_schedule",
    "respace",
    "sample_ddim",
    "sample_ddpm",
    "sample_euler",
    "space_timesteps",
    "uniform_grid",
]
