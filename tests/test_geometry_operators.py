"""Mesh operators: Laplacian, mass, eigenbasis, frames and gradients against analytic targets and
brute-force references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import trimesh
from scipy.spatial import Delaunay

from jaxtalk.geometry import operators as ops_mod
from jaxtalk.geometry.operators import (
    EigenDecompositionError,
    compute_operators,
    cotangent_laplacian,
    eigen_decomposition,
    gradient_operators,
    laplacian_and_mass,
    tangent_frames,
    vertex_normals,
)


def bumpy_sphere(subdivisions: int = 2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere with random radial bumps: no symmetry, so eigenvalues are simple."""
    m = trimesh.creation.icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    v = m.vertices * (1.0 + 0.1 * rng.random((len(m.vertices), 1)))
    return v, np.asarray(m.faces)


def flat_patch(seed: int = 0, n: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Delaunay-triangulated random planar patch embedded in a tilted plane; returns its normal."""
    rng = np.random.default_rng(seed)
    uv = rng.random((n, 2))
    faces = Delaunay(uv).simplices
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    v = uv @ q[:2] + np.array([0.3, -0.2, 0.5])
    return v, faces, q[2]


def test_cotangent_laplacian_hand_computed_right_triangle():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    lap, mass = cotangent_laplacian(v, np.array([[0, 1, 2]]))
    # Angles 90, 45, 45 degrees: edge (1,2) has weight cot90/2 = 0, edges (0,1),(0,2) cot45/2 = 1/2.
    expected = np.array([[1.0, -0.5, -0.5], [-0.5, 0.5, 0.0], [-0.5, 0.0, 0.5]])
    np.testing.assert_allclose(lap.toarray(), expected, atol=1e-12)
    np.testing.assert_allclose(mass, np.full(3, 1 / 6) * (1 + 1e-8), rtol=1e-12)


@pytest.mark.parametrize("method", ["cotan", "robust"])
def test_laplacian_kills_constants_and_is_symmetric_psd(method):
    v, f = bumpy_sphere(1)
    lap, mass = laplacian_and_mass(v, f, method)
    np.testing.assert_allclose(lap @ np.ones(len(v)), 0.0, atol=1e-10)
    dense = lap.toarray()
    np.testing.assert_allclose(dense, dense.T, atol=1e-12)
    assert np.linalg.eigvalsh(dense).min() > -1e-10
    assert np.all(mass > 0)
    # Lumped mass sums to the surface area (the robust one up to its tiny mollification).
    np.testing.assert_allclose(mass.sum(), trimesh.Trimesh(v, f).area, rtol=1e-4)


@pytest.mark.parametrize("solver", ["cholmod", "superlu"])
def test_eigenpairs_match_dense_generalised_solver(solver):
    v, f = bumpy_sphere(1)
    lap, mass = laplacian_and_mass(v, f, "cotan")
    evals, evecs = eigen_decomposition(lap, mass, 12, solver=solver)
    ref = scipy.linalg.eigh(lap.toarray(), np.diag(mass), eigvals_only=True)[:12]
    np.testing.assert_allclose(evals, np.clip(ref, 0, None), rtol=1e-8, atol=1e-9)
    assert np.all(np.diff(evals) >= 0) and evals.min() >= 0
    np.testing.assert_allclose(evecs.T @ (mass[:, None] * evecs), np.eye(12), atol=1e-10)
    # Each column really is an eigenvector: L phi = lambda M phi.
    np.testing.assert_allclose(lap @ evecs, mass[:, None] * evecs * evals[None, :], atol=1e-8)


def test_sphere_spectrum_approaches_l_l_plus_1_with_multiplicities():
    m = trimesh.creation.icosphere(4)  # 2562 vertices, unit radius
    ops = compute_operators(m.vertices, m.faces, 16, method="cotan")
    targets = np.repeat([0.0, 2.0, 6.0, 12.0], [1, 3, 5, 7])
    np.testing.assert_allclose(ops.evals, targets, atol=0.01 * 12)
    # Multiplicities: within-group spread is tiny compared with the gaps between groups.
    for lo, hi in [(1, 4), (4, 9)]:
        assert np.ptp(ops.evals[lo:hi]) < 0.02
    gram = ops.evecs.astype(np.float64).T @ (ops.mass[:, None] * ops.evecs)
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-5)
    assert ops.evals.dtype == np.float32 and ops.evecs.dtype == np.float32


def test_eigen_retries_with_growing_shift(monkeypatch):
    v, f = bumpy_sphere(1)
    lap, mass = laplacian_and_mass(v, f, "cotan")
    real_eigsh = ops_mod.sla.eigsh
    shifts = []

    def flaky(a, **kw):
        # The solve runs on the standard form D L D + s I (D = M^-1/2): its diagonal minus L_00 / m_0.
        shifts.append(float(a.diagonal()[0] - lap.diagonal()[0] / mass[0]))
        if len(shifts) < 3:
            raise ops_mod.sla.ArpackNoConvergence("no convergence", np.zeros(0), np.zeros((len(v), 0)))
        return real_eigsh(a, **kw)

    monkeypatch.setattr(ops_mod.sla, "eigsh", flaky)
    evals, _ = eigen_decomposition(lap, mass, 6)
    assert len(shifts) == 3
    np.testing.assert_allclose(shifts[1] / shifts[0], 10.0, rtol=1e-6)
    np.testing.assert_allclose(shifts[2] / shifts[1], 10.0, rtol=1e-6)
    ref = scipy.linalg.eigh(lap.toarray(), np.diag(mass), eigvals_only=True)[:6]
    np.testing.assert_allclose(evals, np.clip(ref, 0, None), rtol=1e-6, atol=1e-8)


def test_eigen_raises_clearly_when_every_shift_fails():
    v, f = bumpy_sphere(1)
    lap, mass = laplacian_and_mass(v, f, "cotan")
    broken = lap.tolil()
    broken[0, 0] = np.nan
    with pytest.raises(EigenDecompositionError, match="failed for every shift"):
        eigen_decomposition(broken.tocsr(), mass, 6, max_retries=2)


@pytest.mark.parametrize(
    ("k", "mass_fn", "match"),
    [(0, None, "k must satisfy"), (12, None, "k must satisfy"), (4, lambda m: -m, "mass must be finite")],
)
def test_eigen_argument_errors(k, mass_fn, match):
    v, f = bumpy_sphere(0)  # 12 vertices: k = 12 is too many for ARPACK
    lap, mass = laplacian_and_mass(v, f, "cotan")
    with pytest.raises(ValueError, match=match):
        eigen_decomposition(lap, mass if mass_fn is None else mass_fn(mass), k)


@pytest.mark.parametrize("regularization, tol", [(0.0, 1e-9), (1e-5, 1e-3)])
def test_gradient_of_linear_function_on_flat_mesh_is_exact(regularization, tol):
    v, f, normal = flat_patch()
    frames = tangent_frames(vertex_normals(v, f))
    # Every vertex normal is the plane's normal (up to orientation).
    np.testing.assert_allclose(np.abs(frames[:, 2] @ normal), 1.0, atol=1e-9)
    gx, gy = gradient_operators(v, f, frames, regularization=regularization)
    g = np.array([0.7, -1.3, 2.1])
    g_tangent = g - (g @ normal) * normal
    field = v @ g
    expected_x = frames[:, 0] @ g_tangent
    expected_y = frames[:, 1] @ g_tangent
    scale = np.linalg.norm(g_tangent)
    np.testing.assert_allclose(gx @ field, expected_x, atol=tol * scale)
    np.testing.assert_allclose(gy @ field, expected_y, atol=tol * scale)


def test_gradients_match_per_vertex_least_squares_reference():
    v, f = bumpy_sphere(1, seed=3)
    frames = tangent_frames(vertex_normals(v, f))
    gx, gy = gradient_operators(v, f, frames, regularization=1e-3)
    edges = trimesh.Trimesh(v, f, process=False).edges_unique
    nbrs = [[] for _ in range(len(v))]
    for a, b in edges:
        nbrs[a].append(b)
        nbrs[b].append(a)
    a_all = np.concatenate([(v[n] - v[i]) @ frames[i, :2].T for i, n in enumerate(nbrs)])
    r = 1e-3 * np.mean(np.sum(a_all**2, axis=1))
    dense_x = np.zeros((len(v), len(v)))
    dense_y = np.zeros((len(v), len(v)))
    for i, n in enumerate(nbrs):  # the slow reference: one small solve per vertex
        a = (v[n] - v[i]) @ frames[i, :2].T
        coef = np.linalg.solve(a.T @ a + r * np.eye(2), a.T)  # (2, n_i)
        dense_x[i, n] += coef[0]
        dense_x[i, i] -= coef[0].sum()
        dense_y[i, n] += coef[1]
        dense_y[i, i] -= coef[1].sum()
    np.testing.assert_allclose(gx.toarray(), dense_x, atol=1e-9)
    np.testing.assert_allclose(gy.toarray(), dense_y, atol=1e-9)
    assert gx.nnz == gy.nnz and np.array_equal(gx.indices, gy.indices)


def test_tangent_frames_are_orthonormal_and_right_handed():
    v, f = bumpy_sphere(1)
    frames = tangent_frames(vertex_normals(v, f))
    np.testing.assert_allclose(np.einsum("vij,vkj->vik", frames, frames), np.broadcast_to(np.eye(3), frames.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-12)
    # Normals of a sphere point outwards.
    assert np.all(np.einsum("vi,vi->v", frames[:, 2], v) > 0)


def test_permuting_vertices_permutes_operators():
    v, f = bumpy_sphere(1, seed=1)
    perm = np.random.default_rng(5).permutation(len(v))
    inv = np.argsort(perm)
    a = compute_operators(v, f, 10)
    b = compute_operators(v[perm], inv[f], 10)  # vertex i of b is vertex perm[i] of a
    np.testing.assert_allclose(b.mass, a.mass[perm], rtol=1e-6)
    np.testing.assert_allclose(b.evals, a.evals, rtol=1e-4, atol=1e-5)
    # Simple eigenvalues: eigenvectors agree up to sign.
    signs = np.sign(np.sum(b.evecs * a.evecs[perm], axis=0))
    np.testing.assert_allclose(b.evecs * signs, a.evecs[perm], atol=1e-4)
    p = sp.csr_matrix((np.ones(len(v)), (np.arange(len(v)), perm)), shape=(len(v), len(v)))
    np.testing.assert_allclose(b.grad_x.toarray(), (p @ a.grad_x @ p.T).toarray(), atol=1e-5)
    np.testing.assert_allclose(b.grad_y.toarray(), (p @ a.grad_y @ p.T).toarray(), atol=1e-5)
    np.testing.assert_allclose(b.frames, a.frames[perm], atol=1e-6)


def test_point_cloud_operators():
    rng = np.random.default_rng(0)
    pts = rng.standard_normal((400, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    ops = compute_operators(pts, np.zeros((0, 3), dtype=np.int64), 9)
    assert ops.method == "robust"
    assert np.all(np.isfinite(ops.evecs)) and np.all(np.isfinite(ops.grad_x.data))
    # Unit sphere again: 0, then three eigenvalues near 2.
    np.testing.assert_allclose(ops.evals[:4], [0, 2, 2, 2], atol=0.25)
    # Normals from PCA point outwards.
    assert np.all(np.einsum("vi,vi->v", ops.frames[:, 2], pts) > 0.9)
