"""Inversion through the samplers: recover a condition from a target clip by differentiating the sampler.

Two conditions are inverted with optimistix, with the sampler's starting noise held fixed so that the
sampled clip is a deterministic, differentiable function of the condition:

* :func:`invert_style`: the TokTalk style VECTOR whose sampled motion (the full Euler scan with CFG,
  :func:`jaxtalk.models.toktalk.sample`) matches a target clip of 56-d head vectors. The default
  starting point is the style encoder's estimate for the same clip (:func:`~jaxtalk.models.toktalk.encode_style`),
  so ``init_loss`` vs ``loss`` of the result compares the encoder with the inversion directly.
* :func:`invert_intensity`: FreeTalk's continuous emotion intensity whose ATS sample (deterministic
  DDIM, ``eta = 0``, :func:`sample_ats_from_noise`) matches a target landmark-displacement clip.
  ATS embeds a float intensity affinely (emotion vector + intensity-scaled direction), so the
  intensity is differentiable as it is (no hook needed). The model clips intensities to ``[1, L]``
  (flat loss outside), so the solver works on a latent ``z`` reflected into the range; the sampled
  clip is still a non-convex function of the intensity through the transformer, so by default the
  solver runs once from the midpoint of each stretch between levels and keeps the best.

The objective is the per-example mean squared error over real frames and coordinates (TokTalk: raw
FLAME units; ATS: the model's units, i.e. ``displacement_scale`` x metres, or standardised units for
a ``fit_ats`` model), each example its own problem (vmapped), plus an optional L2 prior on the style
vector. Solvers: ``"levenberg_marquardt"`` (default;
:func:`optimistix.least_squares` on the residual, one forward-mode pass per unknown per step: few
steps for the small style and intensity dimensions) or ``"bfgs"`` (:class:`optimistix.BFGS` on the
scalar loss, one reverse pass per step with memory bounded by ``remat``; for large style vectors,
but it needs many more steps on these ill-conditioned problems).

An inversion never fails silently: a solver result other than ``successful``, a non-finite loss, or
a per-example loss above ``max_loss`` raises :class:`InversionFailedError` naming the optimistix
result, the step count and the losses (or, with ``on_failure="return"``, comes back with
``converged`` False).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxtalk.audio.framerate import default_num_frames
from jaxtalk.fit.face_fit import _check_finite, _float_array, result_name
from jaxtalk.models import toktalk as tt
from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.ats import ATSCondition
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.types import Array, Bool, Float, Int, PRNGKeyArray, Shaped

__all__ = [
    "SOLVERS",
    "InversionResult",
    "InversionFailedError",
    "style_loss",
    "invert_style",
    "ats_noise",
    "sample_ats_from_noise",
    "intensity_loss",
    "invert_intensity",
]

PyTree = Any
ArrayLike = Array | np.ndarray
SOLVERS = ("bfgs", "levenberg_marquardt")


# ---- result and failure ----------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class InversionResult:
    """Outcome of an inversion (a pytree of arrays); every example is its own problem (vmapped).

    Attributes:
        value: the recovered condition: style vectors ``(B, style_vector_dim)`` or intensities ``(B,)``.
        loss: per-example mean squared error of the sample at ``value`` against the target, ``(B,)``.
        init_loss: the same at the starting point (for :func:`invert_style` with ``init=None``:
            the style encoder's estimate), ``(B,)``.
        result_code: optimistix ``RESULTS`` index per example (see :func:`jaxtalk.fit.result_name`),
            ``(B,)``.
        steps: solver steps taken per example, ``(B,)``.
        converged: per example, solver successful and the loss finite and within ``max_loss``, ``(B,)``.
    """

    value: Float[Array, "batch *dims"]
    loss: Float[Array, " batch"]
    init_loss: Float[Array, " batch"]
    result_code: Int[Array, " batch"]
    steps: Int[Array, " batch"]
    converged: Bool[Array, " batch"]

    @property
    def results(self) -> tuple[str, ...]:
        """The optimistix result's name per example, e.g. ``("successful", ...)``."""
        return tuple(result_name(int(c)) for c in np.asarray(self.result_code))

    @property
    def all_converged(self) -> bool:
        """True when every example converged."""
        return bool(np.all(np.asarray(self.converged)))


class InversionFailedError(RuntimeError):
    """An inversion did not converge, or left a loss that is not finite or above ``max_loss``.

    Attributes:
        result: the :class:`InversionResult` (``converged`` False).
    """

    def __init__(self, message: str, result: InversionResult):
        super().__init__(message)
        self.result = result


# ---- the solve, shared by both inversions ----------------------------------------------------------


def _tolerances(rtol: float | None, atol: float | None, dtype: Any) -> tuple[float, float]:
    # float32 iterates wander at ~1e-6 relative near a minimum, so tighter float32 tolerances only
    # burn steps up to max_steps; float64 affords much tighter ones.
    default_rtol, default_atol = (1e-8, 1e-10) if np.dtype(dtype).itemsize >= 8 else (1e-5, 1e-7)
    return (default_rtol if rtol is None else rtol), (default_atol if atol is None else atol)


def _solve(residual_fn: Any, y0: Array, args: Any, solver: str, rtol: float, atol: float, max_steps: int):
    """Minimise the sum of squares of ``residual_fn(y, args)[0]`` over ``y``.

    ``residual_fn`` returns ``(residuals pytree, aux)``; BFGS minimises the sum of their squares (one
    reverse pass per step), Levenberg-Marquardt works on the residuals themselves.

    Returns:
        ``(y, aux at y, result code, steps)``.
    """
    if solver == "bfgs":

        def objective(y, a):
            residuals, aux = residual_fn(y, a)
            return sum(jnp.sum(jnp.square(r)) for r in jax.tree.leaves(residuals)), aux

        sol = optx.minimise(objective, optx.BFGS(rtol=rtol, atol=atol), y0, args, has_aux=True,
                            max_steps=max_steps, throw=False)
    else:
        sol = optx.least_squares(residual_fn, optx.LevenbergMarquardt(rtol=rtol, atol=atol), y0, args,
                                 has_aux=True, max_steps=max_steps, throw=False)
    # The enum item's integer is the only array form of the result code optimistix gives.
    code = jnp.asarray(sol.result._value, jnp.int32)
    return sol.value, sol.aux, code, jnp.asarray(sol.stats["num_steps"], jnp.int32)


def _frame_weights(mask: Array, width: int, dtype: Any) -> Array:
    """``(B, T)`` weights ``mask / sqrt(real frames * width)``: the weighted sum of squares is the MSE."""
    count = jnp.maximum(jnp.sum(mask, axis=1, keepdims=True), 1).astype(dtype)
    return mask.astype(dtype) / jnp.sqrt(count * width)


def _check_solver_args(solver: str, rtol: Any, atol: Any, max_steps: Any, max_loss: Any, on_failure: str) -> None:
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    for name, value in (("rtol", rtol), ("atol", atol)):
        if value is not None and (not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0):
            raise ValueError(f"{name} must be a positive finite number or None, got {value!r}")
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
    if max_loss is not None and (not isinstance(max_loss, (int, float)) or not max_loss > 0):
        raise ValueError(f"max_loss must be a positive number or None, got {max_loss!r}")
    if on_failure not in ("raise", "return"):
        raise ValueError(f"on_failure must be 'raise' or 'return', got {on_failure!r}")


def _finish(what: str, value: Array, loss: Array, init_loss: Array, codes: Array, steps: Array,
            max_steps: int, max_loss: float | None, on_failure: str) -> InversionResult:
    loss_np, codes_np = np.asarray(loss), np.asarray(codes)
    ok = (codes_np == 0) & np.isfinite(loss_np)
    if max_loss is not None:
        ok &= loss_np <= max_loss
    result = InversionResult(
        value=value, loss=loss, init_loss=init_loss, result_code=jnp.asarray(codes_np, jnp.int32),
        steps=jnp.asarray(steps, jnp.int32), converged=jnp.asarray(ok),
    )
    if not np.all(ok) and on_failure == "raise":
        bad = np.flatnonzero(~ok)
        first = int(bad[0])
        threshold = "" if max_loss is None else f" (max_loss={max_loss:.3g})"
        raise InversionFailedError(
            f"{what} inversion failed for {len(bad)} of {len(ok)} example(s) {bad.tolist()}; first: example "
            f"{first}: optimistix result {result.results[first]!r} after {int(np.asarray(steps)[first])} steps "
            f"(max_steps={max_steps}), loss {loss_np[first]:.4g}{threshold} (starting loss "
            f"{float(np.asarray(init_loss)[first]):.4g})",
            result,
        )
    return result


def _compute_dtype() -> Any:
    # float64 when x64 is on (float64 fixture, finite-difference checks), else float32.
    return np.dtype(jnp.result_type(float))


# ---- TokTalk style --------------------------------------------------------------------------------


def _style_data(style, params, tokens, target, noise, mask, cfg_scale, *, config, sample_steps, remat):
    """Weighted residuals ``(B, T, D)`` whose per-example sum of squares is the MSE (the data term)."""
    x = tt.sample(params, config, tokens, style, noise=noise, sample_steps=sample_steps, cfg_scale=cfg_scale,
                  mask=mask, remat=remat)
    w = _frame_weights(mask, x.shape[-1], x.dtype)
    return (x - target) * w[..., None]


def _per_example(residual: Array) -> Array:
    return jnp.sum(jnp.square(residual.reshape(residual.shape[0], -1)), axis=1)


@functools.partial(jax.jit, static_argnames=("config", "sample_steps", "remat"))
def _style_loss(params, tokens, target, noise, style, mask, cfg_scale, *, config, sample_steps, remat):
    return _per_example(_style_data(style, params, tokens, target, noise, mask, cfg_scale, config=config,
                                    sample_steps=sample_steps, remat=remat))


def style_loss(
    params: PyTree,
    config: tt.TokTalkConfig,
    tokens: Float[ArrayLike, "batch tokens width"],
    target: Float[ArrayLike, "batch frames param"],
    noise: Float[ArrayLike, "batch frames param"],
    style: Float[ArrayLike, "batch style"],
    *,
    cfg_scale: Float[ArrayLike, ""] | float | None = None,
    sample_steps: int | None = None,
    mask: Bool[ArrayLike, "batch frames"] | None = None,
    remat: bool = True,
) -> Float[Array, " batch"]:
    """Per-example MSE between the TokTalk sample for ``style`` (fixed noise) and a target clip.

    The data term :func:`invert_style` minimises (the same code path), differentiable in ``style``
    and every other array argument; jitted (``config``, ``sample_steps``, ``remat`` static). No
    validation beyond :func:`jaxtalk.models.toktalk.sample`'s.

    Args:
        params, config: the TokTalk model.
        tokens: ``(B, Tt, speech_dim)`` base-space token embeddings.
        target: ``(B, T, param_dim)`` target motion (raw FLAME units).
        noise: ``(B, T, param_dim)`` the sampler's starting noise.
        style: ``(B, style_vector_dim)`` style vectors.
        cfg_scale: guidance weight (traced; default ``config.cfg_scale``).
        sample_steps: Euler steps (default ``config.sample_steps``).
        mask: ``(B, T)`` real frames, passed to the sampler and scoring only those (None: all).
        remat: checkpoint each Euler step (memory of the gradient O(1) in the step count).

    Returns:
        ``(B,)`` mean over real frames and the ``param_dim`` coordinates of the squared error.
    """
    m = jnp.ones(jnp.shape(target)[:2], bool) if mask is None else mask
    w = config.cfg_scale if cfg_scale is None else cfg_scale
    return _style_loss(params, tokens, target, noise, style, m, jnp.asarray(w, jnp.result_type(noise)),
                       config=config, sample_steps=sample_steps, remat=bool(remat))


def _style_residuals(style, args, *, config, sample_steps, remat):
    params, tokens, target, noise, mask, cfg_scale, prior = args
    data = _style_data(style, params, tokens, target, noise, mask, cfg_scale, config=config,
                       sample_steps=sample_steps, remat=remat)
    # The per-example data loss rides along as aux: the solver hands it back at its solution.
    return {"data": data, "prior": jnp.sqrt(prior) * style}, _per_example(data)


@functools.partial(
    jax.jit, static_argnames=("config", "sample_steps", "solver", "rtol", "atol", "max_steps", "remat")
)
def _invert_style_core(params, tokens, target, noise, mask, init, cfg_scale, prior, *, config, sample_steps,
                       solver, rtol, atol, max_steps, remat):
    fn = functools.partial(_style_residuals, config=config, sample_steps=sample_steps, remat=remat)

    # One problem per example, vmapped: a joint problem would make Levenberg-Marquardt build a
    # block-diagonal (B style_vector_dim)-column Jacobian, B times the forward-mode passes needed.
    def one(tok, tgt, nz, m, s0):
        args = (params, tok[None], tgt[None], nz[None], m[None], cfg_scale, prior)
        style, loss, code, steps = _solve(fn, s0[None], args, solver, rtol, atol, max_steps)
        return style[0], loss[0], fn(s0[None], args)[1][0], code, steps

    return jax.vmap(one)(tokens, target, noise, mask, init)


def invert_style(
    params: PyTree,
    config: tt.TokTalkConfig,
    tokens: Float[ArrayLike, "..."],
    target: Float[ArrayLike, "..."],
    noise: Float[ArrayLike, "..."],
    *,
    init: Sequence[float] | Float[ArrayLike, "..."] | None = None,
    mask: Shaped[ArrayLike, "..."] | None = None,
    cfg_scale: float | Float[ArrayLike, ""] | None = None,
    sample_steps: int | None = None,
    prior: float | Float[ArrayLike, ""] = 0.0,
    solver: str = "levenberg_marquardt",
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 100,
    remat: bool = True,
    max_loss: float | None = None,
    on_failure: str = "raise",
) -> InversionResult:
    """Find the TokTalk style vector whose sampled motion (fixed noise) matches a target clip.

    Minimises ``style_loss_b(s_b) + prior |s_b|^2`` over each example's ``s_b`` through the
    whole Euler/CFG sampler (one jitted program per shapes and static settings; ``cfg_scale`` and
    ``prior`` are traced). Inputs are annotated loosely so malformed arrays reach the checks below.

    Args:
        params, config: a TokTalk model.
        tokens: ``(B, Tt, speech_dim)`` base-space token embeddings at ``config.token_rate``, covering
            ``T`` frames.
        target: ``(B, T, param_dim)`` target motion in raw FLAME units; NaN allowed only on frames
            outside ``mask``.
        noise: ``(B, T, param_dim)`` the fixed starting noise of the sampler.
        init: starting style, ``(style_vector_dim,)`` or ``(B, style_vector_dim)``. ``None``: the style encoder's
            estimate for the target clip (needs ``T >= config.style_min_frames``).
        mask: ``(B, T)`` bool, real frames (given to the sampler, and only they are scored).
        cfg_scale: guidance weight (default ``config.cfg_scale``).
        sample_steps: Euler steps (static; default ``config.sample_steps``).
        prior: L2 weight on the style vector (>= 0; regularises directions the clip does not see).
        solver: ``"levenberg_marquardt"`` (default) or ``"bfgs"`` (see the module docstring).
        rtol, atol: optimistix Cauchy termination tolerances (``None``: 1e-5 / 1e-7 in float32,
            1e-8 / 1e-10 in float64).
        max_steps: most solver steps.
        remat: ``jax.checkpoint`` each sampler step (bounds the gradient's memory).
        max_loss: fail when an example's final MSE exceeds this. ``None``: no threshold.
        on_failure: ``"raise"`` (default) or ``"return"`` a result with ``converged`` False.

    Returns:
        :class:`InversionResult` with ``value`` ``(B, style_vector_dim)``.

    Raises:
        ValueError: wrong shapes or widths, tokens that do not cover ``T`` frames, NaN/inf in
            tokens, noise, init or observed target frames, a clip too short for the encoder with
            ``init=None``, bad solver settings.
        InversionFailedError: the solver did not succeed, a loss is not finite, or ``max_loss`` was
            exceeded (``on_failure="raise"``).
    """
    _check_solver_args(solver, rtol, atol, max_steps, max_loss, on_failure)
    dtype = _compute_dtype()
    target_arr = _float_array(target, "target", dtype)
    if target_arr.ndim != 3 or target_arr.shape[2] != config.param_dim or 0 in target_arr.shape[:2]:
        raise ValueError(f"target must have shape (B >= 1, T >= 1, {config.param_dim}), got {target_arr.shape}")
    batch, frames = target_arr.shape[:2]
    tok = _float_array(tokens, "tokens", dtype)
    if tok.ndim != 3 or tok.shape[0] != batch or tok.shape[2] != config.speech_dim or tok.shape[1] == 0:
        raise ValueError(f"tokens must have shape ({batch}, Tt >= 1, {config.speech_dim}), got {tok.shape}")
    covered = default_num_frames(tok.shape[1], config.token_rate, config.fps)
    if covered != frames:
        raise ValueError(
            f"{tok.shape[1]} tokens at {config.token_rate} Hz cover {covered} frames at {config.fps} fps, "
            f"but the target has {frames} frames"
        )
    _check_finite(tok, "tokens")
    noise_arr = _float_array(noise, "noise", dtype)
    if noise_arr.shape != target_arr.shape:
        raise ValueError(f"noise must have the target's shape {target_arr.shape}, got {noise_arr.shape}")
    _check_finite(noise_arr, "noise")
    mask_arr = _frame_mask(mask, batch, frames)
    _check_observed_finite(target_arr, mask_arr)
    target_arr = np.where(mask_arr[..., None], target_arr, 0.0).astype(dtype)
    prior_arr = _float_array(prior, "prior", dtype)
    if prior_arr.shape != () or not np.isfinite(prior_arr) or prior_arr < 0:
        raise ValueError(f"prior must be a finite scalar >= 0, got {prior!r}")
    w = config.cfg_scale if cfg_scale is None else cfg_scale
    w_arr = _float_array(w, "cfg_scale", dtype)
    if w_arr.shape != () or not np.isfinite(w_arr):
        raise ValueError(f"cfg_scale must be a finite scalar, got {cfg_scale!r}")
    if init is None:
        if frames < config.style_min_frames:
            raise ValueError(
                f"init=None starts from the style encoder, which needs clips of at least "
                f"style_min_frames={config.style_min_frames} frames; the target has {frames}: pass init"
            )
        init_arr = np.asarray(tt.encode_style(params, config, target_arr, mask_arr), dtype)
    else:
        init_arr = _float_array(init, "init", dtype)
        if init_arr.shape == (config.style_vector_dim,):
            init_arr = np.broadcast_to(init_arr, (batch, config.style_vector_dim))
        elif init_arr.shape != (batch, config.style_vector_dim):
            raise ValueError(
                f"init must have shape ({config.style_vector_dim},) or ({batch}, {config.style_vector_dim}), got {init_arr.shape}"
            )
        _check_finite(init_arr, "init")
    rtol_, atol_ = _tolerances(rtol, atol, dtype)
    out = _invert_style_core(
        params, jnp.asarray(tok), jnp.asarray(target_arr), jnp.asarray(noise_arr), jnp.asarray(mask_arr),
        jnp.asarray(np.ascontiguousarray(init_arr)), jnp.asarray(w_arr), jnp.asarray(prior_arr),
        config=config, sample_steps=sample_steps, solver=solver, rtol=rtol_, atol=atol_, max_steps=int(max_steps),
        remat=bool(remat),
    )
    return _finish("style", *out, int(max_steps), max_loss, on_failure)


def _frame_mask(mask: Any, batch: int, frames: int) -> np.ndarray:
    if mask is None:
        return np.ones((batch, frames), bool)
    m = np.asarray(mask)
    if m.dtype != bool or m.shape != (batch, frames):
        raise ValueError(f"mask must be a bool array of shape ({batch}, {frames}), got {m.dtype} {m.shape}")
    if not np.all(m.any(axis=1)):
        raise ValueError(f"mask has no real frame in example {int(np.argmin(m.any(axis=1)))}")
    return m


def _check_observed_finite(target: np.ndarray, mask: np.ndarray) -> None:
    bad = mask.reshape(mask.shape + (1,) * (target.ndim - 2)) & ~np.isfinite(target)
    if np.any(bad):
        b, t = (int(i) for i in np.argwhere(bad)[0][:2])
        raise ValueError(
            f"target holds NaN or inf on a real frame (first: example {b}, frame {t}); mask such frames out"
        )


# ---- FreeTalk ATS intensity -----------------------------------------------------------------------


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
            with ``displacement_scale`` 100; standardised units for a ``fit_ats`` model); NaN allowed
            only on frames outside ``cond.mask``.
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
