"""DualTalk conversation metrics: closed forms (Gaussian FD, entropy, Pearson), wiring, errors."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.metrics import (
    PUBLISHED_SCALE,
    conversation,
    conversation_metrics,
    frechet_distance,
    gaussian_frechet_distance,
    gaussian_statistics,
    rpcc,
    sid,
)

JAW = slice(50, 53)




def random_params(frames: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(frames, 56))


# ------------------------------------------------------------------------------ Frechet distance


def test_fd_of_two_1d_gaussians_by_hand():
    # x: mean 1, unbiased var 2; y: mean 3, var (4 + 1 + 9) / 2 = 7.
    # FD = (1 - 3)^2 + 2 + 7 - 2 sqrt(14).
    x = np.array([0.0, 2.0])
    y = np.array([1.0, 2.0, 6.0])
    assert frechet_distance(x, y) == pytest.approx(13.0 - 2.0 * np.sqrt(14.0))
    mu, cov = gaussian_statistics(y)
    np.testing.assert_allclose(mu, [3.0])
    np.testing.assert_allclose(cov, [[7.0]])


def test_fd_diagonal_covariances():
    # Commuting covariances: FD = |dmu|^2 + sum (sqrt s1 - sqrt s2)^2 = 1 + 1 + 4.
    fd = gaussian_frechet_distance(np.array([0.0, 1.0]), np.diag([4.0, 9.0]), np.array([1.0, 1.0]), np.eye(2))
    assert fd == pytest.approx(6.0)


def test_fd_matches_2x2_closed_form():
    # S1 S2 has positive eigenvalues, so tr sqrt(S1 S2) = sqrt(tr(S1 S2) + 2 sqrt(det S1 det S2)).
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 2)), rng.normal(size=(2, 2))
    s1, s2 = a @ a.T + 0.1 * np.eye(2), b @ b.T + 0.1 * np.eye(2)
    mu1, mu2 = rng.normal(size=2), rng.normal(size=2)
    tr_sqrt = np.sqrt(np.trace(s1 @ s2) + 2 * np.sqrt(np.linalg.det(s1) * np.linalg.det(s2)))
    expected = np.sum((mu1 - mu2) ** 2) + np.trace(s1) + np.trace(s2) - 2 * tr_sqrt
    assert gaussian_frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, rel=1e-10)


def test_fd_identity_and_symmetry():
    x = np.random.default_rng(1).normal(size=(80, 6))
    y = np.random.default_rng(2).normal(size=(70, 6)) * 2.0 + 1.0
    assert frechet_distance(x, x) == pytest.approx(0.0, abs=1e-9)
    assert frechet_distance(x, y) == pytest.approx(frechet_distance(y, x), rel=1e-9)


def test_fd_singular_covariance_is_handled():
    # A constant feature makes both covariances singular; it contributes nothing to the distance.
    x = np.array([0.0, 2.0, 1.0, 3.0])
    y = np.array([1.0, 2.0, 6.0, 0.5])
    const = np.full(4, 7.0)
    fd = frechet_distance(np.stack([x, const], 1), np.stack([y, const], 1))
    assert fd == pytest.approx(frechet_distance(x, y), abs=1e-6)


def test_fd_retries_with_a_diagonal_offset(monkeypatch):
    # When sqrtm of the product is not finite, eps is added to both diagonals and it is recomputed:
    # FD = |dmu|^2 + sum (s1 + s2 - 2 sqrt((s1 + eps)(s2 + eps))) for diagonal covariances.
    calls = []

    def flaky_sqrtm(a):
        calls.append(a.copy())
        return np.full_like(a, np.nan) if len(calls) == 1 else real_sqrtm(a)

    real_sqrtm = conversation._sqrtm
    monkeypatch.setattr(conversation, "_sqrtm", flaky_sqrtm)
    s1, s2, eps = np.array([4.0, 0.0]), np.array([1.0, 0.0]), 1e-2
    fd = gaussian_frechet_distance(np.zeros(2), np.diag(s1), np.ones(2), np.diag(s2), eps=eps)
    expected = 2.0 + np.sum(s1 + s2 - 2 * np.sqrt((s1 + eps) * (s2 + eps)))
    assert fd == pytest.approx(expected)
    assert len(calls) == 2
    np.testing.assert_allclose(calls[1], np.diag((s1 + eps) * (s2 + eps)))


def test_fd_rejects_a_large_imaginary_part():
    # Not a covariance: cov1 @ cov2 = diag(-1, 1) has square root diag(i, 1).
    with pytest.raises(ValueError, match="imaginary component"):
        gaussian_frechet_distance(np.zeros(2), np.eye(2), np.zeros(2), np.diag([-1.0, 1.0]))


# ------------------------------------------------------------------------------------------- SID

CENTRES = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])


def clustered(counts: list[int], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = [CENTRES[c] + 0.01 * rng.normal(size=(n, 2)) for c, n in enumerate(counts)]
    return np.concatenate(points)


def test_sid_uniform_labels_is_log2_k():
    assert sid(clustered([5, 5, 5, 5]), CENTRES, 4) == pytest.approx(2.0, abs=1e-4)


def test_sid_hand_histograms():
    fit = clustered([5, 5, 5, 5])
    # Labels 2:1:1:0 -> p = (1/2, 1/4, 1/4, 0): H = 1.5 bits.
    assert sid(fit, CENTRES[[0, 0, 1, 2]], 4) == pytest.approx(1.5, abs=1e-4)
    # One cluster -> 0 bits (the +1e-6 inside the log leaves ~1e-6).
    assert sid(fit, CENTRES[[3, 3, 3]], 4) == pytest.approx(0.0, abs=1e-4)


# ------------------------------------------------------------------------------------------ rPCC


@pytest.mark.parametrize(
    "pred,expected",
    [([1.0, 2.0, 3.0, 4.0], 0.0), ([1.0, 3.0, 2.0, 4.0], 0.2), ([-1.0, -2.0, -3.0, -4.0], 2.0),
     ([5.0, 5.0, 5.0, 5.0], 1.0)],
)
def test_rpcc_by_hand(pred, expected):
    # gt == partner (corr 1). [1, 3, 2, 4] vs [1, 2, 3, 4]: centred dot 4, norms sqrt 5 -> corr 0.8.
    # A constant prediction has no correlation (counted as 0).
    partner = np.array([[1.0], [2.0], [3.0], [4.0]])
    assert rpcc(np.array(pred)[:, None], partner, partner) == pytest.approx(expected)


# ---------------------------------------------------------------------------- conversation_metrics


def test_perfect_prediction():
    gt, partner = random_params(60, 0), random_params(60, 1)
    m = conversation_metrics(gt, gt, partner, sid_convention="fit_gt")
    for g in ("exp", "jaw", "pose"):
        # P-FD exp has 100 features from 60 frames: a singular covariance, so sqrtm is only
        # accurate to ~1e-8 of the trace (~100).
        assert m[f"FD_{g}"] == pytest.approx(0.0, abs=1e-5)
        assert m[f"P-FD_{g}"] == pytest.approx(0.0, abs=1e-5)
        assert m[f"MSE_{g}"] == 0.0
        assert m[f"rPCC_{g}"] == pytest.approx(0.0, abs=1e-12)
    assert "SID_fit_pred_exp" not in m


def test_group_split_mse_fd_pfd_and_scaling():
    gt, partner = random_params(60, 0), random_params(60, 1)
    pred = gt.copy()
    pred[:, JAW] += 0.1  # a pure mean shift of the jaw
    m = conversation_metrics(pred, gt, partner, sid_convention=None)
    assert m["MSE_jaw"] == pytest.approx(0.01)
    assert m["MSE_exp"] == 0.0 and m["MSE_pose"] == 0.0
    assert m["FD_jaw"] == pytest.approx(0.03)  # |dmu|^2 = 3 * 0.1^2, covariances equal
    assert m["FD_exp"] == pytest.approx(0.0, abs=1e-8)
    # P-FD puts the partner's group first: a shift of the agent's half only.
    assert m["P-FD_jaw"] == pytest.approx(0.03)
    assert m["P-FD_jaw"] == pytest.approx(frechet_distance(np.hstack([partner[:, JAW], gt[:, JAW]]),
                                                           np.hstack([partner[:, JAW], pred[:, JAW]])))
    scaled = conversation_metrics(pred, gt, partner, sid_convention=None, scaled=True)
    assert scaled["MSE_jaw"] == pytest.approx(10.0)  # x 1e3
    assert scaled["FD_jaw"] == pytest.approx(30.0)  # x 1e3
    for key, value in m.items():
        assert scaled[key] == pytest.approx(value * PUBLISHED_SCALE.get(key, 1.0))
    assert PUBLISHED_SCALE["MSE_exp"] == 10.0 and PUBLISHED_SCALE["rPCC_exp"] == 100.0


def test_sid_conventions_are_named_and_differ():
    # Jaw: gt visits 10 well-separated clusters equally; pred visits each once, then stays in cluster 0.
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(10, 3)) * 10.0
    gt, partner = random_params(100, 1), random_params(100, 2)
    pred = random_params(100, 3)
    gt[:, JAW] = np.repeat(centres, 10, axis=0) + 0.01 * rng.normal(size=(100, 3))
    pred[:, JAW] = np.concatenate([centres, np.repeat(centres[:1], 90, axis=0)]) + 0.01 * rng.normal(size=(100, 3))
    m = conversation_metrics(pred, gt, partner)
    # Fit on gt, count pred: 91 / 100 in one cluster, 1 / 100 in each of 9 others.
    p = np.array([0.91] + [0.01] * 9)
    assert m["SID_fit_gt_jaw"] == pytest.approx(-np.sum(p * np.log2(p)), abs=1e-4)
    # Fit on pred (DualTalk's script), count gt: uniform over 10 clusters.
    assert m["SID_fit_pred_jaw"] == pytest.approx(np.log2(10), abs=1e-4)
    # The other groups are wired to the same function with k = 40 (exp) and 10 (pose).
    assert m["SID_fit_gt_exp"] == pytest.approx(sid(gt[:, :50], pred[:, :50], 40))
    assert m["SID_fit_pred_pose"] == pytest.approx(sid(pred[:, 53:], gt[:, 53:], 10))


def test_list_of_files_is_the_mean_of_files_and_truncation():
    files = [(random_params(12, s), random_params(12, s + 10), random_params(12, s + 20)) for s in range(2)]
    per_file = [conversation_metrics(*f, sid_convention=None) for f in files]
    both = conversation_metrics(*[list(col) for col in zip(*files, strict=True)], sid_convention=None)
    for key in both:
        assert both[key] == pytest.approx((per_file[0][key] + per_file[1][key]) / 2)
    pred, gt, partner = files[0]
    cut = conversation_metrics(pred, gt[:10], partner, sid_convention=None, truncate=True)
    assert cut == pytest.approx(conversation_metrics(pred[:10], gt[:10], partner[:10], sid_convention=None))


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: conversation_metrics(np.zeros((50, 55)), np.zeros((50, 56)), np.zeros((50, 56))), r"\(frames, 56\)"),
        (lambda: conversation_metrics(np.full((50, 56), np.nan), random_params(50, 0), random_params(50, 1)),
         "pred56 contains"),
        (lambda: conversation_metrics(random_params(50, 0), random_params(49, 1), random_params(50, 2)),
         "truncate=True"),
        (lambda: conversation_metrics(random_params(30, 0), random_params(30, 1), random_params(30, 2)),
         "at least 40 frames"),
        (lambda: conversation_metrics(random_params(9, 0), random_params(9, 1), random_params(9, 2),
                                      sid_convention="dualtalk"), "sid_convention"),
        (lambda: conversation_metrics([random_params(9, 0)], random_params(9, 1), [random_params(9, 2)]), "mix"),
        (lambda: conversation_metrics([], [], []), "non-empty"),
        (lambda: conversation_metrics([random_params(50, 0), random_params(3, 0)], [random_params(50, 1)] * 2,
                                      [random_params(50, 2)] * 2, sid_convention=None), "file 1"),
        (lambda: frechet_distance(np.zeros((1, 2)), np.zeros((5, 2))), "at least 2 rows"),
        (lambda: frechet_distance(np.zeros((4, 2)), np.zeros((5, 3))), "same feature dimension"),
        (lambda: sid(np.zeros((3, 2)), np.zeros((5, 2)), 4), "at least 4 rows"),
        (lambda: rpcc(np.zeros((4, 1)), np.zeros((5, 1)), np.zeros((4, 1))), "same shape"),
    ],
)
def test_bad_input(no_typecheck, call, match):
    with pytest.raises(ValueError, match=match):
        call()
