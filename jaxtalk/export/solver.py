"""Blendshape weights by bounded least squares: one jitted, frame-batched solver.

Per frame ``t`` the weights ``w_t`` (``K`` shapes) minimise

    1/2 |B w_t - d_t|^2 + l1 sum(w_t) + l2/2 |w_t|^2 + symmetry/2 sum_pairs (w_tL - w_tR)^2
    + smoothness/2 |w_t - w_{t-1}|^2,        lower <= w_t <= upper (default [0, 1])

summed over frames: the smoothness term couples neighbours (and, for a streamed chunk, the chunk's first
frame to the previous chunk's last weights), so the whole ``(T, K)`` block is one strongly convex
box-constrained quadratic program. On ``[0, 1]`` the L1 norm is the linear term ``l1 sum(w)``.

The problem enters in normal-equation form, ``gram = B^T B`` ``(K, K)`` and ``rhs_t = B^T d_t``
``(T, K)``, so its size is independent of the mesh: the retargeter (:mod:`jaxtalk.export.retarget`)
precomputes ``B^T`` once and every frame costs one ``(V 3) x K`` product.

Solver: FISTA (accelerated projected gradient) with O'Donoghue and Candes' gradient restart, on
Jacobi-scaled variables ``w = s * u`` (``s_k = 1 / sqrt(H_kk)``: the box stays a box, the projection a
clip, and shapes of very different sizes, a 2 cm jaw opening beside a 2 mm dimple, no longer slow it
down). The step is ``1 / L`` with ``L = lambda_max(S H S) + 4 smoothness max(s^2)`` (the chain
Laplacian's eigenvalues lie below 4); it stops when the gradient-mapping step ``|x_{k+1} - y_k|`` is below
``tol`` in weight units for every entry, or after ``max_iter`` steps, in a ``lax.while_loop`` (inference
only: no gradients flow through it). Every penalty, the bounds, ``tol`` and ``max_iter`` are traced:
changing them never recompiles; only ``K`` and ``T`` set the program.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Float, Int

__all__ = ["Penalties", "SolveInfo", "symmetry_matrix", "solve_weights"]

ArrayLike = Array | np.ndarray

DEFAULT_TOL = 1e-7
DEFAULT_MAX_ITER = 3000


@dataclasses.dataclass(frozen=True)
class Penalties:
    """Regularisation of the weight fit, relative to the fit term (see the module docstring).

    Attributes:
        smoothness: ``|w_t - w_{t-1}|^2`` weight (temporal smoothness; 0: frames independent).
        l1: the L1 weight (sparsity: small shapes go to exactly 0).
        l2: the L2 (ridge) weight.
        symmetry: ``(w_left - w_right)^2`` weight of each left/right pair.
    """

    smoothness: float = 0.0
    l1: float = 0.0
    l2: float = 0.0
    symmetry: float = 0.0

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{field.name} must be a finite number >= 0, got {value}")

    def as_array(self) -> np.ndarray:
        """``[smoothness, l1, l2, symmetry]`` (traced inside the solver)."""
        return np.array([self.smoothness, self.l1, self.l2, self.symmetry], np.float64)


class SolveInfo(NamedTuple):
    """How a solve ended: ``iterations`` run and the last gradient-mapping ``step`` (weight units)."""

    iterations: Int[Array, ""]
    step: Float[Array, ""]


def symmetry_matrix(pairs: Sequence[tuple[int, int]], num_shapes: int) -> Float[np.ndarray, "k k"]:
    """``S = sum_pairs (e_l - e_r)(e_l - e_r)^T``: ``w^T S w = sum_pairs (w_l - w_r)^2``.

    Raises:
        ValueError: an index outside ``[0, num_shapes)`` or a shape paired with itself.
    """
    s = np.zeros((num_shapes, num_shapes))
    for left, right in pairs:
        if not (0 <= left < num_shapes and 0 <= right < num_shapes) or left == right:
            raise ValueError(f"symmetry pair ({left}, {right}) does not name two of the {num_shapes} shapes")
        s[left, left] += 1.0
        s[right, right] += 1.0
        s[left, right] -= 1.0
        s[right, left] -= 1.0
    return s


class _State(NamedTuple):
    x: Float[Array, "frames k"]  # the iterate (scaled variables)
    y: Float[Array, "frames k"]  # the extrapolated point
    t: Float[Array, ""]  # FISTA's momentum sequence
    it: Int[Array, ""]
    step: Float[Array, ""]  # last |x_{k+1} - y_k|_inf, weight units


def _chain_laplacian(w: Array) -> Array:
    """``(D w)_t = (w_t - w_{t-1}) [t > 0] + (w_t - w_{t+1}) [t < T - 1]`` (zero for one frame)."""
    diff = w[1:] - w[:-1]
    zero = jnp.zeros_like(w[:1])
    return jnp.concatenate([zero, diff]) - jnp.concatenate([diff, zero])


@jax.jit
def _solve(gram, sym, rhs, previous, anchored, lam, lower, upper, tol, max_iter):
    dtype = rhs.dtype
    smooth, l1, l2, lam_sym = (lam[i].astype(dtype) for i in range(4))
    k = gram.shape[0]
    h = gram + l2 * jnp.eye(k, dtype=dtype) + lam_sym * sym
    s = jax.lax.rsqrt(jnp.maximum(jnp.diag(h), jnp.finfo(dtype).tiny))
    hs = s[:, None] * h * s[None, :]
    lipschitz = jnp.linalg.eigvalsh(hs)[-1] + 4.0 * smooth * jnp.max(s * s)
    c = (rhs - l1) * s[None, :]  # the linear term in scaled variables
    lo = jnp.broadcast_to(lower / s, rhs.shape)
    hi = jnp.broadcast_to(upper / s, rhs.shape)
    anchor = anchored.astype(dtype) * jnp.zeros_like(rhs).at[0].set(1.0)

    def grad(u):
        w = u * s[None, :]
        return u @ hs - c + smooth * s[None, :] * (_chain_laplacian(w) + anchor * (w - previous[None, :]))

    # Start from the frames' unconstrained solutions, clipped (a pseudo-inverse: a rig may have shapes
    # that the fitted vertices cannot tell apart).
    evals, evecs = jnp.linalg.eigh(hs)
    inv = jnp.where(evals > 1e-6 * evals[-1], 1.0 / jnp.where(evals > 0, evals, 1.0), 0.0)
    x0 = jnp.clip(((c @ evecs) * inv[None, :]) @ evecs.T, lo, hi)

    def body(state: _State) -> _State:
        g = grad(state.y)
        x = jnp.clip(state.y - g / lipschitz, lo, hi)
        t = 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * state.t * state.t))
        # Gradient restart: momentum that points uphill is dropped.
        restart = jnp.sum((state.y - x) * (x - state.x)) > 0
        y = jnp.where(restart, x, x + ((state.t - 1.0) / t) * (x - state.x))
        t = jnp.where(restart, jnp.ones_like(t), t)
        step = jnp.max(jnp.abs((x - state.y) * s[None, :]))
        return _State(x, y, t, state.it + 1, step)

    def cond(state: _State):
        return (state.it < max_iter) & (state.step > tol)

    one = jnp.ones((), dtype)
    state = jax.lax.while_loop(cond, body, _State(x0, x0, one, jnp.zeros((), jnp.int32), jnp.full((), jnp.inf, dtype)))
    return state.x * s[None, :], SolveInfo(state.it, state.step)


def solve_weights(
    gram: Float[ArrayLike, "..."],
    rhs: Float[ArrayLike, "..."],
    penalties: Penalties = Penalties(),
    *,
    symmetry: Float[ArrayLike, "..."] | None = None,
    previous: Float[ArrayLike, "..."] | None = None,
    lower: float | Float[ArrayLike, "..."] = 0.0,
    upper: float | Float[ArrayLike, "..."] = 1.0,
    tol: float = DEFAULT_TOL,
    max_iter: int = DEFAULT_MAX_ITER,
) -> tuple[Float[Array, "frames k"], SolveInfo]:
    """Box-constrained weights of every frame at once (module docstring), jitted.

    Inputs are annotated loosely, so that a wrong shape reaches the ValueError that names it.

    Args:
        gram: ``B^T B``, symmetric positive semi-definite (positive definite once ``l2`` or the fitted
            vertices make it so).
        rhs: ``B^T d_t`` per frame.
        penalties: the regularisation weights.
        symmetry: :func:`symmetry_matrix` of the left/right pairs (None: no pairs).
        previous: the weights of the frame before the first (a streamed chunk's predecessor), which the
            smoothness term ties the first frame to; None: the first frame is free.
        lower, upper: the box, a scalar or one bound per shape.
        tol: stop when no weight moves by more than this in a gradient-mapping step.
        max_iter: at most this many steps.

    Returns:
        ``(weights (T, K), SolveInfo)`` in ``rhs``'s dtype.

    Raises:
        ValueError: mismatched shapes, NaN or inf, ``lower > upper``.
    """
    rhs = jnp.asarray(rhs)
    if not jnp.issubdtype(rhs.dtype, jnp.floating):
        rhs = rhs.astype(jnp.result_type(float))
    dtype = rhs.dtype
    if rhs.ndim != 2 or rhs.shape[0] < 1:
        raise ValueError(f"rhs must have shape (frames >= 1, K), got {rhs.shape}")
    k = rhs.shape[1]
    gram = jnp.asarray(gram, dtype)
    if gram.shape != (k, k):
        raise ValueError(f"gram must have shape ({k}, {k}) to match rhs {rhs.shape}, got {gram.shape}")
    sym = jnp.zeros((k, k), dtype) if symmetry is None else jnp.asarray(symmetry, dtype)
    if sym.shape != (k, k):
        raise ValueError(f"symmetry must have shape ({k}, {k}), got {sym.shape}")
    prev = jnp.zeros((k,), dtype) if previous is None else jnp.asarray(previous, dtype)
    if prev.shape != (k,):
        raise ValueError(f"previous must have shape ({k},), got {prev.shape}")
    lo = jnp.broadcast_to(jnp.asarray(lower, dtype), (k,))
    hi = jnp.broadcast_to(jnp.asarray(upper, dtype), (k,))
    for name, value in (("gram", gram), ("rhs", rhs), ("previous", prev), ("lower", lo), ("upper", hi)):
        if not isinstance(value, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(value))):
            raise ValueError(f"{name} holds NaN or inf")
    if not isinstance(lo, jax.core.Tracer) and bool(jnp.any(lo > hi)):
        raise ValueError("lower bound above upper bound")
    return _solve(gram, sym, rhs, prev, jnp.asarray(previous is not None), jnp.asarray(penalties.as_array(), dtype),
                  lo, hi, jnp.asarray(tol, dtype), jnp.asarray(max_iter, jnp.int32))
