"""Vertex metrics on small sequences whose answers are worked out by hand, plus invariances and errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.metrics import delta_cd, delta_m, dfd, dtw, fdd, fdd_batch, jitter, lve, mod, mve, vertex




def zeros(frames: int = 2, verts: int = 4) -> np.ndarray:
    return np.zeros((frames, verts, 3))


# --------------------------------------------------------------------------------------------- LVE


def test_lve_is_max_squared_error_over_lips(float64):
    gt = zeros(2, 4)
    pred = gt.copy()
    lips = np.array([0, 1])
    pred[0, 0] = [1.0, 0, 0]  # |e|^2 = 1
    pred[0, 1] = [0, 2.0, 0]  # |e|^2 = 4  <- frame 0 max
    pred[1, 1] = [0, 0, 3.0]  # |e|^2 = 9  <- frame 1 max
    pred[:, 3] = [100.0, 0, 0]  # not a lip vertex: ignored
    assert float(lve(pred, gt, lips)) == pytest.approx((4.0 + 9.0) / 2)


def test_lve_constant_offset(float64):
    gt = np.random.default_rng(0).normal(size=(5, 6, 3))
    offset = np.array([0.1, -0.2, 0.2])
    assert float(lve(gt + offset, gt, np.arange(3))) == pytest.approx(0.09)


def test_lve_gradient_inside_jit(float64):
    # Traced inputs pass the checks; the gradient of the max is 2 e / T at the arg-max vertex.
    gt = zeros(2, 3)
    pred = gt.copy()
    pred[0, 1] = [0.5, 0, 0]
    pred[1, 2] = [0, 1.0, 0]
    grad = jax.jit(jax.grad(lambda p: lve(p, gt, np.array([1, 2]))))(jnp.asarray(pred))
    expected = np.zeros_like(pred)
    expected[0, 1] = [0.5, 0, 0]  # 2 * 0.5 / 2
    expected[1, 2] = [0, 1.0, 0]  # 2 * 1.0 / 2
    np.testing.assert_allclose(np.asarray(grad), expected)


# --------------------------------------------------------------------------------------------- MVE


def test_mve_hand_and_identity(float64):
    gt = np.random.default_rng(1).normal(size=(3, 4, 3))
    pred = gt.copy()
    pred[:, :2] += np.array([3.0, 4.0, 0.0])  # error 5 on half the vertices
    assert float(mve(pred, gt)) == pytest.approx(2.5)
    assert float(mve(gt, gt)) == 0.0


# --------------------------------------------------------------------------------------------- FDD


def sinusoid(frames: int, amplitude: float, verts: int = 3) -> np.ndarray:
    t = np.arange(frames)
    v = zeros(frames, verts)
    v[:, 0, 0] = amplitude * np.sin(2 * np.pi * t / 20)
    return v


def test_fdd_of_a_sinusoid(float64):
    # ||v_t - tmpl||^2 = A^2 sin^2(w t) = A^2 (1 - cos 2wt) / 2; over whole periods its std is
    # A^2 / (2 sqrt 2). One upper vertex moves in gt, none in pred: FDD = that std.
    amplitude = 0.3
    gt = sinusoid(40, amplitude)
    pred = zeros(40, 3)
    template = np.zeros((3, 3))
    expected = amplitude**2 / (2 * np.sqrt(2))
    assert float(fdd(pred, gt, template, [0])) == pytest.approx(expected)
    # Averaged over upper vertices (vertex 1 is still in both) and signed: gt - pred.
    assert float(fdd(pred, gt, template, [0, 1])) == pytest.approx(expected / 2)
    assert float(fdd(gt, pred, template, [0])) == pytest.approx(-expected)
    assert float(fdd(gt, gt, template, [0, 1, 2])) == pytest.approx(0.0, abs=1e-15)


def test_fdd_batch_is_mean_over_sequences(float64):
    a, b = 0.3, 0.5
    gts = [sinusoid(40, a), sinusoid(20, b)]
    preds = [zeros(40, 3), zeros(20, 3)]
    template = np.zeros((3, 3))
    expected = (a**2 + b**2) / (2 * np.sqrt(2)) / 2
    assert float(fdd_batch(preds, gts, template, [0])) == pytest.approx(expected)
    assert float(fdd_batch(preds, gts, [template, template], [0])) == pytest.approx(expected)


# --------------------------------------------------------------------------------------------- MOD


def mouth(openings: np.ndarray) -> np.ndarray:
    # Vertices 0, 1 upper lip at y = +h/2, vertices 2, 3 lower lip at y = -h/2 (x = -1, +1).
    v = zeros(len(openings), 5)
    for k, x in enumerate([-1.0, 1.0]):
        v[:, k] = np.stack([np.full_like(openings, x), openings / 2, 0 * openings], axis=1)
        v[:, 2 + k] = np.stack([np.full_like(openings, x), -openings / 2, 0 * openings], axis=1)
    return v


def test_mod_hand(float64):
    gt = mouth(np.array([0.0, 1.0, 2.0]))
    pred = mouth(np.array([0.5, 1.0, 1.0]))
    assert float(mod(pred, gt, [0, 1], [2, 3])) == pytest.approx((0.5 + 0 + 1.0) / 3)
    assert float(mod(pred, gt, [0, 1], [2, 3], paired=True)) == pytest.approx((0.5 + 0 + 1.0) / 3)
    assert float(mod(gt, gt, [0, 1], [2, 3])) == 0.0


def test_mod_regions_of_different_sizes(float64):
    # Centroid openings work for unequal sets: upper {0, 1} has centroid (0, h/2), lower {2} is the
    # point (-1, -h/2), so the opening is sqrt(1 + h^2).
    gt = mouth(np.array([1.0, 3.0]))
    pred = mouth(np.array([2.0, 2.0]))
    expected = (abs(np.sqrt(5) - np.sqrt(2)) + abs(np.sqrt(5) - np.sqrt(10))) / 2
    assert float(mod(pred, gt, np.array([0, 1]), np.array([2]))) == pytest.approx(expected)


def test_mod_centroid_versus_paired(float64):
    # Pairs (0, 3) and (1, 2) cross: paired distance sqrt(4 + h^2), centroid distance h.
    h = 2.0
    gt = mouth(np.array([h]))
    pred = mouth(np.array([0.0]))
    assert float(mod(pred, gt, [0, 1], [3, 2])) == pytest.approx(h)
    assert float(mod(pred, gt, [0, 1], [3, 2], paired=True)) == pytest.approx(np.sqrt(4 + h**2) - 2.0)


# ------------------------------------------------------------------------------------ DTW and DFD


def lips(frames: int) -> np.ndarray:
    t = np.arange(frames, dtype=np.float64)
    v = zeros(frames, 4)
    v[:, 0, 1] = np.sin(t / 3)
    v[:, 1, 1] = -np.sin(t / 3)
    v[:, 2, 0] = t  # not a lip vertex
    return v


def test_dtw_dfd_identity_and_time_warp(float64):
    gt = lips(4)
    slowed = np.repeat(gt, 2, axis=0)  # every frame held twice: a pure time warp of the lips
    assert float(dtw(gt, gt, [0, 1])) == 0.0
    assert float(dfd(gt, gt, [0, 1])) == 0.0
    assert float(dtw(slowed, gt, [0, 1])) == 0.0
    assert float(dfd(slowed, gt, [0, 1])) == 0.0


def test_dtw_dfd_constant_lip_offset(float64):
    # Offsetting both lip vertices by o moves every frame by sqrt(2) |o| in R^6.
    gt = lips(8)
    pred = gt.copy()
    pred[:, :2] += np.array([0.0, 0.0, 0.25])
    assert float(dfd(pred, gt, [0, 1])) == pytest.approx(np.sqrt(2) * 0.25)
    assert float(dtw(pred, gt, [0, 1])) == pytest.approx(np.sqrt(2) * 0.25)
    assert float(dtw(pred, gt, [0, 1], normalized=False)) == pytest.approx(8 * np.sqrt(2) * 0.25)


# ----------------------------------------------------------------------------- delta_M, delta_Cd


def drift(frames: int, step: list[float], verts: int = 2) -> np.ndarray:
    return np.broadcast_to(np.arange(frames)[:, None, None] * np.asarray(step, np.float64), (frames, verts, 3)).copy()


def test_delta_m_hand(float64):
    pred = drift(4, [1.0, 0, 0])
    gt = drift(4, [0, 1.0, 0])
    assert float(delta_m(pred, gt)) == pytest.approx(2.0)  # ||(1, -1, 0)||^2
    # Only motion counts: a constant offset costs nothing.
    assert float(delta_m(gt + 5.0, gt)) == pytest.approx(0.0)


@pytest.mark.parametrize(
    "step_pred,step_gt,expected",
    [([1.0, 0, 0], [0, 2.0, 0], 1.0), ([1.0, 0, 0], [-3.0, 0, 0], 2.0), ([1.0, 1.0, 0], [2.0, 2.0, 0], 0.0),
     ([0, 0, 0], [0, 0, 0], 0.0), ([0, 0, 0], [0, 1.0, 0], 1.0)],
)
def test_delta_cd_hand(float64, step_pred, step_gt, expected):
    assert float(delta_cd(drift(3, step_pred), drift(3, step_gt))) == pytest.approx(expected)


def test_delta_cd_eps_is_traced(float64):
    # eps is a swept numeric knob: changing it must not recompile. 0.5 per frame is "still" at
    # eps = 1 (both still -> 0) but a direction at eps = 0.1 (opposite -> 2).
    pred, gt = drift(3, [0.5, 0, 0]), drift(3, [-0.5, 0, 0])
    assert float(delta_cd(pred, gt, eps=1.0)) == 0.0
    size = vertex._delta_cd._cache_size()
    assert float(delta_cd(pred, gt, eps=0.1)) == pytest.approx(2.0)
    assert vertex._delta_cd._cache_size() == size


def test_delta_region_subset(float64):
    pred = drift(3, [1.0, 0, 0], verts=3)
    gt = pred.copy()
    gt[:, 2] = drift(3, [-1.0, 0, 0], verts=1)[:, 0]  # vertex 2 moves the opposite way
    assert float(delta_cd(pred, gt, [0, 1])) == 0.0
    assert float(delta_cd(pred, gt)) == pytest.approx(2.0 / 3.0)
    assert float(delta_m(pred, gt, [2])) == pytest.approx(4.0)


# ------------------------------------------------------------------------------------------ jitter


def test_jitter_quadratic_and_linear(float64):
    t = np.arange(6.0)[:, None]
    assert float(jitter(np.concatenate([t**2, 0 * t], axis=1))) == pytest.approx(2.0)
    assert float(jitter(3.0 * t + 1.0)) == pytest.approx(0.0)


def test_jitter_near_boundaries(float64):
    # A unit step at the chunk boundary b = 5: second differences +1 at frame 4 and -1 at frame 5.
    frames, b = 12, 5
    x = (np.arange(frames) >= b).astype(np.float64)[:, None]
    assert float(jitter(x)) == pytest.approx(2.0 / (frames - 2))
    assert float(jitter(x, [b], window=2)) == pytest.approx(2.0 / 4)  # frames 3, 4, 5, 6
    assert float(jitter(x, [b], window=1)) == pytest.approx(1.0)  # frames 4, 5
    # A second boundary with no step halves the boundary jitter; overlapping windows count once.
    assert float(jitter(x, [b, 9], window=2)) == pytest.approx(2.0 / 8)
    assert float(jitter(x, [b, 6], window=2)) == pytest.approx(2.0 / 5)  # frames 3 .. 7


def test_jitter_vertices_average_per_vertex_norms(float64):
    v = zeros(5, 2)
    v[:, 0, 0] = np.arange(5.0) ** 2  # acceleration 2 on vertex 0, 0 on vertex 1
    assert float(jitter(v)) == pytest.approx(1.0)


# ------------------------------------------------------------------------------------------ errors


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: mve(zeros(2, 4), zeros(3, 4)), "same shape"),
        (lambda: mve(zeros(2, 4), zeros(2, 5)), "same shape"),
        (lambda: mve(np.zeros((2, 4, 2)), np.zeros((2, 4, 2))), "trailing shape"),
        (lambda: mve(np.full((2, 4, 3), np.nan), zeros(2, 4)), "pred contains 24 non-finite"),
        (lambda: lve(zeros(), zeros(), np.array([], np.int64)), "lip_idx is empty"),
        (lambda: lve(zeros(), zeros(), [0, 4]), "out of range"),
        (lambda: lve(zeros(), zeros(), np.array([0.0, 1.0])), "integers"),
        (lambda: fdd(zeros(), zeros(), np.zeros((3, 3)), [0]), r"template must have shape \(4, 3\)"),
        (lambda: fdd_batch([zeros()], [zeros(), zeros()], np.zeros((4, 3)), [0]), "equal length"),
        (lambda: fdd_batch([zeros(), zeros()], [zeros(), zeros(3)], np.zeros((4, 3)), [0]), "sequence 1"),
        (lambda: mod(zeros(), zeros(), [0, 1], [2], paired=True), "equal length"),
        (lambda: dtw(zeros(3, 4), zeros(3, 5), [0]), "same vertex count"),
        (lambda: delta_m(zeros(1), zeros(1)), "at least 2 frame"),
        (lambda: delta_cd(zeros(), zeros(), eps=-1.0), "eps must be >= 0"),
        (lambda: jitter(np.zeros((2, 3))), "at least 3 frame"),
        (lambda: jitter(np.zeros(5)), r"\(T, D\) or vertices"),
        (lambda: jitter(np.zeros((6, 2)), [6]), r"in \[1, 5\]"),
        (lambda: jitter(np.zeros((6, 2)), []), "non-empty"),
        (lambda: jitter(np.zeros((6, 2)), [3], window=0), "window must be an integer >= 1"),
    ],
)
def test_bad_input(no_typecheck, call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_shape_contract_is_enforced_by_the_type_checker():
    # Under the test suite's jaxtyping hook the annotations themselves reject a frame mismatch.
    with pytest.raises((TypeError, ValueError)):
        mve(zeros(2, 4), zeros(3, 4))
