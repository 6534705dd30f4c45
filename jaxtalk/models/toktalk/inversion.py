"""Inversion of TokTalk's style through its sampler (:mod:`jaxtalk.fit.inversion` holds the shared solve).

:func:`invert_style` finds the style VECTOR whose sampled motion (the full Euler scan with CFG,
:func:`jaxtalk.models.toktalk.sample`, from fixed starting noise) matches a target clip of 56-d head
vectors. The default starting point is the style encoder's estimate for the same clip
(:func:`~jaxtalk.models.toktalk.encode_style`), so ``init_loss`` vs ``loss`` of the result compares the
encoder with the inversion directly. The objective is the per-example mean squared error over real
frames in raw FLAME units, plus an optional L2 prior on the style vector.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.audio.framerate import default_num_frames
from jaxtalk.fit.face_fit import _check_finite, _float_array
from jaxtalk.fit.inversion import (  # the solve and checks every inversion shares
    InversionResult,
    _check_observed_finite,
    _check_solver_args,
    _compute_dtype,
    _finish,
    _frame_mask,
    _frame_weights,
    _per_example,
    _solve,
    _tolerances,
)
from jaxtalk.models import toktalk as tt
from jaxtalk.types import Array, Bool, Float, Shaped

__all__ = ["style_loss", "invert_style"]

PyTree = Any
ArrayLike = Array | np.ndarray


def _style_data(style, params, tokens, target, noise, mask, cfg_scale, *, config, sample_steps, remat):
    """Weighted residuals ``(B, T, D)`` whose per-example sum of squares is the MSE (the data term)."""
    x = tt.sample(params, config, tokens, style, noise=noise, sample_steps=sample_steps, cfg_scale=cfg_scale,
                  mask=mask, remat=remat)
    w = _frame_weights(mask, x.shape[-1], x.dtype)
    return (x - target) * w[..., None]


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
