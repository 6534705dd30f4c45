"""DTW and discrete Frechet distance: hand-worked cases, a brute-force double loop, invariances."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.metrics import alignment, trajectory_dfd, trajectory_dtw




def brute_force(a: np.ndarray, b: np.ndarray, kind: str) -> float:
    """The textbook O(N M) double loop (Sakoe-Chiba DTW / Eiter-Mannila DFD)."""
    n, m = len(a), len(b)
    d = np.full((n, m), np.inf)
    for i in range(n):
        for j in range(m):
            c = float(np.linalg.norm(a[i] - b[j]))
            if i == 0 and j == 0:
                d[i, j] = c
                continue
            prev = min(d[i - 1, j] if i else np.inf, d[i, j - 1] if j else np.inf,
                       d[i - 1, j - 1] if i and j else np.inf)
            d[i, j] = c + prev if kind == "dtw" else max(c, prev)
    return float(d[-1, -1])


def col(values) -> np.ndarray:
    return np.asarray(values, np.float64)[:, None]


def test_repeated_frame_warps_to_zero(float64):
    a, b = col([0, 1, 2]), col([0, 0, 1, 2])
    assert float(trajectory_dtw(a, b)) == 0.0
    assert float(trajectory_dtw(a, b, normalized=False)) == 0.0
    assert float(trajectory_dfd(a, b)) == 0.0


def test_hand_worked_three_by_two(float64):
    # cost = [[0, 2], [1, 1], [2, 0]]; D = [[0, 2], [1, 1], [3, 1]]: DTW 1 along a 3-cell path.
    # Frechet: F = [[0, 2], [1, 1], [2, 1]] -> 1.
    a, b = col([0, 1, 2]), col([0, 2])
    assert float(trajectory_dtw(a, b, normalized=False)) == pytest.approx(1.0)
    assert float(trajectory_dtw(a, b)) == pytest.approx(1.0 / 3.0)
    assert float(trajectory_dfd(a, b)) == pytest.approx(1.0)


def test_ties_normalise_by_the_shortest_optimal_path(float64):
    # cost rows [0, 1, 2], [2, 1, 0], [2, 1, 0]: the diagonal (3 cells) and (0,0)(0,1)(1,2)(2,2)
    # (4 cells) both cost 1; the mean cost is taken along the shorter one.
    a, b = col([0, 2, 2]), col([0, 1, 2])
    assert float(trajectory_dtw(a, b, normalized=False)) == pytest.approx(1.0)
    assert float(trajectory_dtw(a, b)) == pytest.approx(1.0 / 3.0)


def test_parallel_segments(float64):
    # Two parallel segments h apart, same sampling: every coupling costs >= h, the diagonal exactly h.
    h = 0.3
    s = np.linspace(0.0, 1.0, 8)
    a = np.stack([s, np.zeros_like(s)], axis=1)
    b = a + np.array([0.0, h])
    assert float(trajectory_dfd(a, b)) == pytest.approx(h)
    assert float(trajectory_dtw(a, b)) == pytest.approx(h)
    assert float(trajectory_dtw(a, b, normalized=False)) == pytest.approx(8 * h)


def test_single_point_against_sequence(float64):
    # One point must be coupled with every frame of the other trajectory.
    a = col([0.0])
    b = col([1.0, -2.0, 3.0])
    assert float(trajectory_dtw(a, b, normalized=False)) == pytest.approx(6.0)
    assert float(trajectory_dtw(a, b)) == pytest.approx(2.0)
    assert float(trajectory_dfd(a, b)) == pytest.approx(3.0)


# Sizes straddle the padding buckets (8 -> 16) so that padded cells are exercised.
@pytest.mark.parametrize("n,m,dim", [(1, 1, 2), (7, 8, 3), (9, 6, 1), (13, 16, 4), (16, 11, 6)])
def test_matches_brute_force(float64, n, m, dim):
    rng = np.random.default_rng(n * 100 + m)
    a = rng.normal(size=(n, dim))
    b = rng.normal(size=(m, dim))
    assert float(trajectory_dtw(a, b, normalized=False)) == pytest.approx(brute_force(a, b, "dtw"), rel=1e-12)
    assert float(trajectory_dfd(a, b)) == pytest.approx(brute_force(a, b, "dfd"), rel=1e-12)


def test_symmetric_and_identity(float64):
    rng = np.random.default_rng(3)
    a = rng.normal(size=(12, 3))
    b = rng.normal(size=(15, 3))
    assert float(trajectory_dtw(a, b)) == pytest.approx(float(trajectory_dtw(b, a)))
    assert float(trajectory_dfd(a, b)) == pytest.approx(float(trajectory_dfd(b, a)))
    assert float(trajectory_dtw(a, a)) == 0.0
    assert float(trajectory_dfd(a, a)) == 0.0
    # DFD bounds: at least the endpoint distances, at most the largest pairwise distance.
    ends = max(np.linalg.norm(a[0] - b[0]), np.linalg.norm(a[-1] - b[-1]))
    dfd = float(trajectory_dfd(a, b))
    assert ends - 1e-12 <= dfd <= np.max(np.linalg.norm(a[:, None] - b[None], axis=-1)) + 1e-12


def test_path_length_normalisation(float64):
    # b is a slowed down 2x and shifted by 0.5: every cell costs >= 0.5 and an 8-cell path (the
    # minimum, max(n, m)) costs exactly 0.5 per cell, so the total is 4 and the mean 0.5.
    a = col(np.arange(4.0))
    b = col(np.repeat(np.arange(4.0), 2)) + 0.5
    total = float(trajectory_dtw(a, b, normalized=False))
    assert total == pytest.approx(4.0)
    assert total == pytest.approx(brute_force(a, b, "dtw"))
    assert float(trajectory_dtw(a, b)) == pytest.approx(0.5)


def test_lengths_in_one_bucket_share_a_compilation(float64):
    rng = np.random.default_rng(0)
    trajectory_dtw(rng.normal(size=(10, 2)), rng.normal(size=(11, 2)))
    size = alignment._sweep._cache_size()
    trajectory_dtw(rng.normal(size=(13, 5)), rng.normal(size=(16, 5)))
    trajectory_dfd(rng.normal(size=(9, 1)), rng.normal(size=(12, 1)))
    assert alignment._sweep._cache_size() == size


@pytest.mark.parametrize(
    "a,b,match",
    [
        (np.zeros(4), np.zeros((4, 1)), "2 dimensions"),
        (np.zeros((3, 2)), np.zeros((3, 3)), "same point dimension"),
        (np.zeros((0, 2)), np.zeros((3, 2)), "at least 1 frame"),
        (np.array([[0.0], [np.nan]]), np.zeros((3, 1)), "non-finite"),
    ],
)
def test_bad_input(no_typecheck, float64, a, b, match):
    with pytest.raises(ValueError, match=match):
        trajectory_dtw(a, b)
    with pytest.raises(ValueError, match=match):
        trajectory_dfd(a, b)
