"""A lineax least-squares solver for frame-banded Jacobians (block-tridiagonal normal equations).

Fitting a sequence jointly with a first-difference smoothness term gives a least-squares problem in
``T x n`` unknowns whose Jacobian is *frame-banded*: every residual row depends on one frame, or on
two adjacent frames. A dense solver (``lineax.QR``, optimistix's default for Levenberg-Marquardt)
materialises the ``(rows, T n)`` Jacobian and factorises it in ``O(rows (T n)^2)``: seconds per step
at ``T = 50``. The structure allows much better:

1. **Probing with two colours.** Frames of equal parity never share a residual row, so two probes per
   parameter (``e_k`` in every even frame, ``e_k`` in every odd frame) give every Jacobian entry:
   ``2 n`` operator products instead of ``T n``.
2. **Normal equations.** ``H = A^T A`` is block tridiagonal with ``n x n`` blocks; ``A^T b`` comes
   from the same Jacobian blocks (no transposed copy of the residual function to compile).
3. **Block Cholesky** (block Thomas algorithm) in two ``lax.scan`` passes: ``O(T n^3)``.

The normal equations square the condition number, so they are solved after Jacobi scaling
(unit diagonal): that removes the scale differences between parameters (millimetre-scale expression
units next to radian-scale rotations), which is most of the ill-conditioning in face fitting.

Contract on the operator ``A``: its input is one array ``(T, n)``; every output leaf has leading axis
``T`` (row block ``t`` depends on frame ``t`` only) or ``T - 1`` (row block ``t`` depends on frames
``t`` and ``t + 1`` only). The residual functions of :mod:`jaxtalk.fit.face_fit` are written to it, and
so is the damped operator optimistix's Levenberg-Marquardt builds from them (it appends a ``(T, n)``
leaf). The solver needs full column rank (Levenberg-Marquardt's damping provides it); a singular
system returns ``RESULTS.singular`` instead of NaN.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np

from jaxtalk.types import Array, Float

__all__ = ["FrameBandedSolver", "block_tridiagonal_solve"]


def block_tridiagonal_solve(
    diag: Float[Array, "frames n n"],
    lower: Float[Array, "pairs n n"],
    rhs: Float[Array, "frames n"],
) -> Float[Array, "frames n"]:
    """Solve a symmetric positive definite block-tridiagonal system by block Cholesky.

    Args:
        diag: diagonal blocks ``H[t, t]``, shape ``(T, n, n)``.
        lower: sub-diagonal blocks ``H[t + 1, t]``, shape ``(T - 1, n, n)``.
        rhs: right-hand side, shape ``(T, n)``.

    Returns:
        ``x`` with ``H x = rhs``, shape ``(T, n)``; non-finite where ``H`` is not positive definite
        (Cholesky of a non-positive pivot block gives NaN, which the caller checks).
    """
    n = diag.shape[-1]
    dtype = diag.dtype
    # H[t, t-1] for t = 0..T-1, with an all-zero block before the first frame.
    below = jnp.concatenate([jnp.zeros((1, n, n), dtype), lower], axis=0)

    def forward(carry, inputs):
        chol_prev, y_prev = carry
        d, b, r = inputs
        # C = B L_prev^{-T}: the sub-diagonal block of the Cholesky factor.
        c = jax.scipy.linalg.solve_triangular(chol_prev, b.T, lower=True).T
        chol = jnp.linalg.cholesky(d - c @ c.T)
        y = jax.scipy.linalg.solve_triangular(chol, r - c @ y_prev, lower=True)
        return (chol, y), (chol, c, y)

    init = (jnp.eye(n, dtype=dtype), jnp.zeros((n,), dtype))
    _, (chols, cs, ys) = jax.lax.scan(forward, init, (diag, below, rhs))

    # C[t + 1] for t = 0..T-1, with an all-zero block after the last frame.
    next_c = jnp.concatenate([cs[1:], jnp.zeros((1, n, n), dtype)], axis=0)

    def backward(x_next, inputs):
        chol, c_next, y = inputs
        x = jax.scipy.linalg.solve_triangular(chol.T, y - c_next.T @ x_next, lower=False)
        return x, x

    _, xs = jax.lax.scan(backward, jnp.zeros((n,), dtype), (chols, next_c, ys), reverse=True)
    return xs


def _frame_jacobian_blocks(operator: lx.AbstractLinearOperator) -> list[tuple[str, Array, Array | None]]:
    """Every Jacobian entry of a frame-banded operator from ``2 n`` probes, per output leaf.

    Returns one entry per output leaf, in ``tree_leaves`` order: ``("frame", J, None)`` with
    ``J[t] = d rows_t / d frame t`` of shape ``(T, n, m)``, or ``("pair", J0, J1)`` with
    ``J0[t] = d rows_t / d frame t`` and ``J1[t] = d rows_t / d frame t+1``, each ``(T-1, n, m)``.
    """
    struct = operator.in_structure()
    if not isinstance(struct, jax.ShapeDtypeStruct) or len(struct.shape) != 2:
        raise ValueError(f"FrameBandedSolver needs a single (T, n) array as input, got {struct}")
    num_frames, n = struct.shape
    colours = min(2, num_frames)
    parity = np.arange(num_frames) % 2
    # probes[c, k] = e_k in every frame of parity c.
    probes = (parity[None, :] == np.arange(colours)[:, None])[:, None, :, None] * np.eye(n)[None, :, None, :]
    probes = jnp.asarray(probes.reshape(colours * n, num_frames, n), struct.dtype)
    outputs = jax.vmap(operator.mv)(probes)

    frames = np.arange(num_frames)
    blocks: list[tuple[str, Array, Array | None]] = []
    for leaf in jax.tree_util.tree_leaves(outputs):
        rows = leaf.shape[1] if leaf.ndim > 1 else None
        width = int(np.prod(leaf.shape[2:]))  # explicit: a (T-1 = 0)-row leaf cannot infer it
        if rows == num_frames:
            # Row block t of this leaf sees frame t only, which lives in the probe of its parity.
            per_probe = leaf.reshape(colours, n, rows, width)
            blocks.append(("frame", per_probe[parity, :, frames, :], None))  # (T, n, m)
        elif rows == num_frames - 1:
            per_probe = leaf.reshape(colours, n, rows, width)
            pairs = frames[:-1]
            # Frames t and t+1 have different parities, so each probe holds exactly one of them.
            blocks.append(("pair", per_probe[parity[:-1], :, pairs, :], per_probe[1 - parity[:-1], :, pairs, :]))
        else:
            raise ValueError(
                f"FrameBandedSolver: every output leaf must have leading axis T={num_frames} or "
                f"T-1={num_frames - 1}, got a leaf of shape {leaf.shape[1:]}"
            )
    return blocks


def _normal_blocks(blocks, num_frames: int, n: int, dtype) -> tuple[Array, Array]:
    """Blocks of ``A^T A``: diagonal ``(T, n, n)`` and sub-diagonal ``H[t+1, t]``, ``(T-1, n, n)``."""
    diag = jnp.zeros((num_frames, n, n), dtype)
    lower = jnp.zeros((max(num_frames - 1, 0), n, n), dtype)
    for kind, first, second in blocks:
        if kind == "frame":
            diag = diag + jnp.einsum("tim,tjm->tij", first, first)
        elif first.shape[0] > 0:
            diag = diag.at[:-1].add(jnp.einsum("tim,tjm->tij", first, first))
            diag = diag.at[1:].add(jnp.einsum("tim,tjm->tij", second, second))
            lower = lower + jnp.einsum("tim,tjm->tij", second, first)
    return diag, lower


def _transpose_apply(blocks, vector, num_frames: int, n: int, dtype) -> Array:
    """``A^T b`` from the stored blocks (no transposed copy of the residual function)."""
    out = jnp.zeros((num_frames, n), dtype)
    for (kind, first, second), leaf in zip(blocks, jax.tree_util.tree_leaves(vector)):
        b = leaf.reshape(leaf.shape[0], int(np.prod(leaf.shape[1:])))
        if kind == "frame":
            out = out + jnp.einsum("tim,tm->ti", first, b)
        elif first.shape[0] > 0:
            out = out.at[:-1].add(jnp.einsum("tim,tm->ti", first, b))
            out = out.at[1:].add(jnp.einsum("tim,tm->ti", second, b))
    return out


class FrameBandedSolver(lx.AbstractLinearSolver):
    """Least-squares ``A x ~ b`` for a frame-banded ``A`` through block-tridiagonal normal equations.

    Use as the ``linear_solver`` of ``optimistix.LevenbergMarquardt`` or ``optimistix.GaussNewton``
    when the residual function follows the contract in this module's docstring. ``O(T n^3)`` per
    solve instead of dense QR's ``O(rows (T n)^2)``.

    Attributes:
        ridge: added to the unit diagonal of the Jacobi-scaled normal matrix. ``None``: ``10 n``
            machine epsilons of the dtype (~7e-5 in float32 at n = 56, ~1e-13 in float64), enough
            to keep Cholesky positive definite when the Jacobian is rank deficient (a face model
            whose components the data cannot tell apart) or the damping is below rounding. It
            changes the step, never the fixed point: a Gauss-Newton or Levenberg-Marquardt
            iteration stops where ``A^T b = 0`` whatever the step's conditioning, so the fit is
            unaffected, and along exact null directions the step stays zero (minimum norm). ``0``
            reports a singular system as ``RESULTS.singular``.
    """

    ridge: float | None = None

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        blocks = _frame_jacobian_blocks(operator)  # checks the (T, n) input structure
        (num_frames, n), dtype = operator.in_structure().shape, operator.in_structure().dtype
        diag, lower = _normal_blocks(blocks, num_frames, n, dtype)
        # Jacobi scaling to unit diagonal; an all-zero column keeps scale 1 and stays singular.
        d = jnp.diagonal(diag, axis1=-2, axis2=-1)
        scale = jnp.where(d > 0, jax.lax.rsqrt(jnp.where(d > 0, d, 1.0)), 1.0)
        diag = diag * scale[:, :, None] * scale[:, None, :]
        ridge = 10 * diag.shape[-1] * float(jnp.finfo(diag.dtype).eps) if self.ridge is None else self.ridge
        diag = diag + ridge * jnp.eye(diag.shape[-1], dtype=diag.dtype)[None]
        lower = lower * scale[1:, :, None] * scale[:-1, None, :]
        return blocks, diag, lower, scale

    def compute(self, state, vector, options: dict[str, Any]):
        del options
        blocks, diag, lower, scale = state
        num_frames, n = scale.shape
        gradient = _transpose_apply(blocks, vector, num_frames, n, scale.dtype)
        z = block_tridiagonal_solve(diag, lower, scale * gradient)
        solution = scale * z
        ok = jnp.all(jnp.isfinite(solution))
        result = lx.RESULTS.where(ok, lx.RESULTS.successful, lx.RESULTS.singular)
        return jnp.where(ok, solution, 0.0), result, {}

    def transpose(self, state, options: dict[str, Any]):
        raise NotImplementedError(
            "FrameBandedSolver solves least-squares problems inside optimistix's loop and does not "
            "support transposed solves (differentiate fits with optimistix's implicit adjoint)"
        )

    def conj(self, state, options: dict[str, Any]):
        raise NotImplementedError("FrameBandedSolver is for real least-squares problems only")

    def assume_full_rank(self) -> bool:
        return True
