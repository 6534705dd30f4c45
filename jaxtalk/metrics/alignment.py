"""Dynamic time warping and discrete Frechet distance between two trajectories of points.

Both are the classic O(N M) dynamic programmes over the local-cost matrix
``c[i, j] = ||a_i - b_j||_2``:

* DTW:  ``D[i, j] = c[i, j] + min(D[i-1, j], D[i, j-1], D[i-1, j-1])`` (sum of local costs along the
  best monotone warping path from (0, 0) to (N-1, M-1)).
* DFD (Eiter & Mannila, 1994): ``D[i, j] = max(c[i, j], min(D[i-1, j], D[i, j-1], D[i-1, j-1]))``
  (the smallest achievable maximum local cost along a monotone coupling).

Cells on one anti-diagonal ``i + j = k`` depend only on the two previous anti-diagonals, so the
programme is one ``lax.scan`` over ``N + M - 1`` anti-diagonals with every diagonal updated as a vector.

To avoid recompiling for every utterance length, trajectories are padded to power-of-two buckets; the
padded cells get infinite cost (they can never lie on a path into the true corner, because the
recurrence only looks up and left) and the true lengths enter as traced integers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Float

from jaxtalk.metrics._validate import AnyArray, as_sequence_array
from jaxtalk.types import Array

__all__ = ["trajectory_dtw", "trajectory_dfd"]

_MIN_BUCKET = 8


def _bucket(n: int) -> int:
    """Padded length: the next power of two (at least ``_MIN_BUCKET``), to bound recompilation."""
    return max(_MIN_BUCKET, 1 << (n - 1).bit_length())


def _shift_down(x: jax.Array, fill: float | int) -> jax.Array:
    """``out[i] = x[i-1]`` with ``out[0] = fill``: moves a diagonal entry from row i-1 to row i."""
    return jnp.concatenate([jnp.full((1,), fill, x.dtype), x[:-1]])


@jax.jit
def _cost_matrix(a: jax.Array, b: jax.Array) -> jax.Array:
    """Euclidean distances between all frames, ``(N, M)``."""
    # Exact differences (not the |a|^2 + |b|^2 - 2ab expansion): identical frames cost exactly 0 and
    # small motions are not lost to float32 cancellation. XLA fuses this without an (N, M, D) buffer.
    return jnp.sqrt(jnp.sum(jnp.square(a[:, None, :] - b[None, :, :]), axis=-1))


@jax.jit
def _sweep(cost: jax.Array, n: jax.Array, m: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Anti-diagonal DPs over a padded cost matrix ``(N, M)`` whose true size is ``(n, m)``.

    DTW and DFD run in the same sweep (they share the grid bookkeeping, and one compiled program
    per length bucket serves both, whatever the point dimension).

    Returns:
        DTW accumulated cost, the cell count of the shortest optimal DTW path, and the DFD.
    """
    num_a, num_b = cost.shape
    rows = jnp.arange(num_a)
    cols = jnp.arange(num_b)
    cost = jnp.where((rows[:, None] < n) & (cols[None, :] < m), cost, jnp.inf)
    # Skew once so that row k holds anti-diagonal k indexed by i: skewed[k, i] = cost[i, k - i].
    diags = jnp.arange(num_a + num_b - 1)
    j = diags[:, None] - rows[None, :]
    on_grid = (j >= 0) & (j < num_b)
    skewed = jnp.where(on_grid, cost[rows[None, :], jnp.clip(j, 0, num_b - 1)], jnp.inf)

    target = n + m - 2  # the anti-diagonal holding the corner cell
    first = rows == 0
    big = jnp.iinfo(jnp.int32).max

    def predecessors(prev1: jax.Array, prev2: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        # Predecessors of (i, j): (i-1, j-1) on diagonal k-2, (i-1, j) and (i, j-1) on diagonal k-1.
        return _shift_down(prev2, jnp.inf), _shift_down(prev1, jnp.inf), prev1

    def step(carry, inputs):
        (w1, w2, len1, len2, f1, f2), (w_val, w_len, f_val) = carry
        k, local = inputs
        start = (k == 0) & first

        diag, up, left = predecessors(w1, w2)
        best = jnp.minimum(diag, jnp.minimum(up, left))
        # Lexicographic (cost, length): among equally good predecessors keep the shortest path.
        best_len = jnp.minimum(
            jnp.where(diag == best, _shift_down(len2, 0), big),
            jnp.minimum(jnp.where(up == best, _shift_down(len1, 0), big), jnp.where(left == best, len1, big)),
        )
        w = local + jnp.where(start, 0.0, best)
        w_cells = jnp.where(start, 0, best_len) + 1

        diag, up, left = predecessors(f1, f2)
        f = jnp.maximum(local, jnp.where(start, 0.0, jnp.minimum(diag, jnp.minimum(up, left))))

        hit = k == target
        out = (jnp.where(hit, w[n - 1], w_val), jnp.where(hit, w_cells[n - 1], w_len), jnp.where(hit, f[n - 1], f_val))
        return ((w, w1, w_cells, len1, f, f1), out), None

    inf_diag = jnp.full((num_a,), jnp.inf, cost.dtype)
    zero_len = jnp.zeros((num_a,), jnp.int32)
    inf = jnp.asarray(jnp.inf, cost.dtype)
    init = ((inf_diag, inf_diag, zero_len, zero_len, inf_diag, inf_diag), (inf, jnp.asarray(0, jnp.int32), inf))
    (_, result), _ = jax.lax.scan(step, init, (diags, skewed))
    return result


def _prepare(a: AnyArray, b: AnyArray) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Validate, pad to length buckets, and return (padded cost matrix, true n, true m)."""
    a = as_sequence_array(a, "a", ndim=2)
    b = as_sequence_array(b, "b", ndim=2)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"trajectories must have the same point dimension, got {a.shape[1]} and {b.shape[1]}")
    n, m = a.shape[0], b.shape[0]
    dtype = jnp.result_type(a.dtype, b.dtype)
    a = jnp.pad(a.astype(dtype), ((0, _bucket(n) - n), (0, 0)))
    b = jnp.pad(b.astype(dtype), ((0, _bucket(m) - m), (0, 0)))
    return _cost_matrix(a, b), jnp.asarray(n, jnp.int32), jnp.asarray(m, jnp.int32)


def trajectory_dtw(a: Float[AnyArray, "n dim"], b: Float[AnyArray, "m dim"], *,
                   normalized: bool = True) -> Float[Array, ""]:
    """Dynamic time warping distance between two trajectories of points in R^dim.

    Local cost: Euclidean distance between points. Standard step pattern (down, right, diagonal),
    no window constraint. The accumulated cost is the sum of local costs along the optimal path;
    ``normalized=True`` divides it by the number of cells on that path (the mean local cost along the
    optimal alignment), which makes values comparable across sequence lengths. Among equally cheap
    paths the shortest is used for the normalisation.

    Args:
        a: first trajectory, ``(n, dim)``.
        b: second trajectory, ``(m, dim)``; lengths may differ.
        normalized: divide by the optimal path length (``max(n, m) <= length <= n + m - 1``).

    Returns:
        Scalar DTW distance (same units as the points).

    Raises:
        ValueError: not 2-D, empty, different point dimensions, or non-finite values.
    """
    value, length, _ = _sweep(*_prepare(a, b))
    return value / length.astype(value.dtype) if normalized else value


def trajectory_dfd(a: Float[AnyArray, "n dim"], b: Float[AnyArray, "m dim"]) -> Float[Array, ""]:
    """Discrete Frechet distance (Eiter & Mannila 1994) between two trajectories of points in R^dim.

    The smallest, over monotone couplings of the two point sequences that start at (a_0, b_0) and
    end at (a_{n-1}, b_{m-1}), of the largest Euclidean distance between coupled points.

    Args:
        a: first trajectory, ``(n, dim)``.
        b: second trajectory, ``(m, dim)``; lengths may differ.

    Returns:
        Scalar discrete Frechet distance (same units as the points).

    Raises:
        ValueError: not 2-D, empty, different point dimensions, or non-finite values.
    """
    _, _, value = _sweep(*_prepare(a, b))
    return value

