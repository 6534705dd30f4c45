"""Vertex-space metrics of speech-driven face animation: LVE, MVE, FDD, MOD, DTW, DFD, delta_M,
delta_Cd and jitter.

Conventions follow the public reference code (CodeTalker / FaceDiffuser / ScanTalk evaluation
scripts) where one exists; definitions the papers give only in words are stated in each docstring.
Inputs are vertex sequences ``(frames, verts, 3)`` in the face model's units (metres for the
built-in face and FLAME); regions are 1-D arrays of vertex indices (``LinearFaceModel.regions``).
No unit scaling is applied: papers print these in their own scaled units, so scale the returned
values as the table you compare with does.

Every function validates its inputs on the host (clear ``ValueError``), then runs a jitted kernel.
Value checks (NaN) are skipped for tracers, so the differentiable metrics can be used inside a
caller's ``jit``/``grad``.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float, Int

from jaxtalk.metrics._validate import (
    AnyArray,
    as_index_array,
    as_sequence_array,
    check_same_shape,
)
from jaxtalk.metrics.alignment import trajectory_dfd, trajectory_dtw
from jaxtalk.types import Array

__all__ = ["lve", "mve", "fdd", "fdd_batch", "mod", "dtw", "dfd", "delta_m", "delta_cd", "jitter"]

# Region index arrays: "_region" is documentation only (unchecked), so two regions may differ in size.
Index = Int[AnyArray, " _region"] | Sequence[int]


def _vertex_pair(pred: AnyArray, gt: AnyArray, min_frames: int = 1) -> tuple[jax.Array, jax.Array]:
    pred = as_sequence_array(pred, "pred", ndim=3, trailing=(3,), min_frames=min_frames)
    gt = as_sequence_array(gt, "gt", ndim=3, trailing=(3,), min_frames=min_frames)
    check_same_shape(pred, gt, "pred", "gt")
    dtype = jnp.result_type(pred.dtype, gt.dtype)
    return pred.astype(dtype), gt.astype(dtype)


# ----------------------------------------------------------------------------------------- kernels


@jax.jit
def _lve(pred: jax.Array, gt: jax.Array, idx: jax.Array) -> jax.Array:
    sq = jnp.sum(jnp.square(pred[:, idx] - gt[:, idx]), axis=-1)  # (T, L) squared L2 per lip vertex
    return jnp.mean(jnp.max(sq, axis=1))


@jax.jit
def _mve(pred: jax.Array, gt: jax.Array) -> jax.Array:
    return jnp.mean(jnp.linalg.norm(pred - gt, axis=-1))


@jax.jit
def _fdd(pred: jax.Array, gt: jax.Array, template: jax.Array, idx: jax.Array) -> jax.Array:
    def dynamics(v):
        # Per upper-face vertex: the std over time (ddof 0, as np.std) of the squared distance from
        # the template, then the mean over vertices.
        sq = jnp.sum(jnp.square(v[:, idx] - template[idx][None]), axis=-1)  # (T, U)
        return jnp.mean(jnp.std(sq, axis=0))

    return dynamics(gt) - dynamics(pred)


def _opening(v: jax.Array, upper: jax.Array, lower: jax.Array, paired: bool) -> jax.Array:
    if paired:
        return jnp.mean(jnp.linalg.norm(v[:, upper] - v[:, lower], axis=-1), axis=1)
    return jnp.linalg.norm(jnp.mean(v[:, upper], axis=1) - jnp.mean(v[:, lower], axis=1), axis=-1)


@partial(jax.jit, static_argnames=("paired",))
def _mod(pred: jax.Array, gt: jax.Array, upper: jax.Array, lower: jax.Array, paired: bool) -> jax.Array:
    return jnp.mean(jnp.abs(_opening(pred, upper, lower, paired) - _opening(gt, upper, lower, paired)))


@jax.jit
def _delta_m(pred: jax.Array, gt: jax.Array) -> jax.Array:
    d_pred = jnp.diff(pred, axis=0)
    d_gt = jnp.diff(gt, axis=0)
    return jnp.mean(jnp.sum(jnp.square(d_pred - d_gt), axis=-1))


@jax.jit
def _delta_cd(pred: jax.Array, gt: jax.Array, eps: jax.Array) -> jax.Array:
    d_pred = jnp.diff(pred, axis=0)
    d_gt = jnp.diff(gt, axis=0)
    n_pred = jnp.linalg.norm(d_pred, axis=-1)
    n_gt = jnp.linalg.norm(d_gt, axis=-1)
    moving_pred = n_pred > eps
    moving_gt = n_gt > eps
    both = moving_pred & moving_gt
    # Safe denominator: the cosine is only used where both vectors move.
    cos = jnp.sum(d_pred * d_gt, axis=-1) / jnp.where(both, n_pred * n_gt, 1.0)
    dist = jnp.where(both, 1.0 - cos, jnp.where(moving_pred | moving_gt, 1.0, 0.0))
    return jnp.mean(dist)


@jax.jit
def _jitter(x: jax.Array, weights: jax.Array) -> jax.Array:
    acc = x[2:] - 2.0 * x[1:-1] + x[:-2]  # second difference centred on frames 1 .. T-2
    norms = jnp.linalg.norm(acc, axis=-1)
    if norms.ndim == 2:  # vertices: one acceleration per vertex, averaged over the mesh
        norms = jnp.mean(norms, axis=1)
    return jnp.sum(weights * norms) / jnp.sum(weights)


# ------------------------------------------------------------------------------------- public API


def lve(pred: Float[AnyArray, "frames verts 3"], gt: Float[AnyArray, "frames verts 3"],
        lip_idx: Index) -> Float[Array, ""]:
    """Lip vertex error: per frame the MAX over lip vertices of the SQUARED L2 error, mean over frames.

    This is the CodeTalker / FaceDiffuser / ScanTalk code convention (no square root). Over a test
    set those scripts average over all frames of all sequences (frame-weighted); average per-sequence
    values with weights ``frames`` to reproduce that.

    Args:
        pred: predicted vertices ``(T, V, 3)``.
        gt: ground-truth vertices ``(T, V, 3)``.
        lip_idx: indices of the lip vertices ``(L,)``.

    Returns:
        Scalar LVE in squared model units (m^2 for the built-in face).

    Raises:
        ValueError: shape mismatch, non-finite values, empty or out-of-range ``lip_idx``.
    """
    pred, gt = _vertex_pair(pred, gt)
    idx = as_index_array(lip_idx, "lip_idx", pred.shape[1])
    return _lve(pred, gt, jnp.asarray(idx))


def mve(pred: Float[AnyArray, "frames verts 3"], gt: Float[AnyArray, "frames verts 3"]) -> Float[Array, ""]:
    """Mean vertex error: the L2 error of each vertex, averaged over frames and vertices.

    (FreeTalk's metric list expands MVE as "Max Vertex Error"; jaxtalk follows the reference code
    convention of the notes, the mean.)

    Args:
        pred: predicted vertices ``(T, V, 3)``.
        gt: ground-truth vertices ``(T, V, 3)``.

    Returns:
        Scalar MVE in model units.

    Raises:
        ValueError: shape mismatch or non-finite values.
    """
    pred, gt = _vertex_pair(pred, gt)
    return _mve(pred, gt)


def fdd(pred: Float[AnyArray, "frames verts 3"], gt: Float[AnyArray, "frames verts 3"],
        template: Float[AnyArray, "verts 3"], upper_idx: Index) -> Float[Array, ""]:
    """Upper-face dynamics deviation of one sequence (CodeTalker's definition), signed.

    For a sequence ``v`` let ``dyn(v) = mean_u std_t ||v_t[u] - template[u]||^2`` over upper-face
    vertices ``u`` (population std over time of the squared distance from the neutral template).
    ``FDD = dyn(gt) - dyn(pred)``: positive when the prediction moves the upper face too little.

    Args:
        pred: predicted vertices ``(T, V, 3)``.
        gt: ground-truth vertices ``(T, V, 3)``.
        template: the neutral face of this sequence's identity ``(V, 3)``.
        upper_idx: indices of the upper-face vertices ``(U,)``.

    Returns:
        Scalar signed FDD in squared model units.

    Raises:
        ValueError: shape mismatch (including the template), non-finite values, bad ``upper_idx``.
    """
    pred, gt = _vertex_pair(pred, gt)
    tmpl = as_sequence_array(template, "template", ndim=2, trailing=(3,))
    if tmpl.shape != pred.shape[1:]:
        raise ValueError(f"template must have shape {pred.shape[1:]} (verts, 3), got {tmpl.shape}")
    idx = as_index_array(upper_idx, "upper_idx", pred.shape[1])
    return _fdd(pred, gt, tmpl.astype(pred.dtype), jnp.asarray(idx))


def fdd_batch(preds: Sequence[Float[AnyArray, "_ verts 3"]], gts: Sequence[Float[AnyArray, "_ verts 3"]],
              templates: Float[AnyArray, "verts 3"] | Sequence[Float[AnyArray, "verts 3"]],
              upper_idx: Index) -> Float[Array, ""]:
    """FDD over a test set: the mean over sequences of the per-sequence signed FDD (see ``fdd``).

    Args:
        preds: predicted sequences, each ``(T_i, V, 3)``.
        gts: ground-truth sequences, each ``(T_i, V, 3)``, in the same order.
        templates: one neutral face ``(V, 3)`` for all sequences, or one per sequence.
        upper_idx: indices of the upper-face vertices ``(U,)``.

    Returns:
        Scalar mean signed FDD.

    Raises:
        ValueError: empty or unequal lists, or any per-sequence error of ``fdd`` (message names the
            sequence index).
    """
    if len(preds) == 0 or len(preds) != len(gts):
        raise ValueError(f"preds and gts must be non-empty lists of equal length, got {len(preds)} and {len(gts)}")
    if isinstance(templates, (jax.Array, np.ndarray)):
        templates = [templates] * len(preds)
    if len(templates) != len(preds):
        raise ValueError(f"need one template or one per sequence ({len(preds)}), got {len(templates)}")
    values = []
    for i, (p, g, t) in enumerate(zip(preds, gts, templates, strict=True)):
        try:
            values.append(fdd(p, g, t, upper_idx))
        except ValueError as err:
            raise ValueError(f"sequence {i}: {err}") from None
    return jnp.mean(jnp.stack(values))


def mod(pred: Float[AnyArray, "frames verts 3"], gt: Float[AnyArray, "frames verts 3"],
        upper_idx: Index, lower_idx: Index, *, paired: bool = False) -> Float[Array, ""]:
    """Mouth opening distance: mean over frames of ``|opening(pred_t) - opening(gt_t)|``.

    The opening of a frame is the Euclidean distance between the centroid of the ``mouth_upper``
    vertices and the centroid of the ``mouth_lower`` vertices (works for sets of any sizes). With
    ``paired=True`` the two index arrays are read as vertex pairs ``(upper[k], lower[k])`` (e.g.
    vertically aligned inner-lip points) and the opening is the mean pair distance.

    Args:
        pred: predicted vertices ``(T, V, 3)``.
        gt: ground-truth vertices ``(T, V, 3)``.
        upper_idx: upper-lip (mouth_upper) vertex indices.
        lower_idx: lower-lip (mouth_lower) vertex indices.
        paired: use paired distances instead of the centroid distance.

    Returns:
        Scalar MOD in model units.

    Raises:
        ValueError: shape mismatch, non-finite values, bad indices, or ``paired`` with index arrays
            of different lengths.
    """
    pred, gt = _vertex_pair(pred, gt)
    upper = as_index_array(upper_idx, "upper_idx", pred.shape[1])
    lower = as_index_array(lower_idx, "lower_idx", pred.shape[1])
    if paired and upper.shape != lower.shape:
        raise ValueError(f"paired=True needs index arrays of equal length, got {upper.size} and {lower.size}")
    return _mod(pred, gt, jnp.asarray(upper), jnp.asarray(lower), paired)


def _lip_trajectories(pred: AnyArray, gt: AnyArray, lip_idx: Index) -> tuple[jax.Array, jax.Array]:
    pred = as_sequence_array(pred, "pred", ndim=3, trailing=(3,))
    gt = as_sequence_array(gt, "gt", ndim=3, trailing=(3,))
    if pred.shape[1] != gt.shape[1]:
        raise ValueError(f"pred and gt must have the same vertex count, got {pred.shape[1]} and {gt.shape[1]}")
    idx = jnp.asarray(as_index_array(lip_idx, "lip_idx", pred.shape[1]))
    # Each frame's lip vertices become one point in R^{3L}.
    return pred[:, idx].reshape(pred.shape[0], -1), gt[:, idx].reshape(gt.shape[0], -1)


def dtw(pred: Float[AnyArray, "frames_pred verts 3"], gt: Float[AnyArray, "frames_gt verts 3"],
        lip_idx: Index, *, normalized: bool = True) -> Float[Array, ""]:
    """Dynamic time warping distance between the lip-vertex trajectories of two sequences.

    Each frame is one point in R^{3L} (its L lip vertices stacked); the local cost is the Euclidean
    distance between frames; the standard DTW recurrence (steps down, right, diagonal; no window)
    accumulates it. ``normalized=True`` (default) reports the accumulated cost divided by the number
    of cells on the optimal path, i.e. the mean frame distance along the best alignment, so values
    do not grow with sequence length; ``normalized=False`` reports the raw accumulated cost.

    Args:
        pred: predicted vertices ``(T_pred, V, 3)``.
        gt: ground-truth vertices ``(T_gt, V, 3)``; lengths may differ.
        lip_idx: lip vertex indices ``(L,)``.
        normalized: divide by the optimal path length.

    Returns:
        Scalar DTW distance in model units.

    Raises:
        ValueError: vertex-count mismatch, empty sequences, non-finite values, bad ``lip_idx``.
    """
    a, b = _lip_trajectories(pred, gt, lip_idx)
    return trajectory_dtw(a, b, normalized=normalized)


def dfd(pred: Float[AnyArray, "frames_pred verts 3"], gt: Float[AnyArray, "frames_gt verts 3"],
        lip_idx: Index) -> Float[Array, ""]:
    """Discrete Frechet distance (Eiter & Mannila) between lip-vertex trajectories.

    Frames are points in R^{3L} as in ``dtw``; the DFD is the smallest, over monotone couplings of
    the two frame sequences, of the largest Euclidean distance between coupled frames.

    Args:
        pred: predicted vertices ``(T_pred, V, 3)``.
        gt: ground-truth vertices ``(T_gt, V, 3)``; lengths may differ.
        lip_idx: lip vertex indices ``(L,)``.

    Returns:
        Scalar DFD in model units.

    Raises:
        ValueError: vertex-count mismatch, empty sequences, non-finite values, bad ``lip_idx``.
    """
    a, b = _lip_trajectories(pred, gt, lip_idx)
    return trajectory_dfd(a, b)


def _displacement_pair(pred: AnyArray, gt: AnyArray, region_idx: Index | None) -> tuple[jax.Array, jax.Array]:
    pred, gt = _vertex_pair(pred, gt, min_frames=2)
    if region_idx is not None:
        idx = jnp.asarray(as_index_array(region_idx, "region_idx", pred.shape[1]))
        pred, gt = pred[:, idx], gt[:, idx]
    return pred, gt


def delta_m(pred: Float[AnyArray, "frames verts 3"], gt: Float[AnyArray, "frames verts 3"],
            region_idx: Index | None = None) -> Float[Array, ""]:
    """delta_M, FreeTalk's "mean squared displacement error" of consecutive-frame motion.

    With per-vertex displacements ``d_t = v_{t+1} - v_t`` (``T - 1`` of them),
    ``delta_M = mean_{t, v} ||d_pred_t[v] - d_gt_t[v]||^2``: the error of the frame-to-frame motion,
    blind to a constant offset between the sequences.

    Args:
        pred: predicted vertices ``(T, V, 3)``, ``T >= 2``.
        gt: ground-truth vertices ``(T, V, 3)``.
        region_idx: optional vertex subset (e.g. lips); all vertices when None.

    Returns:
        Scalar delta_M in squared model units.

    Raises:
        ValueError: shape mismatch, fewer than 2 frames, non-finite values, bad ``region_idx``.
    """
    pred, gt = _displacement_pair(pred, gt, region_idx)
    return _delta_m(pred, gt)


def delta_cd(pred: Float[AnyArray, "frames verts 3"], gt: Float[AnyArray, "frames verts 3"],
             region_idx: Index | None = None, *, eps: float = 1e-6) -> Float[Array, ""]:
    """delta_Cd, FreeTalk's "cosine displacement error" of consecutive-frame motion directions.

    Mean over frames and vertices of the cosine distance ``1 - cos(d_pred_t[v], d_gt_t[v])`` between
    the displacements ``d_t = v_{t+1} - v_t`` (0 = same direction, 1 = orthogonal, 2 = opposite).
    A direction is undefined for a vertex that does not move, so pairs are scored as: both
    displacements shorter than ``eps`` -> 0 (both still: agreement); exactly one shorter -> 1 (no
    directional agreement, like orthogonal motion); otherwise the cosine distance.

    Args:
        pred: predicted vertices ``(T, V, 3)``, ``T >= 2``.
        gt: ground-truth vertices ``(T, V, 3)``.
        region_idx: optional vertex subset; all vertices when None.
        eps: displacement length (model units per frame) below which a vertex counts as still.

    Returns:
        Scalar delta_Cd in [0, 2].

    Raises:
        ValueError: shape mismatch, fewer than 2 frames, non-finite values, bad ``region_idx``,
            negative ``eps``.
    """
    if not eps >= 0:
        raise ValueError(f"eps must be >= 0, got {eps}")
    pred, gt = _displacement_pair(pred, gt, region_idx)
    return _delta_cd(pred, gt, jnp.asarray(eps, pred.dtype))


def _boundary_weights(num_frames: int, boundaries: Sequence[int] | AnyArray, window: int) -> np.ndarray:
    """0/1 weights over the second-difference frames 1 .. T-2 that lie near a chunk boundary."""
    b = np.asarray(boundaries)
    if b.ndim != 1 or b.size == 0 or not np.issubdtype(b.dtype, np.integer):
        raise ValueError(f"boundaries must be a non-empty 1-D sequence of integer frame indices, got {boundaries!r}")
    if b.min() < 1 or b.max() > num_frames - 1:
        raise ValueError(f"boundaries must lie in [1, {num_frames - 1}] (first frame of a new chunk), "
                         f"got min {int(b.min())}, max {int(b.max())}")
    frames = np.arange(1, num_frames - 1)
    # Boundary b sits between frames b-1 and b: the window is the 2*window frames b-window .. b+window-1.
    near = (frames[:, None] >= b[None, :] - window) & (frames[:, None] <= b[None, :] + window - 1)
    return near.any(axis=1).astype(np.float32)


def jitter(x: Float[AnyArray, "frames *dims"], boundaries: Sequence[int] | Int[AnyArray, " b"] | None = None,
           window: int = 2) -> Float[Array, ""]:
    """Jitter: mean L2 norm of the second difference (per-frame acceleration) of a motion sequence.

    TokTalk's Table 5 measures "average per-frame acceleration near chunk boundaries". The
    acceleration at frame t is ``a_t = x_{t+1} - 2 x_t + x_{t-1}`` (t = 1 .. T-2, frames as the unit
    of time). For parameters ``(T, D)`` its norm is the L2 norm of the D-vector; for vertices
    ``(T, V, 3)`` it is the per-vertex L2 norm averaged over vertices.

    Without ``boundaries`` the mean runs over all frames. With ``boundaries`` (indices of the first
    frame of each new chunk) it runs over the frames within ``window`` frames of a boundary: for a
    boundary b (between frames b-1 and b) the frames b-window .. b+window-1, each counted once.

    Args:
        x: parameters ``(T, D)`` or vertices ``(T, V, 3)``, ``T >= 3``.
        boundaries: chunk boundaries in ``[1, T-1]`` (e.g. ``range(chunk, T, chunk)``), or None.
        window: half-width of the boundary window in frames (>= 1).

    Returns:
        Scalar jitter (model units per frame^2).

    Raises:
        ValueError: rank not 2 or 3 (or not ``(T, V, 3)``), ``T < 3``, non-finite values, boundaries
            out of range or empty, ``window < 1``.
    """
    ndim = len(np.shape(x))
    if ndim not in (2, 3):
        raise ValueError(f"x must be parameters (T, D) or vertices (T, V, 3), got shape {tuple(np.shape(x))}")
    x = as_sequence_array(x, "x", trailing=(3,) if ndim == 3 else None, min_frames=3)
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"window must be an integer >= 1, got {window!r}")
    num_frames = x.shape[0]
    if boundaries is None:
        weights = np.ones(num_frames - 2, np.float32)
    else:
        weights = _boundary_weights(num_frames, boundaries, int(window))
    return _jitter(x, jnp.asarray(weights, x.dtype))
