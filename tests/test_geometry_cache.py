"""Disk cache of operators: keyed by mesh + method, reused with smaller k, atomic, robust to corruption."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from jaxtalk.geometry import cache
from jaxtalk.geometry import operators as ops_mod
from jaxtalk.geometry.operators import compute_operators


@pytest.fixture
def mesh():
    m = trimesh.creation.icosphere(2)
    rng = np.random.default_rng(0)
    return np.asarray(m.vertices) * (1 + 0.05 * rng.random((len(m.vertices), 1))), np.asarray(m.faces)


@pytest.fixture
def count_eigensolves(monkeypatch):
    calls = []
    real = ops_mod.eigen_decomposition

    def counting(*args, **kwargs):
        calls.append(args[2])
        return real(*args, **kwargs)

    monkeypatch.setattr(ops_mod, "eigen_decomposition", counting)
    return calls


def assert_same(a, b):
    np.testing.assert_array_equal(a.mass, b.mass)
    np.testing.assert_array_equal(a.evals, b.evals)
    np.testing.assert_array_equal(a.evecs, b.evecs)
    np.testing.assert_array_equal(a.frames, b.frames)
    assert (a.grad_x != b.grad_x).nnz == 0 and (a.grad_y != b.grad_y).nnz == 0
    assert a.method == b.method


def test_cache_hit_and_reuse_with_smaller_k(tmp_path, mesh, count_eigensolves):
    v, f = mesh
    first = compute_operators(v, f, 20, cache_dir=tmp_path)
    assert count_eigensolves == [20]
    assert len(os.listdir(tmp_path)) == 1
    again = compute_operators(v, f, 20, cache_dir=tmp_path)
    smaller = compute_operators(v, f, 8, cache_dir=tmp_path)
    assert count_eigensolves == [20]  # both served from disk
    assert_same(again, first)
    assert smaller.k == 8
    np.testing.assert_array_equal(smaller.evecs, first.evecs[:, :8])
    np.testing.assert_array_equal(smaller.evals, first.evals[:8])


def test_larger_k_recomputes_and_replaces_entry(tmp_path, mesh, count_eigensolves):
    v, f = mesh
    compute_operators(v, f, 8, cache_dir=tmp_path)
    bigger = compute_operators(v, f, 16, cache_dir=tmp_path)
    assert count_eigensolves == [8, 16] and bigger.k == 16
    compute_operators(v, f, 12, cache_dir=tmp_path)
    assert count_eigensolves == [8, 16]
    # Only the final entry is left: no temporary files from the atomic writes.
    assert [p for p in os.listdir(tmp_path)] == [os.path.basename(cache.cache_path(tmp_path, cache.cache_key(v, f, "cotan")))]


def test_key_depends_on_vertices_faces_and_method(mesh):
    v, f = mesh
    base = cache.cache_key(v, f, "cotan")
    assert base == cache.cache_key(v.copy(), f.astype(np.int32), "cotan")
    moved = v.copy()
    moved[3, 1] += 1e-9
    assert cache.cache_key(moved, f, "cotan") != base
    assert cache.cache_key(v, f[:, [1, 2, 0]], "cotan") != base
    assert cache.cache_key(v, f, "robust") != base


def test_corrupt_entry_is_recomputed(tmp_path, mesh, count_eigensolves):
    v, f = mesh
    path = cache.cache_path(tmp_path, cache.cache_key(v, f, "cotan"))
    os.makedirs(tmp_path, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(b"not an npz file")
    ops = compute_operators(v, f, 6, cache_dir=tmp_path)
    assert count_eigensolves == [6]
    assert_same(cache.load(tmp_path, cache.cache_key(v, f, "cotan"), 6), ops)


def test_failed_write_leaves_no_partial_file(tmp_path, mesh, monkeypatch):
    v, f = mesh
    ops = compute_operators(v, f, 6)

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(cache.np, "savez", boom)
    with pytest.raises(OSError, match="disk full"):
        cache.save(tmp_path, "abc", ops)
    assert os.listdir(tmp_path) == []
