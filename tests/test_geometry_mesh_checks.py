"""Bad meshes: clear errors for malformed input; finite, valid operators for awkward but legal input."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from jaxtalk.geometry.mesh_checks import clean_mesh, inspect_mesh, validate_mesh
from jaxtalk.geometry.operators import compute_operators, laplacian_and_mass, resolve_method


def sphere(subdivisions: int = 2, offset=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdivisions)
    return np.asarray(m.vertices) + np.asarray(offset), np.asarray(m.faces)


def with_duplicate_vertex(v, f):
    """Split vertex 0: a copy at the same position takes over vertex 0's first face."""
    v2 = np.vstack([v, v[:1]])
    f2 = f.copy()
    first = np.flatnonzero((f == 0).any(axis=1))[0]
    f2[first][f2[first] == 0] = len(v)
    return v2, f2


def with_zero_area_faces(v, f):
    # A repeated-index face and a collinear one (midpoint of an existing edge).
    a, b = f[0, 0], f[0, 1]
    v2 = np.vstack([v, 0.5 * (v[a] + v[b])])
    return v2, np.vstack([f, [[a, a, b], [a, b, len(v)]]])


def with_isolated_vertices(v, f):
    return np.vstack([v, [[3.0, 3.0, 3.0], [-3.0, 0.0, 1.0]]]), f


def with_nonmanifold_edge(v, f):
    # A fin: a third face on edge (f0[0], f0[1]) sticking out of the surface.
    a, b = f[0, 0], f[0, 1]
    tip = 1.5 * (v[a] + v[b])
    return np.vstack([v, tip]), np.vstack([f, [[a, b, len(v)]]])


def with_two_components(v, f):
    v2, f2 = sphere(1, offset=(5.0, 0.0, 0.0))
    return np.vstack([v, v2]), np.vstack([f, f2 + len(v)])


def with_hole(v, f):
    return v, f[5:]


BAD_MESHES = {
    "duplicate_vertex": with_duplicate_vertex,
    "zero_area_faces": with_zero_area_faces,
    "isolated_vertices": with_isolated_vertices,
    "nonmanifold_edge": with_nonmanifold_edge,
    "two_components": with_two_components,
    "hole": with_hole,
}


@pytest.mark.parametrize(
    ("vertices", "faces", "match"),
    [
        (np.zeros((4, 2)), np.array([[0, 1, 2]]), r"vertices must have shape \(V, 3\)"),
        (np.zeros((0, 3)), np.zeros((0, 3), int), "no vertices"),
        (np.array([[0.0, 0, 0], [np.nan, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]), "non-finite rows.*index 1"),
        (np.eye(3), np.array([[0, 1, 3]]), r"face indices must lie in \[0, 2\].*3\]"),
        (np.eye(3), np.array([[0, -1, 2]]), "face indices must lie"),
        (np.eye(3), np.array([[0, 1]]), r"faces must have shape \(F, 3\)"),
        (np.eye(3), np.array([[0.5, 1, 2]]), "integer vertex indices"),
    ],
)
def test_validate_mesh_rejects_malformed_input(vertices, faces, match):
    with pytest.raises(ValueError, match=match):
        validate_mesh(vertices, faces)
    with pytest.raises(ValueError, match=match):
        compute_operators(vertices, faces, 1)


def test_inspect_counts_each_defect():
    v, f = sphere(1)
    clean = inspect_mesh(v, f)
    assert (clean.duplicate_vertices, clean.degenerate_faces, clean.isolated_vertices) == (0, 0, 0)
    assert (clean.nonmanifold_edges, clean.boundary_edges, clean.components) == (0, 0, 1)
    assert not clean.needs_robust_laplacian
    assert inspect_mesh(*with_duplicate_vertex(v, f)).duplicate_vertices == 1
    assert inspect_mesh(*with_zero_area_faces(v, f)).degenerate_faces == 2
    assert inspect_mesh(*with_isolated_vertices(v, f)).isolated_vertices == 2
    assert inspect_mesh(*with_nonmanifold_edge(v, f)).nonmanifold_edges == 1
    assert inspect_mesh(*with_two_components(v, f)).components == 2
    holed = inspect_mesh(*with_hole(v, f))
    assert holed.boundary_edges > 0 and holed.nonmanifold_edges == 0


@pytest.mark.parametrize("name", sorted(BAD_MESHES))
def test_operators_on_bad_meshes_are_finite_and_valid(name):
    v, f = BAD_MESHES[name](*sphere(2))
    k = 12
    ops = compute_operators(v, f, k)
    expected_method = "robust" if name in ("duplicate_vertex", "zero_area_faces", "nonmanifold_edge") else "cotan"
    assert ops.method == expected_method == resolve_method(v, f, "auto")
    for arr in (ops.mass, ops.evals, ops.evecs, ops.frames, ops.grad_x.data, ops.grad_y.data):
        assert np.all(np.isfinite(arr)), name
    assert np.all(ops.mass > 0)
    assert np.all(np.diff(ops.evals) >= 0) and ops.evals.min() >= 0
    gram = ops.evecs.astype(np.float64).T @ (ops.mass[:, None].astype(np.float64) * ops.evecs)
    np.testing.assert_allclose(gram, np.eye(k), atol=1e-5)
    lap, _ = laplacian_and_mass(v, f, ops.method)
    np.testing.assert_allclose(lap @ np.ones(len(v)), 0.0, atol=1e-9)
    if name == "two_components":
        # One zero eigenvalue per component.
        assert np.sum(ops.evals < 1e-4) == 2 and ops.evals[2] > 0.5
    if name == "isolated_vertices":
        # Each isolated vertex is its own component (documented); the mesh keeps the third.
        assert np.sum(ops.evals < 1e-4) == 3 and ops.evals[3] > 0.5


def test_cotan_on_zero_area_faces_stays_finite():
    lap, mass = laplacian_and_mass(*with_zero_area_faces(*sphere(1)), "cotan")
    assert np.all(np.isfinite(lap.data)) and np.all(np.isfinite(mass))


def test_all_faces_degenerate_is_a_clear_error():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    with pytest.raises(ValueError, match="zero total area"):
        laplacian_and_mass(v, np.array([[0, 1, 2], [1, 2, 3]]), "cotan")
    with pytest.raises(ValueError, match="no non-degenerate faces"):
        clean_mesh(v, np.array([[0, 1, 2], [1, 2, 3]]))


def test_clean_mesh_removes_defects_and_maps_vertices():
    v, f = sphere(1)
    bad_v, bad_f = with_isolated_vertices(*with_zero_area_faces(*with_duplicate_vertex(v, f)))
    cleaned = clean_mesh(bad_v, bad_f)
    report = inspect_mesh(cleaned.vertices, cleaned.faces)
    assert (report.duplicate_vertices, report.degenerate_faces, report.isolated_vertices) == (0, 0, 0)
    assert report.boundary_edges == 0 and report.nonmanifold_edges == 0
    # The duplicate folds back onto vertex 0; the isolated ones (and the unused midpoint) are dropped.
    assert cleaned.vertex_map[len(v)] == cleaned.vertex_map[0]
    assert np.all(cleaned.vertex_map[-2:] == -1)
    kept = cleaned.vertex_map >= 0
    np.testing.assert_array_equal(cleaned.vertices[cleaned.vertex_map[kept]], bad_v[kept])
    assert len(cleaned.vertices) == len(v) and len(cleaned.faces) == len(f)
    assert compute_operators(cleaned.vertices, cleaned.faces, 8).method == "cotan"


def test_k_too_large_and_unknown_method_are_clear_errors():
    v, f = sphere(0)
    with pytest.raises(ValueError, match="k must satisfy 1 <= k < V = 12"):
        compute_operators(v, f, 12)
    with pytest.raises(ValueError, match="method must be"):
        resolve_method(v, f, "fem")
    with pytest.raises(ValueError, match="needs faces"):
        laplacian_and_mass(np.random.default_rng(0).random((50, 3)), np.zeros((0, 3), int), "cotan")
