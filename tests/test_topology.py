"""Topology variants: manifold, different vertex counts, exact maps onto the base surface."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from jaxtalk.face import builtin_face
from jaxtalk.geometry.topology import KINDS, make_variant, mesh_summary


@pytest.fixture(scope="module")
def base():
    face = builtin_face(resolution="low")
    return np.asarray(face.template, np.float64), np.asarray(face.faces)


@pytest.fixture(scope="module")
def variants(base):
    vertices, faces = base
    return {kind: make_variant(vertices, faces, kind, seed=0) for kind in KINDS}


def test_mesh_summary_detects_defects():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    ok = mesh_summary(square, np.array([[0, 1, 2], [0, 2, 3]]))
    assert ok["manifold"] and ok["boundary_loops"] == 1 and ok["components"] == 1
    sphere = trimesh.creation.icosphere(subdivisions=1)
    closed = mesh_summary(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    assert closed["manifold"] and closed["boundary_loops"] == 0
    bowtie_v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [-1, 0, 0], [-1, -1, 0]], float)
    bowtie = mesh_summary(bowtie_v, np.array([[0, 1, 2], [0, 3, 4]]))
    assert bowtie["nonmanifold_vertices"] == 1 and not bowtie["manifold"]
    fin_v = np.concatenate([square, [[0.5, 0.5, 1.0]]])
    fin = mesh_summary(fin_v, np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4]]))
    assert fin["nonmanifold_edges"] == 1 and not fin["manifold"]
    flipped = mesh_summary(square, np.array([[0, 1, 2], [0, 3, 2]]))
    assert not flipped["winding_consistent"] and not flipped["manifold"]
    two = mesh_summary(np.concatenate([square, square + 5]), np.array([[0, 1, 2], [4, 5, 6]]))
    assert two["components"] == 2 and two["unreferenced_vertices"] == 2


@pytest.mark.parametrize("kind", KINDS)
def test_variant_is_a_manifold_disk_with_its_own_vertex_count(base, variants, kind):
    vertices, faces = base
    var = variants[kind]
    summary = mesh_summary(var.vertices, var.faces)
    assert summary["manifold"], summary
    assert summary["components"] == 1 and summary["boundary_loops"] <= 1
    if kind == "shuffled":
        assert len(var.vertices) == len(vertices) and not np.array_equal(var.vertices, vertices)
    else:
        assert abs(len(var.vertices) - len(vertices)) > 0.1 * len(vertices)
    # Same orientation as the base: normals face the viewer (+z) on average.
    assert trimesh.Trimesh(var.vertices, var.faces, process=False).face_normals[:, 2].mean() > 0.5


@pytest.mark.parametrize("kind", KINDS)
def test_transfer_of_the_template_reproduces_the_variant(base, variants, kind):
    vertices, faces = base
    var = variants[kind]
    np.testing.assert_allclose(var.transfer(vertices), var.vertices, atol=1e-9)
    # Every variant vertex lies on the base surface (an independent check of face + barycentric).
    _, dist, _ = trimesh.proximity.closest_point(trimesh.Trimesh(vertices, faces, process=False), var.vertices)
    assert dist.max() < 1e-6  # sub-micron: trimesh's own closest-point tolerance
    assert np.all(var.barycentric >= -1e-12) and np.allclose(var.barycentric.sum(axis=1), 1.0)


@pytest.mark.parametrize("kind", KINDS)
def test_rigid_motion_transfers_as_the_same_rigid_motion(base, variants, kind):
    vertices, _ = base
    var = variants[kind]
    rots = Rotation.from_rotvec([[0.1, 0.2, -0.3], [0.0, 0.0, 0.0], [-0.4, 0.1, 0.05]]).as_matrix()
    shifts = np.array([[0.01, -0.02, 0.03], [0.0, 0.0, 0.0], [0.05, 0.0, -0.01]])
    seq = np.einsum("tab,vb->tva", rots, vertices) + shifts[:, None, :]
    expected = np.einsum("tab,vb->tva", rots, var.vertices) + shifts[:, None, :]
    np.testing.assert_allclose(var.transfer(seq), expected, atol=1e-9)


def test_subdivision_map_commutes_with_deformation(base, variants):
    # Subdividing a deformed base gives exactly the transferred deformation (midpoints are linear).
    vertices, faces = base
    rng = np.random.default_rng(0)
    deformed = vertices + 0.003 * rng.normal(size=vertices.shape)
    sub_v, sub_f = trimesh.remesh.subdivide(deformed, faces)
    var = variants["subdivided"]
    np.testing.assert_array_equal(sub_f, var.faces)
    np.testing.assert_allclose(var.transfer(deformed), sub_v, atol=1e-12)


def test_shuffle_is_a_permutation_of_the_base(base, variants):
    vertices, faces = base
    var = variants["shuffled"]
    rng = np.random.default_rng(1)
    moved = vertices + 0.01 * rng.normal(size=vertices.shape)
    perm = np.array([np.flatnonzero(np.all(vertices == v, axis=1))[0] for v in var.vertices])
    assert sorted(perm.tolist()) == list(range(len(vertices)))
    np.testing.assert_array_equal(var.transfer(moved), moved[perm])
    # Same triangles up to relabelling and a cyclic corner shift.
    as_base = {tuple(np.roll(f, -int(np.argmin(f)))) for f in perm[var.faces]}
    assert as_base == {tuple(np.roll(f, -int(np.argmin(f)))) for f in faces}


def test_jax_input_gives_jax_output_and_jits(base, variants):
    vertices, _ = base
    var = variants["retriangulated"]
    seq = np.stack([vertices, 1.1 * vertices])
    got = jax.jit(var.transfer)(jnp.asarray(seq, jnp.float32))
    assert isinstance(got, jax.Array) and got.shape == (2, len(var.vertices), 3)
    np.testing.assert_allclose(np.asarray(got), var.transfer(seq), atol=1e-6)


def test_same_seed_same_variant_other_seed_other_variant(base):
    vertices, faces = base
    a, b = make_variant(vertices, faces, "retriangulated", 5), make_variant(vertices, faces, "retriangulated", 5)
    c = make_variant(vertices, faces, "retriangulated", 6)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)


def test_bad_inputs_raise(base, variants):
    vertices, faces = base
    with pytest.raises(ValueError, match="unknown topology variant kind 'remeshed'"):
        make_variant(vertices, faces, "remeshed")
    with pytest.raises(ValueError, match="vertices must have shape"):
        make_variant(vertices[:, :2], faces, "subdivided")
    bad = vertices.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        make_variant(bad, faces, "subdivided")
    with pytest.raises(ValueError, match="face indices must lie in"):
        make_variant(vertices, faces + len(vertices), "decimated")
    sphere = trimesh.creation.icosphere(subdivisions=2)
    with pytest.raises(ValueError, match="closed mesh"):
        make_variant(np.asarray(sphere.vertices), np.asarray(sphere.faces), "retriangulated")
    with pytest.raises(ValueError, match="base_vertex_seq must end in"):
        variants["decimated"].transfer(vertices[:10])
