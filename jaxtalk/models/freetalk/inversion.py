"""Inversion of FreeTalk's emotion intensity through the ATS sampler (:mod:`jaxtalk.fit.inversion` holds
the shared solve).

:func:`invert_intensity` finds the continuous emotion intensity whose ATS sample (deterministic DDIM,
``eta = 0``, :func:`sample_ats_from_noise`) matches a target landmark-displacement clip. ATS embeds a
float intensity affinely (emotion vector + intensity-scaled direction), so the intensity is
differentiable as it is (no hook needed). The model clips intensities to ``[1, L]`` (flat loss
outside), so the solver works on a latent ``z`` reflected into the range; the sampled clip is still a
non-convex function of the intensity through the transformer, so by default the solver runs once from
the midpoint of each stretch between levels and keeps the best. The objective is the per-example mean
squared error in the model's units (``displacement_scale`` x metres, or standardised units for a
model of ATS's recipe).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.fit.face_fit import _check_finite, _float_array
from jaxtalk.fit.inversion import (  # the solve and checks every inversion shares
    InversionResult,
    _check_observed_finite,
    _check_solver_args,
    _compute_dtype,
    _finish,
    _frame_weights,
    _per_example,
    _solve,
    _tolerances,
)
from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.ats import ATSCondition
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.types import Array, Float, PRNGKeyArray

__all__ = ["ats_noise", "sample_ats_from_noise", "intensity_loss", "invert_intensity"]

PyTree = Any
ArrayLike = Array | np.ndarray


def _resolve_steps(config: ATSConfig, sample_steps: Any) -> int:
    steps = config.sample_steps if sample_steps is None else sample_steps
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 1 <= steps <= config.num_timesteps:
        raise ValueError(f"sample_steps must be an integer in [1, {config.num_timesteps}], got {sample_steps!r}")
    return int(steps)


def ats_noise(config: ATSConfig, cond: ATSCondition, key: PRNGKeyArray) -> Float[Array, "batch frames motion"]:
    """The starting noise :func:`~jaxtalk.models.freetalk.ats.sample` draws from ``key``.

    With it, :func:`sample_ats_from_noise` reproduces ``ats.sample(..., key, eta=0)`` exactly.

    Args:
        config: ATS configuration.
        cond: the condition (its ``mask`` sets the batch and frame count).
        key: the key that would be given to ``ats.sample``.

    Returns:
        ``(B, T, 3N)`` standard normal noise (model units).
    """
    b, frames = cond.mask.shape
    k_noise, _ = jax.random.split(key)
    return jax.random.normal(k_noise, (b, frames, config.motion_dim))


def sample_ats_from_noise(
    params: PyTree,
    config: ATSConfig,
    cond: ATSCondition,
    noise: Float[ArrayLike, "batch frames motion"],
    *,
    sample_steps: int | None = None,
    remat: bool = False,
) -> Float[Array, "batch frames landmarks 3"]:
    """Deterministic DDIM sampling of ATS from explicit starting noise (``ats.sample`` with ``eta = 0``).

    ``ats.sample(params, config, cond, None, noise=noise, remat=remat)``: the noise is an argument
    (held fixed and differentiable), with ``jax.checkpoint`` on the DDIM step available.

    Args:
        params: ATS variables.
        config: ATS configuration.
        cond: from :func:`~jaxtalk.models.freetalk.ats.make_condition`.
        noise: ``(B, T, 3N)`` starting noise (model units), e.g. :func:`ats_noise`.
        sample_steps: DDIM steps (static; default ``config.sample_steps``).
        remat: checkpoint each DDIM step.

    Returns:
        ``(B, T, N, 3)`` displacements in ``ats.sample``'s units (model units / ``displacement_scale``).

    Raises:
        ValueError: a bad step count, or noise of the wrong shape or with NaN/inf.
    """
    return ats.sample(params, config, cond, None, sample_steps=sample_steps, noise=noise, remat=remat)


def _intensity_data(intensity, params, cond, target, noise, *, config, sample_steps, remat):
    """Weighted residuals ``(B, T, 3N)`` (model units) whose per-example sum of squares is the MSE."""
    b, frames = cond.mask.shape
    x = ats.sample(params, config, cond._replace(intensity=intensity), None, sample_steps=sample_steps, noise=noise,
                   remat=remat).reshape(b, frames, -1)
    w = _frame_weights(cond.mask, config.motion_dim, x.dtype)
    return config.displacement_scale * (x - target.reshape(b, frames, -1)) * w[..., None]


@functools.partial(jax.jit, static_argnames=("config", "sample_steps", "remat"))
def _intensity_loss(params, cond, target, noise, intensity, *, config, sample_steps, remat):
    return _per_example(_intensity_data(intensity, params, cond, target, noise, config=config,
                                        sample_steps=sample_steps, remat=remat))


def intensity_loss(
    params: PyTree,
    config: ATSConfig,
    cond: ATSCondition,
    target: Float[ArrayLike, "batch frames landmarks 3"],
    noise: Float[ArrayLike, "batch frames motion"],
    intensity: Float[ArrayLike, " batch"],
    *,
    sample_steps: int | None = None,
    remat: bool = True,
) -> Float[Array, " batch"]:
    """Per-example MSE (model units) between the ATS sample for ``intensity`` (fixed noise) and a target.

    The data term :func:`invert_intensity` minimises (the same code path), differentiable in
    ``intensity``; jitted (``config``, ``sample_steps``, ``remat`` static).

    Args:
        params, config: the ATS model.
        cond: condition (audio, emotion, masks; its intensity is replaced by ``intensity``).
        target: ``(B, T, N, 3)`` target displacements in ``ats.sample``'s units.
        noise: ``(B, T, 3N)`` fixed starting noise.
        intensity: ``(B,)`` intensities (meaningful in ``[1, num_intensities]``; ATS clips them).
        sample_steps: DDIM steps (default ``config.sample_steps``).
        remat: checkpoint each DDIM step.

    Returns:
        ``(B,)`` mean over real frames and the ``3N`` coordinates of the squared error, in model units
        (``displacement_scale`` x ``ats.sample``'s units).

    Raises:
        ValueError: a bad step count.
    """
    steps = _resolve_steps(config, sample_steps)
    return _intensity_loss(params, cond, target, noise, intensity, config=config, sample_steps=steps,
                           remat=bool(remat))


# ATS clips intensities to [1, L] (flat loss outside, where a solver would stop on a zero gradient), so
# the solver works on an unconstrained latent z reflected into the range: u = z mod 2,
# intensity = 1 + (L - 1) (1 - |1 - u|). Every z maps inside; an interior minimum has no spurious
# stationary copy on a bound (the slope in z is +-1 times the slope in intensity); and a minimum ON a
# bound is a kink in z where the residual is linear on both sides, so a Gauss-Newton step lands on it
# (a smooth map such as a sigmoid would put it at infinity, a cosine would make convergence linear).
def _intensity_from_latent(z: Array, levels: int) -> Array:
    return 1.0 + (levels - 1.0) * (1.0 - jnp.abs(1.0 - jnp.mod(z, 2.0)))


def _latent_from_intensity(intensity: np.ndarray, levels: int) -> np.ndarray:
    # |.| has a zero derivative at its kink: start 1 % of the range inside rather than on a bound.
    return np.clip((intensity - 1.0) / (levels - 1.0), 0.01, 0.99)


def _intensity_residuals(z, args, *, config, sample_steps, remat):
    params, cond, target, noise = args
    intensity = _intensity_from_latent(z, config.num_intensities)
    data = _intensity_data(intensity, params, cond, target, noise, config=config, sample_steps=sample_steps, remat=remat)
    return data, _per_example(data)


@functools.partial(
    jax.jit, static_argnames=("config", "sample_steps", "solver", "rtol", "atol", "max_steps", "remat")
)
def _invert_intensity_core(params, cond, target, noise, z0, *, config, sample_steps, solver, rtol, atol, max_steps,
                           remat):
    fn = functools.partial(_intensity_residuals, config=config, sample_steps=sample_steps, remat=remat)

    def one(c, tgt, nz, z_init):  # one problem per example, vmapped (see _invert_style_core)
        args = (params, jax.tree.map(lambda a: a[None], c), tgt[None], nz[None])
        z, loss, code, steps = _solve(fn, z_init[None], args, solver, rtol, atol, max_steps)
        return z[0], loss[0], fn(z_init[None], args)[1][0], code, steps

    z, loss, init_loss, codes, steps = jax.vmap(one)(cond, target, noise, z0)
    return _intensity_from_latent(z, config.num_intensities), loss, init_loss, codes, steps


def _best_of(runs: list[tuple[Array, ...]]) -> tuple[Array, ...]:
    """Per example, the run with the lowest final loss; an example fails if any of its runs failed."""
    values, losses, init_losses, codes, steps = (np.stack([np.asarray(r[k]) for r in runs]) for k in range(5))
    pick = np.argmin(np.where(np.isfinite(losses), losses, np.inf), axis=0)
    cols = np.arange(values.shape[1])
    # Conservative: a run that did not finish might have been heading below the chosen one.
    failed = codes != 0
    code = np.where(failed.any(axis=0), codes[np.argmax(failed, axis=0), cols], 0)
    return (jnp.asarray(values[pick, cols]), jnp.asarray(losses[pick, cols]), jnp.asarray(init_losses[pick, cols]),
            jnp.asarray(code, jnp.int32), jnp.asarray(steps.sum(axis=0), jnp.int32))


def invert_intensity(
    params: PyTree,
    config: ATSConfig,
    cond: ATSCondition,
    target: Float[ArrayLike, "..."],
    noise: Float[ArrayLike, "..."],
    *,
    init: float | Sequence[float] | Float[ArrayLike, "..."] | None = None,
    sample_steps: int | None = None,
    solver: str = "levenberg_marquardt",
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 100,
    remat: bool = True,
    max_loss: float | None = None,
    on_failure: str = "raise",
) -> InversionResult:
    """Recover a continuous emotion intensity per example from a target landmark-displacement clip.

    Minimises ``intensity_loss_b(i_b)`` over each example's ``i_b`` in ``[1, L]`` (``L = num_intensities``)
    through ATS's deterministic DDIM sampler with fixed noise; emotion, audio and masks come from
    ``cond``. The loss is not convex in ``i``: ATS interpolates linearly between learned per-level
    embeddings, so each segment ``[k, k + 1]`` between two levels has its own local minimum. Without
    ``init`` the solver therefore starts once from every segment's midpoint (the same compiled
    program, run ``L - 1`` times) and keeps, per example, the run with the lowest loss. Inputs are
    annotated loosely so malformed arrays reach the checks below.

    Args:
        params, config: an ATS model.
        cond: from :func:`~jaxtalk.models.freetalk.ats.make_condition` (its intensity is ignored).
        target: ``(B, T, N, 3)`` target displacements in ``ats.sample``'s units (metres for a model
            with ``displacement_scale`` 100; standardised units for a model of ATS's recipe); NaN
            allowed only on frames outside ``cond.mask``.
        noise: ``(B, T, 3N)`` the fixed starting noise (model units), e.g. :func:`ats_noise`.
        init: starting intensity, scalar or ``(B,)`` in ``[1, L]`` (one run; a start within 1 % of the
            range from a bound is moved 1 % inside). ``None``: one run per segment midpoint.
        sample_steps: DDIM steps (static; default ``config.sample_steps``).
        solver: ``"levenberg_marquardt"`` (default: one forward-mode pass per example and step, and
            Gauss-Newton steps land on the kinks of the piecewise-linear embedding) or ``"bfgs"``.
        rtol, atol, max_steps, remat, max_loss, on_failure: as :func:`invert_style`.

    Returns:
        :class:`InversionResult` with ``value`` ``(B,)`` intensities in ``[1, L]`` and losses in
        model units (``init_loss`` at the start of the chosen run). With several runs, ``steps`` is
        their total per example and ``result_code`` the first unsuccessful run's (any failed run
        fails its example, even when the chosen value came from another run).

    Raises:
        ValueError: a model with a single intensity level, wrong shapes, NaN/inf in noise or on real
            target frames, ``init`` outside ``[1, L]``, a bad step count or solver settings.
        InversionFailedError: the solver did not succeed, a loss is not finite, or ``max_loss`` was
            exceeded (``on_failure="raise"``).
    """
    _check_solver_args(solver, rtol, atol, max_steps, max_loss, on_failure)
    levels = config.num_intensities
    if levels < 2:
        raise ValueError(f"config.num_intensities={levels}: a single intensity level leaves nothing to invert")
    steps = _resolve_steps(config, sample_steps)
    dtype = _compute_dtype()
    if not isinstance(cond, ATSCondition):
        raise ValueError(f"cond must be an ATSCondition (see ats.make_condition), got {type(cond).__name__}")
    batch, frames = cond.mask.shape
    shape = (batch, frames, config.num_landmarks, 3)
    target_arr = _float_array(target, "target", dtype)
    if target_arr.shape != shape:
        raise ValueError(f"target must have shape {shape} (the condition's batch and frames), got {target_arr.shape}")
    mask_arr = np.asarray(cond.mask)
    if not np.all(mask_arr.any(axis=1)):
        raise ValueError(f"cond.mask has no real frame in example {int(np.argmin(mask_arr.any(axis=1)))}")
    _check_observed_finite(target_arr, mask_arr)
    target_arr = np.where(mask_arr[..., None, None], target_arr, 0.0).astype(dtype)
    noise_arr = _float_array(noise, "noise", dtype)
    if noise_arr.shape != (batch, frames, config.motion_dim):
        raise ValueError(f"noise must have shape {(batch, frames, config.motion_dim)}, got {noise_arr.shape}")
    _check_finite(noise_arr, "noise")
    if init is None:
        starts = [np.full((batch,), k + 0.5) for k in range(1, levels)]
    else:
        init_arr = _float_array(init, "init", np.float64)
        if init_arr.shape == ():
            init_arr = np.full((batch,), float(init_arr))
        if init_arr.shape != (batch,):
            raise ValueError(f"init must be a scalar or have shape ({batch},), got {init_arr.shape}")
        if not np.all(np.isfinite(init_arr)) or init_arr.min() < 1 or init_arr.max() > levels:
            raise ValueError(f"init intensities must lie in [1, {levels}], got {init_arr.tolist()}")
        starts = [init_arr]
    rtol_, atol_ = _tolerances(rtol, atol, dtype)
    runs = [
        _invert_intensity_core(
            params, cond, jnp.asarray(target_arr), jnp.asarray(noise_arr),
            jnp.asarray(_latent_from_intensity(start, levels), dtype),
            config=config, sample_steps=steps, solver=solver, rtol=rtol_, atol=atol_, max_steps=int(max_steps),
            remat=bool(remat),
        )
        for start in starts
    ]
    return _finish("intensity", *_best_of(runs), int(max_steps), max_loss, on_failure)
