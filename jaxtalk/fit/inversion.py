"""Inversion through the samplers: the solve and the checks every inversion shares.

A condition is recovered from a target clip with optimistix, with the sampler's starting noise held
fixed so that the sampled clip is a deterministic, differentiable function of the condition. The
model-specific inversions live with their models (a model is above this layer):

* :func:`jaxtalk.models.toktalk.inversion.invert_style`: TokTalk's style vector.
* :func:`jaxtalk.models.freetalk.inversion.invert_intensity`: FreeTalk's ATS emotion intensity.

The objective is the per-example mean squared error over real frames and coordinates, each example
its own problem (vmapped). Solvers: ``"levenberg_marquardt"`` (default;
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
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxtalk.fit.face_fit import result_name
from jaxtalk.types import Array, Bool, Float, Int

__all__ = ["SOLVERS", "InversionResult", "InversionFailedError"]

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


def _per_example(residual: Array) -> Array:
    return jnp.sum(jnp.square(residual.reshape(residual.shape[0], -1)), axis=1)


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
