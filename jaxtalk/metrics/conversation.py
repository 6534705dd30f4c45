"""Conversational head-motion metrics of the DualTalk benchmark (used by DualTalk and TIMAR).

All metrics are computed per parameter group of the 56-d head vector ``[exp 50 | jaw 3 | pose 3]``
(``jaxtalk.layout``: exp = 0:50, jaw = 50:53, pose = neck 53:56), per file (one conversation side),
then averaged over files (DualTalk's ``metric/metric.py`` protocol):

* FD: Frechet distance between Gaussians fit to the prediction and to the ground truth (frames as
  samples; mean and ``np.cov(rowvar=False)``).
* P-FD: the same on the paired features ``[partner_gt | x]`` (partner's group first), x = gt or pred.
* MSE: mean squared error over frames and the group's dimensions.
* SID: entropy (bits) of the histogram of k-means cluster labels, ``-sum p log2(p + 1e-6)``, with
  k = 40 (exp), 10 (jaw), 10 (pose) and scikit-learn's ``KMeans(n_clusters=k, random_state=0,
  n_init="auto")``. Two conventions, both reported by name:
  ``SID_fit_gt``: k-means fit on the ground truth, histogram of the prediction's labels (the protocol
  as described); ``SID_fit_pred``: fit on the prediction, histogram of the ground truth's labels (what
  DualTalk's released script computes, its arguments being swapped).
* rPCC: ``|corr(gt, partner) - corr(pred, partner)|`` with Pearson correlations of the flattened
  group arrays.

These run on the host in float64 (SciPy ``sqrtm``, scikit-learn k-means); they are evaluation
metrics, not losses.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Literal

import numpy as np
import scipy.linalg
from jaxtyping import Float

from jaxtalk.checks import check_finite
from jaxtalk.metrics._validate import AnyArray
from jaxtalk.types import EXP_SLICE, JAW_SLICE, NECK_SLICE, PARAM_DIM

__all__ = [
    "CONVERSATION_GROUPS",
    "SID_CLUSTERS",
    "PUBLISHED_SCALE",
    "gaussian_statistics",
    "gaussian_frechet_distance",
    "frechet_distance",
    "sid",
    "rpcc",
    "conversation_metrics",
]

# DualTalk calls the neck rotation "pose".
CONVERSATION_GROUPS: dict[str, slice] = {"exp": EXP_SLICE, "jaw": JAW_SLICE, "pose": NECK_SLICE}
SID_CLUSTERS: dict[str, int] = {"exp": 40, "jaw": 10, "pose": 10}
# Factors by which the DualTalk and TIMAR tables print each metric (TIMAR Table 4 headers).
PUBLISHED_SCALE: dict[str, float] = {
    "FD_jaw": 1e3, "FD_pose": 1e2,
    "P-FD_jaw": 1e3, "P-FD_pose": 1e2,
    "MSE_exp": 1e1, "MSE_jaw": 1e3, "MSE_pose": 1e2,
    "rPCC_exp": 1e2, "rPCC_jaw": 1e1, "rPCC_pose": 1e1,
}

SidConvention = Literal["both", "fit_gt", "fit_pred"] | None
_SID_EPS = 1e-6
_IMAG_TOL = 1e-3


def _features(x: AnyArray, name: str, min_rows: int = 1) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"{name} must be (samples, dim), got shape {arr.shape}")
    if arr.shape[0] < min_rows:
        raise ValueError(f"{name} needs at least {min_rows} rows (frames), got {arr.shape[0]}")
    if arr.shape[1] == 0:
        raise ValueError(f"{name} has zero feature dimensions (shape {arr.shape})")
    check_finite(arr, name)
    return arr


def gaussian_statistics(features: Float[AnyArray, "samples *dim"]) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of a feature set, as DualTalk fits them.

    Args:
        features: ``(N, D)`` samples (a 1-D array is read as ``(N, 1)``), ``N >= 2``.

    Returns:
        ``mu (D,)`` and ``cov (D, D)`` (``np.cov(rowvar=False)``: unbiased, divides by N - 1).

    Raises:
        ValueError: wrong rank, fewer than 2 samples, or non-finite values.
    """
    x = _features(features, "features", min_rows=2)
    return x.mean(axis=0), np.atleast_2d(np.cov(x, rowvar=False))


def _sqrtm(a: np.ndarray) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            # A singular product makes sqrtm warn; the finiteness check below handles it.
            warnings.simplefilter("ignore", RuntimeWarning)
            warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)
            return scipy.linalg.sqrtm(a)
    except (scipy.linalg.LinAlgError, ValueError):
        return np.full_like(a, np.nan)


def gaussian_frechet_distance(mu1: Float[AnyArray, " dim"], cov1: Float[AnyArray, "dim dim"],
                              mu2: Float[AnyArray, " dim"], cov2: Float[AnyArray, "dim dim"], *,
                              eps: float = 1e-6) -> float:
    """Frechet distance between N(mu1, cov1) and N(mu2, cov2).

    ``||mu1 - mu2||^2 + tr(cov1 + cov2 - 2 (cov1 cov2)^{1/2})``. The matrix square root is
    ``scipy.linalg.sqrtm``; if it is not finite (singular product), ``eps`` is added to both
    diagonals and it is recomputed; an imaginary part up to 1e-3 on the diagonal is numerical noise
    and dropped (the FID / DualTalk convention).

    Args:
        mu1, mu2: means ``(D,)``.
        cov1, cov2: covariances ``(D, D)``.
        eps: diagonal offset for the retry.

    Returns:
        The distance (float, >= 0 up to rounding).

    Raises:
        ValueError: mismatched shapes, non-finite inputs, or an imaginary component above 1e-3.
    """
    mu1 = np.atleast_1d(np.asarray(mu1, np.float64))
    mu2 = np.atleast_1d(np.asarray(mu2, np.float64))
    cov1 = np.atleast_2d(np.asarray(cov1, np.float64))
    cov2 = np.atleast_2d(np.asarray(cov2, np.float64))
    if mu1.shape != mu2.shape or cov1.shape != cov2.shape or cov1.shape != (mu1.size, mu1.size):
        raise ValueError(f"inconsistent Gaussian shapes: mu {mu1.shape} / {mu2.shape}, "
                         f"cov {cov1.shape} / {cov2.shape}")
    for name, value in (("mu1", mu1), ("mu2", mu2), ("cov1", cov1), ("cov2", cov2)):
        check_finite(value, name)
    diff = mu1 - mu2
    covmean = _sqrtm(cov1 @ cov2)
    if not np.all(np.isfinite(covmean)):
        offset = np.eye(cov1.shape[0]) * eps
        covmean = _sqrtm((cov1 + offset) @ (cov2 + offset))
        if not np.all(np.isfinite(covmean)):
            raise ValueError(f"matrix square root of cov1 @ cov2 is not finite even with {eps} added "
                             "to the diagonals")
    if np.iscomplexobj(covmean):
        imag = np.max(np.abs(np.diagonal(covmean).imag))
        if imag > _IMAG_TOL:
            raise ValueError(f"matrix square root has an imaginary component {imag:.3g} > {_IMAG_TOL}")
        covmean = covmean.real
    return float(diff @ diff + np.trace(cov1) + np.trace(cov2) - 2.0 * np.trace(covmean))


def frechet_distance(x: Float[AnyArray, "samples_x *dim"], y: Float[AnyArray, "samples_y *dim"]) -> float:
    """Frechet distance between Gaussians fit (``gaussian_statistics``) to two feature sets.

    Args:
        x: ``(N, D)`` samples, e.g. predicted frames of one group (1-D: ``(N, 1)``).
        y: ``(M, D)`` samples, e.g. ground-truth frames.

    Returns:
        The distance (float).

    Raises:
        ValueError: fewer than 2 samples, different D, non-finite values, or see
            ``gaussian_frechet_distance``.
    """
    mu1, cov1 = gaussian_statistics(x)
    mu2, cov2 = gaussian_statistics(y)
    if mu1.shape != mu2.shape:
        raise ValueError(f"x and y must have the same feature dimension, got {mu1.size} and {mu2.size}")
    return gaussian_frechet_distance(mu1, cov1, mu2, cov2)


def sid(fit_features: Float[AnyArray, "samples_fit dim"], label_features: Float[AnyArray, "samples dim"],
        k: int, *, seed: int = 0) -> float:
    """Diversity score SID: entropy (bits) of the k-means label histogram of ``label_features``.

    k-means (scikit-learn ``KMeans(n_clusters=k, random_state=seed, n_init="auto")``, as in DualTalk)
    is fit on ``fit_features``; ``label_features`` are assigned to the nearest centre and
    ``SID = -sum_c p_c log2(p_c + 1e-6)``. A uniform histogram gives ~log2(k); one cluster gives ~0.

    Args:
        fit_features: ``(N, D)`` samples to cluster, ``N >= k``.
        label_features: ``(M, D)`` samples whose labels are counted.
        k: number of clusters.
        seed: k-means ``random_state``.

    Returns:
        SID in bits (float).

    Raises:
        ValueError: fewer than ``k`` samples to fit, ``k < 1``, different D, or non-finite values.
    """
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}")
    fit = _features(fit_features, "fit_features", min_rows=k)
    lab = _features(label_features, "label_features")
    if fit.shape[1] != lab.shape[1]:
        raise ValueError(f"fit_features and label_features differ in dimension: {fit.shape[1]} vs {lab.shape[1]}")
    # Imported here: scikit-learn is heavy and only the conversation metrics need it.
    from sklearn.cluster import KMeans
    from sklearn.exceptions import ConvergenceWarning

    with warnings.catch_warnings():
        # Fewer distinct points than k (e.g. a frozen prediction) is a legitimate input: its
        # histogram collapses and SID is ~0, which is the answer the metric should give.
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = KMeans(n_clusters=int(k), random_state=seed, n_init="auto").fit(fit)
    labels = model.predict(lab)
    p = np.bincount(labels, minlength=k) / labels.size
    return float(-np.sum(p * np.log2(p + _SID_EPS)))


def _pearson(x: np.ndarray, y: np.ndarray) -> float:
    """Pearson correlation of flattened arrays; 0 when either is constant (np.corrcoef gives NaN)."""
    x = x.ravel() - x.mean()
    y = y.ravel() - y.mean()
    denom = np.sqrt(np.dot(x, x) * np.dot(y, y))
    return float(np.dot(x, y) / denom) if denom > 0 else 0.0


def rpcc(pred: Float[AnyArray, "frames dim"], gt: Float[AnyArray, "frames dim"],
         partner: Float[AnyArray, "frames dim"]) -> float:
    """Residual Pearson correlation: ``|corr(gt, partner) - corr(pred, partner)|``.

    Correlations are Pearson coefficients of the flattened arrays (DualTalk's
    ``np.corrcoef(a.reshape(-1), b.reshape(-1))[0, 1]``). Deviation, documented: a constant array has
    no defined correlation (NumPy returns NaN, which would poison the average over files); here it
    counts as correlation 0.

    Args:
        pred: predicted group features ``(T, D)``.
        gt: ground-truth group features ``(T, D)``.
        partner: the partner's ground-truth features of the same group ``(T, D)``.

    Returns:
        rPCC in [0, 2] (float).

    Raises:
        ValueError: shape mismatch or non-finite values.
    """
    arrays = {name: _features(v, name) for name, v in (("pred", pred), ("gt", gt), ("partner", partner))}
    shapes = {name: a.shape for name, a in arrays.items()}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"pred, gt and partner must have the same shape, got {shapes}")
    return abs(_pearson(arrays["gt"], arrays["partner"]) - _pearson(arrays["pred"], arrays["partner"]))


def _params56(x: AnyArray, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != PARAM_DIM:
        raise ValueError(f"{name} must be (frames, {PARAM_DIM}) head parameters, got shape {arr.shape}")
    check_finite(arr, name)
    return arr


def _file_metrics(pred: np.ndarray, gt: np.ndarray, partner: np.ndarray,
                  conventions: tuple[str, ...]) -> dict[str, float]:
    out: dict[str, float] = {}
    groups = CONVERSATION_GROUPS.items()
    for g, sl in groups:
        out[f"FD_{g}"] = frechet_distance(pred[:, sl], gt[:, sl])
    for g, sl in groups:
        out[f"P-FD_{g}"] = frechet_distance(np.concatenate([partner[:, sl], gt[:, sl]], axis=1),
                                            np.concatenate([partner[:, sl], pred[:, sl]], axis=1))
    for g, sl in groups:
        out[f"MSE_{g}"] = float(np.mean(np.square(pred[:, sl] - gt[:, sl])))
    for conv in conventions:
        for g, sl in groups:
            fit, lab = (gt, pred) if conv == "fit_gt" else (pred, gt)
            out[f"SID_{conv}_{g}"] = sid(fit[:, sl], lab[:, sl], SID_CLUSTERS[g])
    for g, sl in groups:
        out[f"rPCC_{g}"] = rpcc(pred[:, sl], gt[:, sl], partner[:, sl])
    return out


def conversation_metrics(
    pred56: Float[AnyArray, "frames_pred 56"] | Sequence[Float[AnyArray, "_ 56"]],
    gt56: Float[AnyArray, "frames_gt 56"] | Sequence[Float[AnyArray, "_ 56"]],
    partner56: Float[AnyArray, "frames_partner 56"] | Sequence[Float[AnyArray, "_ 56"]],
    *,
    scaled: bool = False,
    sid_convention: SidConvention = "both",
    truncate: bool = False,
) -> dict[str, float]:
    """DualTalk benchmark metrics of predicted agent head motion, per group, averaged over files.

    Keys (``g`` in exp, jaw, pose): ``FD_g``, ``P-FD_g``, ``MSE_g``, ``SID_fit_gt_g`` and/or
    ``SID_fit_pred_g`` (see the module docstring for the two k-means conventions), ``rPCC_g``.

    Args:
        pred56: predicted agent parameters ``(T, 56)``, or a list of files.
        gt56: ground-truth agent parameters, same structure.
        partner56: ground-truth parameters of the conversation partner, same structure.
        scaled: multiply by the factors the published tables print with (``PUBLISHED_SCALE``:
            FD/P-FD jaw x1e3, pose x1e2; MSE exp x10, jaw x1e3, pose x1e2; rPCC exp x1e2, jaw/pose
            x10; SID and FD/P-FD exp unscaled).
        sid_convention: "both" (default), "fit_gt", "fit_pred", or None to skip SID (k-means needs
            at least 40 frames per file).
        truncate: cut each file's three arrays to their shortest length, as DualTalk's script does;
            when False, unequal lengths are an error.

    Returns:
        Dict of metric name -> mean over files (float).

    Raises:
        ValueError: bad shapes or lengths, NaN, empty lists, fewer than 2 frames (40 with SID), an
            unknown ``sid_convention``, or a failing matrix square root (message names the file).
    """
    conventions = {"both": ("fit_gt", "fit_pred"), "fit_gt": ("fit_gt",), "fit_pred": ("fit_pred",), None: ()}
    if sid_convention not in conventions:
        raise ValueError(f"sid_convention must be one of {list(conventions)}, got {sid_convention!r}")
    files = [pred56, gt56, partner56]
    if isinstance(pred56, (list, tuple)):
        if not all(isinstance(f, (list, tuple)) for f in files):
            raise ValueError("pass either three arrays or three lists of arrays, not a mix")
        counts = [len(f) for f in files]
        if counts[0] == 0 or len(set(counts)) != 1:
            raise ValueError(f"pred56, gt56 and partner56 must be non-empty lists of equal length, got {counts}")
        triples = list(zip(*files, strict=True))
    else:
        triples = [tuple(files)]
    min_frames = max(SID_CLUSTERS.values()) if conventions[sid_convention] else 2

    per_file: list[dict[str, float]] = []
    for i, (p, g, q) in enumerate(triples):
        where = f"file {i}: " if len(triples) > 1 else ""
        try:
            p, g, q = _params56(p, "pred56"), _params56(g, "gt56"), _params56(q, "partner56")
            lengths = (p.shape[0], g.shape[0], q.shape[0])
            if len(set(lengths)) != 1:
                if not truncate:
                    raise ValueError(f"pred56, gt56, partner56 have different lengths {lengths}; "
                                     "pass truncate=True to cut them to the shortest")
                n = min(lengths)
                p, g, q = p[:n], g[:n], q[:n]
            if p.shape[0] < min_frames:
                raise ValueError(f"needs at least {min_frames} frames"
                                 f"{' (k-means with k=40 for SID exp)' if min_frames > 2 else ''}, "
                                 f"got {p.shape[0]}")
            per_file.append(_file_metrics(p, g, q, conventions[sid_convention]))
        except ValueError as err:
            raise ValueError(f"{where}{err}") from None

    result = {key: float(np.mean([m[key] for m in per_file])) for key in per_file[0]}
    if scaled:
        result = {key: value * PUBLISHED_SCALE.get(key, 1.0) for key, value in result.items()}
    return result
