"""Blendshape weights by bounded least squares: one jitted solver, frame after frame.

Frame ``t``'s weights ``w_t`` (``K`` shapes) minimise

    1/2 |B w - d_t|^2 + l1 sum(w) + l2/2 |w|^2 + symmetry/2 sum_pairs (w_L - w_R)^2
    + smoothness/2 |w - w_{t-1}|^2,        lower <= w <= upper (default [0, 1])

where ``w_{t-1}`` is the previous frame's solution (none for a clip's first frame unless ``previous``
gives it, e.g. the last frame of a stream's previous chunk). The smoothness term looks back only: a
frame's weights depend on its own target and the frames before it, never on later ones, so a clip cut
into chunks anywhere, each chunk tied to the last weights of the one before, gives the weights of the
whole clip solved at once, and a live stream gives what the offline solve of its motion gives. On
``[0, 1]`` the L1 norm is the linear term ``l1 sum(w)``.

The problem enters in normal-equation form, ``gram = B^T B`` ``(K, K)`` and ``rhs_t = B^T d_t``
``(T, K)``, so its size is independent of the mesh: the retargeter (:mod:`jaxtalk.export.retarget`)
precomputes ``B^T`` (for head parameters, the whole map from a frame's parameters to ``B^T d_t``) once.

Solver: each frame is a strictly convex box-constrained quadratic program in ``K`` variables with one
Hessian ``H = gram + l2 I + symmetry S (+ smoothness I)``, solved by Bertsekas' projected Newton method
on Jacobi-scaled variables: the weights at a bound whose gradient pushes them out stay there, the others
take the Newton step of their block (a ``K x K`` Cholesky factorisation), and a backtracking line search
along the projected path (all 16 step lengths evaluated at once) keeps every step a descent. It starts
from the previous frame's weights, whose active bounds are mostly the new frame's, so a frame typically
takes two or three steps. It stops when the bounds held are those of the last step and its Newton point
was inside the box (the exact minimiser, to rounding), when no weight moves by more than ``tol``, when
no step lowers the objective, or after ``max_iter`` steps; frames follow each other in a ``lax.scan``
(inference only: no gradients flow through it). Every penalty, the bounds, ``tol`` and ``max_iter`` are
traced: changing them never recompiles; only ``K`` and ``T`` set the program.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Bool, Float, Int

__all__ = ["Penalties", "SolveInfo", "symmetry_matrix", "solve_weights", "solve_frames", "bucket"]

ArrayLike = Array | np.ndarray

DEFAULT_TOL = 1e-7
# Newton steps per frame at most: a frame takes two or three from the previous frame's weights, a
# clip's first frame (from zero) a few more.
DEFAULT_MAX_ITER = 100
# Backtracking: step lengths 1, 1/2, ..., 2^-15 along the projected path, all evaluated at once.
_STEPS = 0.5 ** np.arange(16)
_ARMIJO = 1e-4
# The frame loop is compiled for a frame count rounded up to a power of two (at least this), the frames past
# the real ones skipped at almost no cost: chunks of any length up to it (a live stream's 10-frame chunks and
# the shorter last one of an utterance) share one program, longer ones one per power of two.
MIN_BUCKET = 16
# A weight within this fraction of its box's width of a bound, its gradient pushing outward, is held there
# (Bertsekas' epsilon-active set; it shrinks with the projected-gradient step near the solution).
_ACTIVE_WIDTH = 1e-3


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
    """How a solve ended: the most Newton ``iterations`` a frame took, and whether every frame stopped on
    the rule rather than at ``max_iter``."""

    iterations: Int[Array, ""]
    converged: Bool[Array, ""]


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


class _Newton(NamedTuple):
    x: Float[Array, " k"]  # the iterate (scaled variables)
    g: Float[Array, " k"]  # the gradient there
    held: Bool[Array, " k"]  # the bounds held (epsilon-active set) at x
    it: Int[Array, ""]
    done: Bool[Array, ""]


def _held(x: Array, g: Array, lo: Array, hi: Array) -> Array:
    """Bertsekas' epsilon-active set: at (or within epsilon of) a bound, the gradient pushing outward."""
    width = jnp.max(jnp.abs(x - jnp.clip(x - g, lo, hi)))
    eps = jnp.minimum(_ACTIVE_WIDTH * (hi - lo), width)
    return ((x <= lo + eps) & (g > 0)) | ((x >= hi - eps) & (g < 0))


def _frame(m: Array, q: Array, x0: Array, lo: Array, hi: Array, scale: Array, tol: Array,
           max_iter: Array) -> tuple[Array, Array, Array]:
    """``argmin 1/2 x^T m x - q^T x`` on ``[lo, hi]`` by projected Newton (scaled variables, ``m`` positive
    definite); returns ``(x, iterations, whether it stopped on the rule)``."""
    dtype = q.dtype
    k = q.shape[0]
    steps = jnp.asarray(_STEPS, dtype)
    diag = jnp.diagonal(m)
    eye = jnp.eye(k, dtype=dtype)
    # A shape that moves nothing and no penalty holds (a zero row) would make the free block singular:
    # only then is the block shifted, by a few rounding errors of its unit diagonal.
    shift = 64 * jnp.finfo(dtype).eps

    def body(state: _Newton) -> _Newton:
        x, g, held = state.x, state.g, state.held
        free = (~held).astype(dtype)
        block = m * free[:, None] * free[None, :] + jnp.diag(1.0 - free)
        factor = jax.lax.linalg.cholesky(block)
        factor = jax.lax.cond(jnp.all(jnp.isfinite(factor)), lambda: factor,
                              lambda: jax.lax.linalg.cholesky(block + shift * eye))
        newton = -jax.scipy.linalg.cho_solve((factor, True), g * free)
        d = jnp.where(held, -g / jnp.where(diag > 0, diag, 1.0), newton)
        trial = jnp.clip(x[None] + steps[:, None] * d[None], lo[None], hi[None])
        move = trial - x[None]
        # f(x + move) - f(x), exactly (not a difference of two objectives, which rounding swamps near the end)
        gain = -(move @ g + 0.5 * jnp.sum((move @ m) * move, axis=1))
        # Armijo on the projected path (Bertsekas): the free weights' Newton decrease plus the held ones' move
        expect = (steps * jnp.sum(jnp.where(held, 0.0, -g * d))
                  + jnp.sum(jnp.where(held[None], -g[None] * move, 0.0), axis=1))
        ok = gain >= _ARMIJO * expect
        found = jnp.any(ok)
        first = jnp.argmax(ok)
        x_new = jnp.where(found, trial[first], x)
        g_new = m @ x_new - q
        held_new = _held(x_new, g_new, lo, hi)
        # The Newton point is the minimiser over the free weights with the held ones where they are: exact
        # when those are on their bounds, the free ones stay inside, and the same bounds hold after it.
        inside = jnp.all(jnp.where(held, (x == lo) | (x == hi), (x + d >= lo) & (x + d <= hi)))
        exact = found & (first == 0) & inside & jnp.all(held_new == held)
        step = jnp.max(jnp.abs((x_new - x) * scale))
        return _Newton(x_new, g_new, held_new, state.it + 1, ~found | exact | (step <= tol))

    def cond(state: _Newton) -> Array:
        return (state.it < max_iter) & ~state.done

    x0 = jnp.clip(x0, lo, hi)
    g0 = m @ x0 - q
    start = _Newton(x0, g0, _held(x0, g0, lo, hi), jnp.zeros((), jnp.int32), jnp.zeros((), bool))
    end = jax.lax.while_loop(cond, body, start)
    return end.x, end.it, end.done


def solve_frames(
    frame_rhs: Callable[[Any], Array],
    frames: Any,
    gram: Float[Array, "k k"],
    symmetry: Float[Array, "k k"],
    previous: Float[Array, " k"],
    anchored: Bool[Array, ""],
    penalties: Float[Array, "4"],
    lower: Float[Array, " k"],
    upper: Float[Array, " k"],
    tol: Float[Array, ""],
    max_iter: Int[Array, ""],
    *,
    count: Int[Array, ""] | None = None,
) -> tuple[Float[Array, "frames k"], SolveInfo]:
    """The solver's traceable core (call it inside ``jax.jit``): :func:`solve_weights` with each frame's
    ``B^T d_t`` computed inside the frame loop by ``frame_rhs`` from that frame's slice of ``frames``.

    Computing it there, one frame at a time, makes a frame's arithmetic the same however the clip is
    cut into calls: what lets a stream of chunks reproduce a whole-clip solve exactly.

    Args:
        frame_rhs: one frame's slice of ``frames`` -> its ``(K,)`` right-hand side.
        frames: a pytree of arrays with a leading frame axis.
        gram, symmetry: ``B^T B`` and :func:`symmetry_matrix` (zeros: no pairs).
        previous, anchored: the weights of the frame before the first, and whether there is one.
        penalties: :meth:`Penalties.as_array`.
        lower, upper: the box, per shape.
        tol, max_iter: the stopping rule (module docstring).
        count: solve the first ``count`` frames only (None: all); the rest are padding (a frame count
            rounded up, so that chunks of many lengths share one program), skipped, their weights
            meaningless.

    Returns:
        ``(weights (T, K), SolveInfo)``.
    """
    dtype = gram.dtype
    smooth, l1, l2, lam_sym = (penalties[i].astype(dtype) for i in range(4))
    k = gram.shape[0]
    h = gram + l2 * jnp.eye(k, dtype=dtype) + lam_sym * symmetry
    # Jacobi scaling: shapes of very different sizes (a 2 cm jaw opening beside a 2 mm dimple) get unit
    # diagonals, so that one epsilon and one line search serve all of them.
    s = jax.lax.rsqrt(jnp.maximum(jnp.diagonal(h) + smooth, jnp.finfo(dtype).tiny))
    hs = s[:, None] * h * s[None, :]
    lo, hi = lower / s, upper / s

    num = jax.tree_util.tree_leaves(frames)[0].shape[0]
    count = jnp.asarray(num if count is None else count, jnp.int32)

    def step(carry: tuple[Array, Array], item: tuple[Any, Array]) -> tuple[tuple[Array, Array], tuple[Array, ...]]:
        (before, tied), (frame, t) = carry, item
        a = jnp.where(tied, smooth, 0.0)
        c = frame_rhs(frame).astype(dtype) - l1 + a * before
        real = t < count
        # From the previous frame's weights: its bounds are mostly this frame's.
        u, it, done = _frame(hs + jnp.diag(a * s * s), c * s, jnp.where(tied, before, 0.0) / s, lo, hi, s, tol,
                             jnp.where(real, max_iter, 0))
        w = u * s
        return (w, jnp.ones((), bool)), (w, it, done | ~real)

    _, (weights, its, done) = jax.lax.scan(step, (previous.astype(dtype), anchored),
                                           (frames, jnp.arange(num, dtype=jnp.int32)))
    return weights, SolveInfo(jnp.max(its), jnp.all(done))


def bucket(frames: int) -> int:
    """The frame count a solve of ``frames`` frames is compiled for (:data:`MIN_BUCKET`)."""
    return max(MIN_BUCKET, 1 << (frames - 1).bit_length())


@jax.jit
def _solve(gram, sym, rhs, count, previous, anchored, lam, lower, upper, tol, max_iter):
    return solve_frames(lambda row: row, rhs, gram, sym, previous, anchored, lam, lower, upper, tol, max_iter,
                        count=count)


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
    """Box-constrained weights of every frame (module docstring), jitted.

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
        tol: a frame also stops when no weight moves by more than this in a step.
        max_iter: at most this many Newton steps per frame.

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
    frames = rhs.shape[0]
    padded = jnp.concatenate([rhs, jnp.zeros((bucket(frames) - frames, k), dtype)])
    weights, info = _solve(gram, sym, padded, jnp.asarray(frames, jnp.int32), prev, jnp.asarray(previous is not None),
                           jnp.asarray(penalties.as_array(), dtype), lo, hi, jnp.asarray(tol, dtype),
                           jnp.asarray(max_iter, jnp.int32))
    return weights[:frames], info
