"""Jitted k-means: recovers separated clusters, reaches a Lloyd fixed point, is deterministic."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.audio import kmeans, nearest_centroid
from jaxtalk.audio.kmeans import _kmeans_plus_plus

CENTRES = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]])


def _blobs(seed=0, per=40):
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(4), per)
    return (CENTRES[labels] + 0.5 * rng.standard_normal((4 * per, 3))).astype(np.float32), labels


def test_recovers_separated_blobs(key):
    points, labels = _blobs()
    result = kmeans(points, 4, key=key, iterations=10)
    ids = np.asarray(result.assignments)
    # Each true blob is exactly one cluster, and the centres are the blob means.
    mapping = {label: set(ids[labels == label]) for label in range(4)}
    assert all(len(v) == 1 for v in mapping.values())
    assert len(set.union(*mapping.values())) == 4
    for label, (code,) in mapping.items():
        np.testing.assert_allclose(
            np.asarray(result.centroids)[code], points[labels == label].mean(axis=0), atol=1e-4
        )


@pytest.mark.slow
def test_lloyd_fixed_point_and_inertia(key):
    points = np.random.default_rng(1).standard_normal((300, 5)).astype(np.float32)
    result = kmeans(points, 7, key=key, iterations=60)
    centroids, ids = np.asarray(result.centroids), np.asarray(result.assignments)
    brute = ((points[:, None, :] - centroids[None, :, :]) ** 2).sum(-1)
    np.testing.assert_array_equal(ids, brute.argmin(axis=1))
    for code in range(7):
        np.testing.assert_allclose(centroids[code], points[ids == code].mean(axis=0), atol=1e-5)
    inertia = np.asarray(result.inertia)
    assert inertia.shape == (61,)
    assert np.all(np.diff(inertia) <= 1e-5 * inertia[0])  # Lloyd never increases it
    np.testing.assert_allclose(inertia[-1], brute.min(axis=1).mean(), rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(nearest_centroid(points, centroids)), ids)


def test_deterministic_for_a_key(key):
    points, _ = _blobs(seed=2)
    # Same shapes and sizes as test_recovers_separated_blobs: reuses its compiled program.
    a = kmeans(points, 4, key=key, iterations=10)
    b = kmeans(points, 4, key=key, iterations=10)
    np.testing.assert_array_equal(np.asarray(a.centroids), np.asarray(b.centroids))


def test_plus_plus_seeds_are_distinct_data_points(key):
    points, _ = _blobs(seed=3)
    seeds = np.asarray(_kmeans_plus_plus(jnp.asarray(points), 4, key))
    rows = [np.flatnonzero((points == s).all(axis=1)) for s in seeds]
    assert all(r.size == 1 for r in rows) and len({int(r[0]) for r in rows}) == 4
    # Far-apart blobs: D^2 sampling puts one seed in each blob (fails with uniform seeding often).
    assert len({int(np.argmin(((CENTRES - s) ** 2).sum(1))) for s in seeds}) == 4


@pytest.mark.parametrize(
    ("points", "codes", "iterations", "message"),
    [
        (np.zeros(5, np.float32), 2, 5, "non-empty|points features"),
        (np.zeros((3, 2), np.float32), 4, 5, "num_codes"),
        (np.zeros((3, 2), np.float32), 2, 0, "iterations"),
    ],
)
def test_bad_input_raises(points, codes, iterations, message):
    with pytest.raises((TypeError, ValueError), match=message):
        kmeans(points, codes, key=jax.random.key(0), iterations=iterations)
