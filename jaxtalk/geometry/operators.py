"""DiffusionNet's per-mesh operators, precomputed in float64 with SciPy and stored as float32.

* Laplacian and lumped mass: the cotangent Laplacian (positive semi-definite convention) on clean
  manifold meshes; the robust intrinsic "tufted" Laplacian of ``robust_laplacian`` on non-manifold or
  degenerate meshes and on point clouds.
* Eigenbasis: the k smallest eigenpairs of ``L phi = lambda M phi`` by shift-invert Lanczos (ARPACK)
  whose inner solve is a sparse Cholesky factorisation (CHOLMOD through ``cholespy``) when that
  package is installed, else SciPy's SuperLU. On failure the diagonal shift grows x10 and the solve
  is retried; eigenvalues are clipped to >= 0 and ascending.
* Tangent frames from area-weighted vertex normals (zero/NaN normals: deterministic jitter).
* Gradient operators: per vertex, a regularised least-squares fit of a tangent gradient to the
  one-ring edge differences, all vertices at once through closed-form 2x2 normal equations (the
  reference loops over vertices in Python).

Nothing here is densified V x V. The result is an :class:`Operators` record (NumPy / SciPy CSR);
:mod:`jaxtalk.geometry.diffusionnet` turns it into gather arrays for jitted kernels.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
from typing import Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from jaxtalk.geometry.mesh_checks import inspect_mesh, validate_mesh

__all__ = [
    "Operators",
    "EigenDecompositionError",
    "LaplacianMethod",
    "EigenSolver",
    "laplacian_and_mass",
    "cotangent_laplacian",
    "robust_laplacian_and_mass",
    "eigen_decomposition",
    "vertex_normals",
    "tangent_frames",
    "gradient_operators",
    "compute_operators",
    "resolve_method",
]

LaplacianMethod = Literal["auto", "cotan", "robust"]
EigenSolver = Literal["auto", "cholmod", "superlu"]

# Relative mass regulariser (reference: 1e-8 * mean vertex area) keeps M positive definite for
# isolated or zero-area vertices so the generalised eigenproblem stays well posed.
_MASS_EPS = 1e-8
_POINT_CLOUD_NEIGHBOURS = 30


class EigenDecompositionError(ValueError):
    """The generalised eigenproblem could not be solved even after the shift retries."""


@dataclasses.dataclass(frozen=True)
class Operators:
    """Per-mesh DiffusionNet operators (float32, as the models consume them).

    Attributes:
        mass: (V,) lumped vertex mass (areas), > 0.
        evals: (k,) eigenvalues of ``L phi = lambda M phi``, ascending, >= 0.
        evecs: (V, k) M-orthonormal eigenvectors (``evecs.T @ diag(mass) @ evecs = I``).
        grad_x: (V, V) CSR, X component (tangent frame) of the per-vertex gradient.
        grad_y: (V, V) CSR, Y component; same sparsity pattern as ``grad_x``.
        frames: (V, 3, 3) rows = tangent X axis, tangent Y axis, unit normal.
        method: the Laplacian used ("cotan" or "robust").
    """

    mass: np.ndarray
    evals: np.ndarray
    evecs: np.ndarray
    grad_x: sp.csr_matrix
    grad_y: sp.csr_matrix
    frames: np.ndarray
    method: str

    @property
    def num_vertices(self) -> int:
        return int(self.mass.shape[0])

    @property
    def k(self) -> int:
        return int(self.evals.shape[0])

    def truncated(self, k: int) -> Operators:
        """The same operators with only the first ``k`` eigenpairs.

        Raises:
            ValueError: ``k`` larger than the stored number of eigenpairs or < 1.
        """
        if not 1 <= k <= self.k:
            raise ValueError(f"cannot truncate to k={k}: operators hold {self.k} eigenpairs")
        return dataclasses.replace(self, evals=self.evals[:k], evecs=np.ascontiguousarray(self.evecs[:, :k]))


# --------------------------------------------------------------------------------------------
# Laplacian and mass
# --------------------------------------------------------------------------------------------


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Cotangent Laplacian (PSD: positive diagonal) and lumped (barycentric) vertex mass.

    ``L[i, j] = -(cot a_ij + cot b_ij) / 2`` for an edge, ``L[i, i] = -sum_j L[i, j]``; mass is a
    third of the incident face areas plus ``1e-8 * mean`` so that it is strictly positive.
    Zero-area faces contribute nothing (their cotangents are undefined); use the robust Laplacian
    for meshes that have them.

    Args:
        vertices: (V, 3) float64 positions.
        faces: (F, 3) int indices.

    Returns:
        ``(L (V, V) CSR float64, mass (V,) float64)``.

    Raises:
        ValueError: malformed input (see :func:`jaxtalk.geometry.mesh_checks.validate_mesh`).
    """
    v, f = validate_mesh(vertices, faces)
    n = v.shape[0]
    corners = v[f]  # (F, 3, 3)
    # For corner c, the opposite edge joins the two other corners; its cotangent weights that edge.
    a = corners[:, [1, 2, 0]] - corners  # edge vectors c -> c+1
    b = corners[:, [2, 0, 1]] - corners  # edge vectors c -> c+2
    dots = np.einsum("fci,fci->fc", a, b)
    cross = np.linalg.norm(np.cross(a, b), axis=2)
    area = 0.5 * cross[:, 0]
    ok = cross > 1e-14 * np.maximum(np.einsum("fci,fci->fc", a, a), np.einsum("fci,fci->fc", b, b))
    cot = np.where(ok, dots / np.where(ok, cross, 1.0), 0.0)
    # Corner c's cotangent belongs to the edge (c+1, c+2).
    i = f[:, [1, 2, 0]].ravel()
    j = f[:, [2, 0, 1]].ravel()
    w = 0.5 * cot.ravel()
    off = sp.coo_matrix((np.concatenate([-w, -w]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n))
    off = off.tocsr()
    lap = off - sp.diags(np.asarray(off.sum(axis=1)).ravel())
    mass = np.bincount(f.ravel(), weights=np.repeat(area / 3.0, 3), minlength=n)
    return lap.tocsr(), _regularise_mass(mass)


def _regularise_mass(mass: np.ndarray) -> np.ndarray:
    mean = float(np.mean(mass))
    if not mean > 0:
        raise ValueError("mesh has zero total area (all faces degenerate); cannot build a mass matrix")
    return mass + _MASS_EPS * mean


def robust_laplacian_and_mass(vertices: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Robust intrinsic (tufted-cover) Laplacian and mass from the ``robust_laplacian`` package.

    Valid on non-manifold, degenerate and duplicated input, and on point clouds (``faces`` of shape
    (0, 3), built from 30 nearest neighbours).

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) indices or (0, 3).

    Returns:
        ``(L (V, V) CSR float64 PSD, mass (V,) float64 > 0)``.

    Raises:
        ValueError: malformed input; a point cloud with too few points.
    """
    import robust_laplacian  # local: compiled extension, only needed on this path

    v, f = validate_mesh(vertices, faces)
    if f.shape[0] == 0:
        if v.shape[0] <= _POINT_CLOUD_NEIGHBOURS:
            raise ValueError(
                f"point cloud needs more than {_POINT_CLOUD_NEIGHBOURS} points, got {v.shape[0]}"
            )
        lap, m = robust_laplacian.point_cloud_laplacian(v, n_neighbors=_POINT_CLOUD_NEIGHBOURS)
    else:
        lap, m = robust_laplacian.mesh_laplacian(v, f)
    mass = np.asarray(m.diagonal(), dtype=np.float64)
    return sp.csr_matrix(lap, dtype=np.float64), _regularise_mass(mass)


def resolve_method(vertices: np.ndarray, faces: np.ndarray, method: str) -> str:
    """Pick the Laplacian: "auto" -> "robust" for point clouds and defective meshes, else "cotan".

    Raises:
        ValueError: unknown method.
    """
    if method not in ("auto", "cotan", "robust"):
        raise ValueError(f"method must be 'auto', 'cotan' or 'robust', got {method!r}")
    if method != "auto":
        return method
    f = np.asarray(faces)
    if f.size == 0:
        return "robust"
    return "robust" if inspect_mesh(vertices, faces).needs_robust_laplacian else "cotan"


def laplacian_and_mass(
    vertices: np.ndarray, faces: np.ndarray, method: LaplacianMethod = "auto"
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Laplacian (PSD convention) and lumped mass by the chosen method (see :func:`resolve_method`).

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) indices, or (0, 3) for a point cloud.
        method: "auto", "cotan" or "robust".

    Returns:
        ``(L (V, V) CSR float64, mass (V,) float64)``.

    Raises:
        ValueError: malformed input, unknown method, cotan on a point cloud.
    """
    resolved = resolve_method(vertices, faces, method)
    if resolved == "cotan":
        if np.asarray(faces).size == 0:
            raise ValueError("the cotangent Laplacian needs faces; use method='robust' for point clouds")
        return cotangent_laplacian(vertices, faces)
    return robust_laplacian_and_mass(vertices, faces)


# --------------------------------------------------------------------------------------------
# Eigenbasis
# --------------------------------------------------------------------------------------------


def _cholmod_available() -> bool:
    return importlib.util.find_spec("cholespy") is not None


def _factorised_inverse(matrix: sp.spmatrix, solver: str) -> sla.LinearOperator:
    """A LinearOperator applying ``matrix^-1`` (matrix symmetric positive definite)."""
    n = matrix.shape[0]
    if solver == "cholmod":
        from cholespy import CholeskySolverD, MatrixType

        csr = sp.csr_matrix(matrix)
        csr.sort_indices()
        chol = CholeskySolverD(
            n,
            csr.indptr.astype(np.int32),
            csr.indices.astype(np.int32),
            np.ascontiguousarray(csr.data, dtype=np.float64),
            MatrixType.CSR,
        )

        def solve(rhs: np.ndarray) -> np.ndarray:
            rhs = np.ascontiguousarray(rhs, dtype=np.float64)
            out = np.empty_like(rhs)
            chol.solve(rhs, out)
            if not np.all(np.isfinite(out)):
                # CHOLMOD returns NaN instead of raising when the factorisation was not PD.
                raise np.linalg.LinAlgError("Cholesky solve produced non-finite values")
            return out

    else:
        # Symmetric-mode SuperLU options are not reliably faster here; keep SciPy's defaults.
        lu = sla.splu(sp.csc_matrix(matrix))

        def solve(rhs: np.ndarray) -> np.ndarray:
            return lu.solve(np.asarray(rhs, dtype=np.float64))

    return sla.LinearOperator((n, n), matvec=solve, matmat=solve, dtype=np.float64)


def eigen_decomposition(
    laplacian: sp.spmatrix,
    mass: np.ndarray,
    k: int,
    *,
    solver: EigenSolver = "auto",
    shift: float = 1e-8,
    max_retries: int = 4,
    tol: float = 0.0,
    blas_threads: int | None = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` smallest generalised eigenpairs of ``L phi = lambda M phi`` (M = diag(mass)).

    The lumped mass is diagonal, so the problem is first made standard: with ``D = M^-1/2``,
    ``A = D L D`` has eigenvectors ``psi = M^1/2 phi`` and the same eigenvalues. ARPACK then runs its
    plain symmetric shift-invert mode on ``(A + s I)^-1`` instead of the generalised mode, which
    saves a mass product and an M-inner product per Lanczos step (see docs/design-decisions.md).
    ``A + s I`` is positive definite for any ``s > 0`` even though ``L`` is
    singular, so one Cholesky factorisation serves every iteration; the returned eigenvalues are
    exact (the shift is removed). ``s`` is relative to the spectrum's scale
    (``shift * max_i L_ii / m_i``) so it behaves the same for a face in metres and a unit sphere.
    On failure ``s`` grows x10, up to ``max_retries`` times.

    Args:
        laplacian: (V, V) symmetric PSD sparse Laplacian.
        mass: (V,) positive lumped mass.
        k: number of eigenpairs, 1 <= k < V.
        solver: "cholmod" (cholespy's CHOLMOD), "superlu" (SciPy's SuperLU; what plain
            ``eigsh(..., sigma=...)`` uses), or "auto" (CHOLMOD when installed).
        shift: relative diagonal shift.
        max_retries: how many times to grow the shift after a failure.
        tol: ARPACK relative tolerance (0 = machine precision).
        blas_threads: BLAS threads during the solve (``None``: leave as is). ARPACK's work is
            BLAS-2 on tall, skinny blocks, which gains little from threads and slows down several
            fold when the cores are shared (see docs/design-decisions.md).

    Returns:
        ``(evals (k,) float64 ascending >= 0, evecs (V, k) float64 M-orthonormal)``.

    Raises:
        ValueError: bad ``k``, non-positive or non-finite mass, shape mismatch.
        EigenDecompositionError: every shift failed (the message lists the attempts).
    """
    n = laplacian.shape[0]
    mass = np.asarray(mass, dtype=np.float64)
    if laplacian.shape != (n, n) or mass.shape != (n,):
        raise ValueError(f"laplacian {laplacian.shape} and mass {mass.shape} must be (V, V) and (V,)")
    if not 1 <= k < n:
        raise ValueError(f"k must satisfy 1 <= k < V = {n} (ARPACK needs k < V), got k={k}")
    if not np.all(np.isfinite(mass)) or mass.min() <= 0:
        raise ValueError(f"mass must be finite and > 0, got min {mass.min()}")
    if solver == "auto":
        solver = "cholmod" if _cholmod_available() else "superlu"
    if solver not in ("cholmod", "superlu"):
        raise ValueError(f"solver must be 'auto', 'cholmod' or 'superlu', got {solver!r}")
    lap = sp.csr_matrix(laplacian, dtype=np.float64)
    scale = float(np.max(np.abs(lap.diagonal()) / mass)) or 1.0
    s = shift * scale
    inv_sqrt_mass = 1.0 / np.sqrt(mass)
    # D L D with D = diag(M^-1/2): a symmetric standard problem with the same eigenvalues.
    standard = sp.csr_matrix(lap.multiply(inv_sqrt_mass[:, None]).multiply(inv_sqrt_mass[None, :]))
    from threadpoolctl import threadpool_limits  # local: only this solve needs it

    with threadpool_limits(limits=blas_threads, user_api="blas"):
        vals, psi = _shifted_eigsh(standard, k, s, solver, max_retries, tol)
    return vals, psi * inv_sqrt_mass[:, None]  # phi = M^-1/2 psi is M-orthonormal


def _shifted_eigsh(
    standard: sp.csr_matrix, k: int, s: float, solver: str, max_retries: int, tol: float
) -> tuple[np.ndarray, np.ndarray]:
    n = standard.shape[0]
    identity = sp.identity(n, dtype=np.float64, format="csr")
    attempts: list[str] = []
    for _ in range(max_retries + 1):
        try:
            shifted = (standard + s * identity).tocsr()
            op_inv = _factorised_inverse(shifted, solver)
            # sigma=0 on the shifted matrix: ARPACK's shift-invert mode uses OPinv = (shifted - 0 I)^-1.
            vals, vecs = sla.eigsh(shifted, k=k, sigma=0.0, OPinv=op_inv, which="LM", tol=tol)
            if not (np.all(np.isfinite(vals)) and np.all(np.isfinite(vecs))):
                raise np.linalg.LinAlgError("non-finite eigenpairs")
            order = np.argsort(vals)
            return np.clip(vals[order] - s, 0.0, None), vecs[:, order]
        except (RuntimeError, np.linalg.LinAlgError, sla.ArpackError, sla.ArpackNoConvergence) as err:
            attempts.append(f"shift={s:.3g}: {type(err).__name__}: {err}")
            s *= 10.0
    raise EigenDecompositionError(
        f"eigendecomposition of a {n}-vertex Laplacian (k={k}, solver={solver}) failed for every shift: "
        + "; ".join(attempts)
        + ". The mesh may be badly degenerate: try clean_mesh() or method='robust'."
    )


# --------------------------------------------------------------------------------------------
# Normals, tangent frames, gradients
# --------------------------------------------------------------------------------------------


def _position_hash_jitter(v: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random unit-scale offsets that depend only on each vertex's position.

    Depending on the position (not the index) keeps the operators equivariant to vertex order.
    """
    phase = v @ np.array([[12.9898, 78.233, 37.719], [39.346, 11.135, 83.155], [73.156, 52.235, 9.151]])
    return np.modf(np.sin(phase * 1e3) * 43758.5453)[0]


def _face_vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |.| = 2 * area weights
    out = np.zeros_like(v)
    for axis in range(3):  # 3 bincounts, not a loop over vertices
        out[:, axis] = np.bincount(f.ravel(), weights=np.repeat(face_n[:, axis], 3), minlength=v.shape[0])
    return out


def _point_cloud_normals(v: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    local = v[neighbours] - v[neighbours].mean(axis=1, keepdims=True)
    cov = np.einsum("vki,vkj->vij", local, local)
    _, vecs = np.linalg.eigh(cov)  # batched 3x3
    normal = vecs[:, :, 0]
    # PCA normals have no sign; orient outwards from the centroid for a consistent convention.
    flip = np.einsum("vi,vi->v", normal, v - v.mean(axis=0)) < 0
    return np.where(flip[:, None], -normal, normal)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit, area-weighted vertex normals; never NaN.

    Vertices whose normal vanishes (isolated, or only in zero-area faces) get the normal of the mesh
    with positions jittered by a deterministic, position-derived offset of 1e-4 x the bounding-box
    diagonal; if that is still zero, the direction from the centroid, else +z. Point clouds
    (faces (0, 3)) use PCA over 30 neighbours.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) indices or (0, 3).

    Returns:
        (V, 3) float64 unit normals.

    Raises:
        ValueError: malformed input.
    """
    v, f = validate_mesh(vertices, faces)
    if f.shape[0] == 0:
        normals = _point_cloud_normals(v, _knn(v, min(_POINT_CLOUD_NEIGHBOURS, v.shape[0] - 1)))
    else:
        normals = _face_vertex_normals(v, f)
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) or 1.0
    norm = np.linalg.norm(normals, axis=1)
    bad = ~(norm > 1e-12 * diag**2)
    if bad.any() and f.shape[0]:
        jittered = v + 1e-4 * diag * _position_hash_jitter(v)
        normals[bad] = _face_vertex_normals(jittered, f)[bad]
        norm = np.linalg.norm(normals, axis=1)
        bad = ~(norm > 1e-12 * diag**2)
    if bad.any():
        radial = v[bad] - v.mean(axis=0)
        radial_norm = np.linalg.norm(radial, axis=1, keepdims=True)
        fallback = np.where(radial_norm > 1e-12 * diag, radial, np.array([[0.0, 0.0, 1.0]]))
        normals[bad] = fallback
        norm = np.linalg.norm(normals, axis=1)
    return normals / norm[:, None]


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """Orthonormal tangent frames: X = the world x axis (or y when nearly parallel) projected.

    Args:
        normals: (V, 3) unit normals.

    Returns:
        (V, 3, 3) float64 with rows [tangent X, tangent Y = normal x X, normal].
    """
    n = np.asarray(normals, dtype=np.float64)
    cand = np.where(np.abs(n[:, :1]) > 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
    bx = cand - np.einsum("vi,vi->v", cand, n)[:, None] * n
    bx /= np.linalg.norm(bx, axis=1, keepdims=True)
    by = np.cross(n, bx)
    return np.stack([bx, by, n], axis=1)


def _knn(v: np.ndarray, k: int) -> np.ndarray:
    from scipy.spatial import cKDTree

    _, idx = cKDTree(v).query(v, k=k + 1)
    return idx  # (V, k+1), column 0 is the point itself (or a duplicate of it)


def _directed_edges(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = v.shape[0]
    if f.shape[0] == 0:
        nbr = _knn(v, min(_POINT_CLOUD_NEIGHBOURS, n - 1))
        src = np.repeat(np.arange(n), nbr.shape[1] - 1)
        dst = nbr[:, 1:].ravel()
    else:
        src = f[:, [0, 1, 2, 1, 2, 0]].ravel()
        dst = f[:, [1, 2, 0, 0, 1, 2]].ravel()
    keep = src != dst
    code = np.unique(src[keep] * n + dst[keep])  # dedupe shared edges; sorted by source vertex
    return code // n, code % n


def gradient_operators(
    vertices: np.ndarray,
    faces: np.ndarray,
    frames: np.ndarray,
    *,
    regularization: float = 1e-5,
) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse tangent-gradient operators from a regularised one-ring least-squares fit.

    For vertex i with one-ring edges e_j = p_j - p_i expressed in i's tangent frame as rows a_j of
    A_i (n_i x 2), the gradient g_i minimises ``sum_j (a_j . g - (f_j - f_i))^2 + r |g|^2``, so
    ``g_i = (A_i^T A_i + r I)^-1 A_i^T (f_nbr - f_i)``. All 2x2 normal equations are assembled with
    bincount and inverted in closed form at once. ``r = regularization * mean |a_j|^2`` is relative to
    the mesh scale (the reference's absolute 1e-5 would swamp a face measured in metres).

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) indices, or (0, 3) for a point cloud (30-neighbour graph).
        frames: (V, 3, 3) tangent frames from :func:`tangent_frames`.
        regularization: relative Tikhonov weight (0 = plain least squares).

    Returns:
        ``(grad_x, grad_y)``: (V, V) CSR float64, the tangent X and Y components.

    Raises:
        ValueError: malformed input, frames of the wrong shape, negative regularization.
    """
    v, f = validate_mesh(vertices, faces)
    n = v.shape[0]
    frames = np.asarray(frames, dtype=np.float64)
    if frames.shape != (n, 3, 3):
        raise ValueError(f"frames must have shape ({n}, 3, 3), got {frames.shape}")
    if not regularization >= 0:
        raise ValueError(f"regularization must be >= 0, got {regularization}")
    src, dst = _directed_edges(v, f)
    edge = v[dst] - v[src]
    a = np.einsum("ei,eci->ec", edge, frames[src, :2])  # (E, 2) tangent coordinates
    r = regularization * float(np.mean(np.einsum("ec,ec->e", a, a))) if len(a) else 0.0
    sxx = np.bincount(src, weights=a[:, 0] * a[:, 0], minlength=n) + r
    sxy = np.bincount(src, weights=a[:, 0] * a[:, 1], minlength=n)
    syy = np.bincount(src, weights=a[:, 1] * a[:, 1], minlength=n) + r
    det = sxx * syy - sxy * sxy
    # Vertices with no (or collinear) edges get a zero gradient row instead of inf/NaN.
    ok = det > 1e-12 * np.maximum(sxx * syy, np.finfo(float).tiny)
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    cx = (syy[src] * a[:, 0] - sxy[src] * a[:, 1]) * inv_det[src]
    cy = (sxx[src] * a[:, 1] - sxy[src] * a[:, 0]) * inv_det[src]
    rows = np.concatenate([src, src])
    cols = np.concatenate([dst, src])
    grad_x = sp.csr_matrix((np.concatenate([cx, -cx]), (rows, cols)), shape=(n, n))
    grad_y = sp.csr_matrix((np.concatenate([cy, -cy]), (rows, cols)), shape=(n, n))
    return grad_x, grad_y


# --------------------------------------------------------------------------------------------
# Everything at once
# --------------------------------------------------------------------------------------------


def compute_operators(
    vertices: np.ndarray,
    faces: np.ndarray,
    k: int = 128,
    *,
    method: LaplacianMethod = "auto",
    solver: EigenSolver = "auto",
    cache_dir: str | os.PathLike[str] | None = None,
) -> Operators:
    """All DiffusionNet operators of one mesh (float64 precompute, float32 result), optionally cached.

    Defective meshes never give NaN: "auto" switches to the robust Laplacian for non-manifold,
    duplicated or zero-area input; holes and several components are fine with either. An isolated
    vertex is a component of its own and takes one zero eigenvalue (its value is kept by diffusion);
    :func:`jaxtalk.geometry.mesh_checks.clean_mesh` drops such vertices beforehand.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) triangle indices, or (0, 3) for a point cloud.
        k: number of eigenpairs (k < V).
        method: Laplacian, see :func:`resolve_method` ("auto" picks "robust" for defective meshes).
        solver: eigen solver, see :func:`eigen_decomposition`.
        cache_dir: directory of the disk cache (keyed by a hash of vertices, faces and method);
            ``None`` disables caching. A cached entry with at least ``k`` eigenpairs is sliced.

    Returns:
        An :class:`Operators` record with k eigenpairs.

    Raises:
        ValueError: malformed mesh, bad ``k`` or method.
        EigenDecompositionError: the eigensolve failed for every shift.
    """
    v, f = validate_mesh(vertices, faces)
    if not 1 <= k < v.shape[0]:
        raise ValueError(f"k must satisfy 1 <= k < V = {v.shape[0]}, got k={k}")
    resolved = resolve_method(v, f, method)
    if cache_dir is not None:
        from jaxtalk.geometry import cache

        key = cache.cache_key(v, f, resolved)
        hit = cache.load(cache_dir, key, k)
        if hit is not None:
            return hit
    lap, mass = laplacian_and_mass(v, f, resolved)  # type: ignore[arg-type]
    evals, evecs = eigen_decomposition(lap, mass, k, solver=solver)
    frames = tangent_frames(vertex_normals(v, f))
    grad_x, grad_y = gradient_operators(v, f, frames)
    ops = Operators(
        mass=mass.astype(np.float32),
        evals=evals.astype(np.float32),
        evecs=evecs.astype(np.float32),
        grad_x=grad_x.astype(np.float32),
        grad_y=grad_y.astype(np.float32),
        frames=frames.astype(np.float32),
        method=resolved,
    )
    if cache_dir is not None:
        cache.save(cache_dir, key, ops)
    return ops
