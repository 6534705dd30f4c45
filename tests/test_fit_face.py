"""Face-model fitting: params -> geometry -> fit recovers the params, regularisation, failures.

Everything runs on the low-resolution built-in face in float64 with few frames; fits that share a
``FitConfig`` and shapes share one compiled program (``_fit_core`` is jitted on them). Compile time
dominates (each distinct config compiles an optimistix loop around the face model).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.face import builtin_face
from jaxtalk.fit import (
    FitConfig,
    FitFailedError,
    fit_landmarks,
    fit_vertices,
    identifiable_params,
    result_name,
)
from jaxtalk.fit import face_fit
from jaxtalk.geometry.topology import make_variant

JOINT = FitConfig(mode="joint")
FRAMES = 6


def _face():
    # Built inside the float64 fixture, so every array of the model is float64.
    return builtin_face(0, resolution="low")


def _random_params(num_frames: int, seed: int, keep: np.ndarray | None = None) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = np.concatenate(
        [0.5 * rng.normal(size=(num_frames, 50)), 0.08 * rng.normal(size=(num_frames, 6))], axis=1
    )
    if keep is not None:
        dropped = np.setdiff1d(np.arange(56), keep)
        p[:, dropped] = 0.0
    return p


def _smooth_params(num_frames: int, keep: np.ndarray) -> np.ndarray:
    """A slow trajectory (one sinusoid per parameter) in the given components."""
    rng = np.random.default_rng(3)
    t = np.arange(num_frames)[:, None] / num_frames
    amp = np.concatenate([0.5 * np.ones(50), 0.08 * np.ones(6)])
    p = amp * np.sin(2 * np.pi * (0.3 * t + rng.uniform(size=56)))
    p[:, np.setdiff1d(np.arange(56), keep)] = 0.0
    return p


def _null_space_of_expressions(model) -> np.ndarray:
    """Orthonormal basis (56, k) of parameter directions that move no vertex (rank-deficient basis)."""
    e = np.asarray(model.exp_basis).reshape(-1, 50)
    _, s, vt = np.linalg.svd(e)
    null = vt[s < 1e-10 * s[0]]
    return np.concatenate([null, np.zeros((len(null), 6))], axis=1).T


@pytest.mark.slow
def test_vertex_fit_recovers_params_up_to_the_model_null_space(float64):
    """All 56 params from vertices: exact geometry; params equal the truth projected off the null space.

    The built-in face's expression basis has full rank (50), so the null space is empty and the fit
    must recover every parameter. (Were it rank-deficient, Levenberg-Marquardt from a zero start
    steps only in the Jacobian's row space and returns the minimum-norm solution: the projection.)
    """
    model = _face()
    truth = _random_params(2, seed=0)
    verts = model.vertices_seq(jnp.asarray(truth))
    fit = fit_vertices(model, verts)  # raises if not converged
    null = _null_space_of_expressions(model)
    assert null.shape[1] == 0  # every expression component moves the mesh its own way
    projected = truth - (truth @ null) @ null.T
    np.testing.assert_allclose(fit.params, projected, atol=1e-4)
    assert np.max(np.asarray(fit.rms)) < 1e-9
    np.testing.assert_allclose(model.vertices_seq(fit.params), verts, atol=1e-8)
    assert fit.all_converged and fit.result_code.shape == (2,) and np.all(np.asarray(fit.steps) > 0)


@pytest.mark.slow
def test_landmark_fit_recovers_identifiable_subset(float64):
    """Fitting the pivoted-QR subset that 68 landmarks determine recovers those params exactly."""
    model = _face()
    active = identifiable_params(model, target="landmarks")
    # The subset depends on how much each component moves the 68 points (rtol of the pivots).
    assert 30 < len(active) <= 56
    truth = _random_params(2, seed=1, keep=active)
    landmarks = model.landmarks_seq(jnp.asarray(truth))
    fit = fit_landmarks(model, landmarks, config=FitConfig(active=tuple(active)))
    np.testing.assert_allclose(fit.params, truth, atol=1e-4)
    assert np.max(np.asarray(fit.rms)) < 1e-9


@pytest.mark.slow
def test_landmark_fit_all_params_reproduces_landmarks_with_masked_nans(float64):
    """All 56 from landmarks with a prior: the visible geometry is exact, missing points are ignored."""
    model = _face()
    truth = _random_params(FRAMES, seed=2)
    landmarks = np.array(model.landmarks_seq(jnp.asarray(truth)))
    mask = np.ones(68, bool)
    mask[[0, 16, 40]] = False
    landmarks[:, ~mask] = np.nan  # missing detections
    fit = fit_landmarks(model, landmarks, mask=mask, config=JOINT, prior=1e-8)
    pred = np.asarray(model.landmarks_seq(fit.params))
    np.testing.assert_allclose(pred[:, mask], landmarks[:, mask], atol=1e-6)
    assert fit.result_code.shape == (1,)


@pytest.mark.slow
def test_joint_fit_is_a_stationary_point_of_the_documented_objective(float64):
    """Brute-force check of the joint objective: its gradient, written out here, vanishes at the fit."""
    model = _face()
    truth = _smooth_params(FRAMES, np.arange(56))
    noisy = model.landmarks_seq(jnp.asarray(truth)) + 1e-3 * jax.random.normal(
        jax.random.key(0), (FRAMES, 68, 3), jnp.float64
    )
    prior, smoothness = 1e-2, 0.3
    fit = fit_landmarks(model, noisy, config=JOINT, prior=prior, smoothness=smoothness)

    def objective(p):
        mse_mm = jnp.mean((1000.0 * (model.landmarks_seq(p) - noisy)) ** 2, axis=(1, 2))
        return jnp.sum(mse_mm) + prior * jnp.sum(p**2) + smoothness * jnp.sum((p[1:] - p[:-1]) ** 2)

    grad_fit = jax.grad(objective)(fit.params)
    grad_zero = jax.grad(objective)(jnp.zeros_like(fit.params))
    assert float(jnp.max(jnp.abs(grad_fit))) < 1e-6 * float(jnp.max(jnp.abs(grad_zero)))
    # The residual RMS reported is the landmark RMS in metres.
    rms = np.sqrt(np.mean((np.asarray(model.landmarks_seq(fit.params)) - np.asarray(noisy)) ** 2, axis=(1, 2)))
    np.testing.assert_allclose(fit.rms, rms, rtol=1e-6)


@pytest.mark.slow
def test_weights_are_traced_no_recompilation(float64):
    model = _face()
    landmarks = model.landmarks_seq(jnp.asarray(_smooth_params(FRAMES, np.arange(56))))
    fit_landmarks(model, landmarks, config=JOINT, prior=1e-3, smoothness=0.1)
    size = face_fit._fit_core._cache_size()
    fit_landmarks(model, landmarks, config=JOINT, prior=np.full(56, 2e-3), smoothness=0.7)
    fit_landmarks(model, landmarks + 1e-4, config=JOINT, prior=5e-3, smoothness=0.0)
    assert face_fit._fit_core._cache_size() == size


@pytest.mark.slow
def test_noise_degrades_gracefully_and_smoothing_helps(float64):
    """Error grows about linearly with landmark noise; the temporal term lowers it on a smooth clip."""
    model = _face()
    active = identifiable_params(model, target="landmarks")
    truth = _smooth_params(FRAMES, active)
    clean = model.landmarks_seq(jnp.asarray(truth))
    noise = jax.random.normal(jax.random.key(1), clean.shape, jnp.float64)
    config = FitConfig(mode="joint", active=tuple(active))

    def error(sigma, smoothness=0.0):
        fit = fit_landmarks(model, clean + sigma * noise, config=config, smoothness=smoothness, prior=1e-4)
        return float(jnp.sqrt(jnp.mean((model.landmarks_seq(fit.params) - clean) ** 2)))

    errors = [error(s) for s in (2.5e-4, 5e-4, 1e-3)]
    assert errors[0] < 1e-3
    # Linear response to small noise: doubling the noise doubles the error (within 10%).
    np.testing.assert_allclose(errors[1] / errors[0], 2.0, rtol=0.1)
    np.testing.assert_allclose(errors[2] / errors[1], 2.0, rtol=0.1)
    assert error(1e-3, smoothness=1.0) < 0.9 * errors[2]


@pytest.mark.slow
def test_sequential_mode_warm_starts_and_smooths_causally(float64):
    model = _face()
    active = identifiable_params(model, target="landmarks")
    truth = _random_params(2, seed=4, keep=active)
    landmarks = model.landmarks_seq(jnp.asarray(truth))
    sequential = FitConfig(mode="sequential", active=tuple(active))
    free = fit_landmarks(model, landmarks, config=sequential)
    np.testing.assert_allclose(free.params, truth, atol=1e-4)  # no smoothing: same as per frame
    pulled = fit_landmarks(model, landmarks, config=sequential, smoothness=1e3, on_failure="return")
    # Frame 0 has no predecessor; frame 1 is pulled towards frame 0's fit.
    np.testing.assert_allclose(pulled.params[0], truth[0], atol=1e-4)
    gap_free = np.linalg.norm(np.asarray(free.params[1] - free.params[0]))
    gap_pulled = np.linalg.norm(np.asarray(pulled.params[1] - pulled.params[0]))
    assert gap_pulled < 0.5 * gap_free


@pytest.mark.slow
def test_fit_on_topology_variant_through_its_map(float64):
    model = _face()
    variant = make_variant(np.asarray(model.template), np.asarray(model.faces), "retriangulated", seed=0)
    active = identifiable_params(model, target="vertices")
    truth = _random_params(2, seed=5, keep=active)
    target = variant.transfer(np.asarray(model.vertices_seq(jnp.asarray(truth))))
    fit = fit_vertices(model, target, variant=variant, config=FitConfig(active=tuple(active)))
    np.testing.assert_allclose(fit.params, truth, atol=1e-4)
    np.testing.assert_allclose(variant.transfer(np.asarray(model.vertices_seq(fit.params))), target, atol=1e-8)


@pytest.mark.slow
def test_gauss_newton_option_recovers_identifiable_subset(float64):
    model = _face()
    active = identifiable_params(model, target="landmarks")
    truth = _random_params(2, seed=6, keep=active)
    landmarks = model.landmarks_seq(jnp.asarray(truth))
    fit = fit_landmarks(model, landmarks, config=FitConfig(solver="gauss_newton", active=tuple(active)))
    np.testing.assert_allclose(fit.params, truth, atol=1e-4)
    assert np.all(np.asarray(fit.steps) < 20)  # quadratic convergence on a well-posed problem


@pytest.mark.slow
def test_non_converging_fit_raises_with_result_and_residual(float64):
    model = _face()
    landmarks = model.landmarks_seq(jnp.asarray(_random_params(FRAMES, seed=7)))
    config = FitConfig(mode="joint", max_steps=1)
    with pytest.raises(FitFailedError, match=r"nonlinear_max_steps_reached.*residual RMS [0-9.e-]+ m") as info:
        fit_landmarks(model, landmarks, config=config)
    assert not info.value.result.all_converged
    out = fit_landmarks(model, landmarks, config=config, on_failure="return")
    assert not bool(out.converged[0])
    assert result_name(int(out.result_code[0])) == "nonlinear_max_steps_reached"


def test_residual_above_threshold_raises(float64):
    model = _face()
    landmarks = model.landmarks_seq(jnp.asarray(_smooth_params(FRAMES, np.arange(56))))
    noisy = landmarks + 2e-3 * jax.random.normal(jax.random.key(2), landmarks.shape, jnp.float64)
    with pytest.raises(FitFailedError, match=r"optimistix result 'successful'.*max_rms=1e-05"):
        fit_landmarks(model, noisy, config=JOINT, prior=1e-3, max_rms=1e-5)
    out = fit_landmarks(model, noisy, config=JOINT, prior=1e-3, max_rms=1e-5, on_failure="return")
    assert not out.all_converged and result_name(int(out.result_code[0])) == "successful"


# ---- bad input ---------------------------------------------------------------------------------------


def test_bad_landmark_inputs_raise_clear_errors():
    model = builtin_face(0, resolution="low")
    good = np.zeros((2, 68, 3), np.float32)
    with pytest.raises(ValueError, match=r"landmarks must have shape \(T >= 1, 68, 3\), got \(2, 67, 3\)"):
        fit_landmarks(model, np.zeros((2, 67, 3)))
    with pytest.raises(ValueError, match=r"got \(0, 68, 3\)"):
        fit_landmarks(model, np.zeros((0, 68, 3)))
    nan = good.copy()
    nan[1, 5, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or inf at observed points.*frame 1, landmark 5"):
        fit_landmarks(model, nan)
    few = np.zeros(68, bool)
    few[:10] = True
    with pytest.raises(ValueError, match="too few observed landmarks: frame 0 has 10, need at least 19"):
        fit_landmarks(model, good, mask=few)
    with pytest.raises(ValueError, match="mask must have shape"):
        fit_landmarks(model, good, mask=np.ones((3, 68), bool))
    with pytest.raises(ValueError, match="mask must be boolean"):
        fit_landmarks(model, good, mask=np.ones(68))
    with pytest.raises(ValueError, match=r"init must have shape \(56,\) or \(2, 56\)"):
        fit_landmarks(model, good, init=np.zeros((3, 56)))
    with pytest.raises(ValueError, match="init holds NaN"):
        fit_landmarks(model, good, init=np.full(56, np.nan))
    with pytest.raises(ValueError, match="prior weights must be >= 0"):
        fit_landmarks(model, good, prior=-1.0)
    with pytest.raises(ValueError, match="smoothness=0.5 has no effect in mode 'independent'"):
        fit_landmarks(model, good, smoothness=0.5)
    with pytest.raises(ValueError, match="on_failure must be"):
        fit_landmarks(model, good, on_failure="ignore")
    with pytest.raises(ValueError, match="max_rms must be a positive number"):
        fit_landmarks(model, good, max_rms=-1.0)


def test_bad_vertex_inputs_and_configs_raise_clear_errors():
    model = builtin_face(0, resolution="low")
    n = model.num_vertices
    with pytest.raises(ValueError, match=rf"vertices must have shape \(T >= 1, {n}, 3\), got \({n}, 3\)"):
        fit_vertices(model, np.zeros((n, 3)))
    bad = np.zeros((1, n, 3))
    bad[0, 7, 1] = np.inf
    with pytest.raises(ValueError, match=r"vertices holds NaN or inf \(first at index \[0, 7, 1\]\)"):
        fit_vertices(model, bad)
    other = builtin_face(0, resolution="default")
    variant = make_variant(np.asarray(other.template), np.asarray(other.faces), "shuffled", seed=0)
    with pytest.raises(ValueError, match="variant was made from a mesh with"):
        fit_vertices(model, np.zeros((1, len(variant.vertices), 3)), variant=variant)
    with pytest.raises(ValueError, match="mode must be one of"):
        FitConfig(mode="batch")
    with pytest.raises(ValueError, match="solver must be one of"):
        FitConfig(solver="adam")
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        FitConfig(max_steps=0)
    with pytest.raises(ValueError, match="rtol must be a positive finite number"):
        FitConfig(rtol=-1.0)
    with pytest.raises(ValueError, match="active must be a non-empty sorted tuple"):
        FitConfig(active=(3, 1))
    with pytest.raises(ValueError, match="target must be"):
        identifiable_params(model, target="mesh")
