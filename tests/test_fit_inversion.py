"""Inversion through the samplers (``jaxtalk.fit.inversion`` and the models' ``inversion`` modules).

* A TokTalk style vector and FreeTalk ATS intensities used to sample a target from fixed noise are
  recovered from other starting points (untrained tiny models: the truth is whatever made the target).
* The gradients the solvers use (reverse mode for BFGS, forward mode for Levenberg-Marquardt) equal
  central finite differences in float64, and ``jax.checkpoint`` on the sampler step does not change them.
* ``sample_ats_from_noise`` reproduces ``ats.sample`` exactly; the reported losses are the loss
  functions' values at the returned solution.
* Non-convergence, unreachable targets and malformed input raise errors naming the problem.
"""

from __future__ import annotations

import functools
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.fit import InversionFailedError
from jaxtalk.models.freetalk.inversion import ats_noise, intensity_loss, invert_intensity, sample_ats_from_noise
from jaxtalk.models.toktalk.inversion import invert_style, style_loss
from jaxtalk.models import toktalk as tt
from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.config import ATSConfig


# TokTalk: the tiny preset without middle stages (compile time dominates); 8 tokens = 16 frames.
TT_CFG = tt.TokTalkConfig.tiny(num_mid_blocks=0)
B, TOKENS, FRAMES = 2, 8, 16
CFG_SCALE = 0.7
# ATS: one narrow layer, 4 DDIM steps, 3 intensity levels.
ATS_CFG = ATSConfig.small(width=16, num_layers=1, num_heads=2, ff_dim=32, max_frames=16, speech_dim=8,
                          time_frequency_dim=16, sample_steps=4)
AB, AT = 3, 12
TRUE_INTENSITY = np.array([1.7, 2.4, 3.0], np.float32)  # one per segment, and one on the upper bound


# Module fixtures hold the models and data; they are built on first use inside a test.
@pytest.fixture(scope="module")
def toktalk_cache():
    return SimpleNamespace()


@pytest.fixture
def toktalk(toktalk_cache):
    d = toktalk_cache
    if not hasattr(d, "params"):
        rng = np.random.default_rng(0)
        d.params = tt.init_params(TT_CFG, jax.random.key(0))
        d.tokens = rng.normal(size=(B, TOKENS, TT_CFG.speech_dim)).astype(np.float32)
        d.noise = rng.normal(size=(B, FRAMES, TT_CFG.param_dim)).astype(np.float32)
        d.style = rng.normal(size=(B, TT_CFG.style_vector_dim)).astype(np.float32)
    return d


@pytest.fixture
def style_target(toktalk):
    """The clip sampled with the true style."""
    d = toktalk
    if not hasattr(d, "target"):
        d.target = np.asarray(tt.sample(d.params, TT_CFG, d.tokens, d.style, noise=d.noise, cfg_scale=CFG_SCALE))
    return d.target


@pytest.fixture(scope="module")
def freetalk_cache():
    return SimpleNamespace()


@pytest.fixture
def freetalk(freetalk_cache):
    d = freetalk_cache
    if not hasattr(d, "target"):
        audio = np.random.default_rng(1).normal(size=(AB, AT, ATS_CFG.speech_dim)).astype(np.float32)
        d.cond = ats.make_condition(ATS_CFG, audio, ["happy", "sad", "angry"], 1.0)
        d.params = ats.init_params(ATS_CFG, jax.random.key(0))
        d.noise = ats_noise(ATS_CFG, d.cond, jax.random.key(1))
        # The clip sampled with the true intensities.
        truth = d.cond._replace(intensity=jnp.asarray(TRUE_INTENSITY))
        d.target = np.asarray(sample_ats_from_noise(d.params, ATS_CFG, truth, d.noise))
    return d


def _as64(tree):
    return jax.tree.map(lambda a: jnp.asarray(a, jnp.float64) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating)
                        else a, tree)


def _derivative_probe(loss):
    """One compiled program: the loss, its reverse-mode gradient, and its forward-mode derivative along d."""

    @jax.jit
    def probe(x, d):
        value, grad = jax.value_and_grad(loss)(x)
        return value, grad, jax.jvp(loss, (x,), (d,))[1]

    return probe


# ---- TokTalk style ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_style_recovered_from_a_different_start_and_from_the_encoder(toktalk, style_target):
    d, target = toktalk, style_target
    start = d.style + 1.5 * np.random.default_rng(2).normal(size=d.style.shape).astype(np.float32)
    res = invert_style(d.params, TT_CFG, d.tokens, target, d.noise, init=start, cfg_scale=CFG_SCALE)
    assert res.all_converged and set(res.results) == {"successful"}
    assert np.all((0 < np.asarray(res.steps)) & (np.asarray(res.steps) < 100))
    assert float(np.min(res.init_loss)) > 1e-3  # the start is far off ...
    # ... and the style vector that made the target comes back (stated tolerance: 1e-3 per entry).
    np.testing.assert_allclose(np.asarray(res.value), d.style, atol=1e-3)
    assert float(np.max(res.loss)) < 1e-9

    # Default start: the style encoder's estimate for the same clip (untrained here, so a poor one).
    res_enc = invert_style(d.params, TT_CFG, d.tokens, target, d.noise, cfg_scale=CFG_SCALE)
    np.testing.assert_allclose(np.asarray(res_enc.value), d.style, atol=1e-3)
    # ... which is where init=None starts (the same compiled program; the encoder itself compiled
    # without a mask here differs from the masked call inside by float32 rounding only).
    encoded = np.asarray(tt.encode_style(d.params, TT_CFG, target))
    res_given = invert_style(d.params, TT_CFG, d.tokens, target, d.noise, init=encoded, cfg_scale=CFG_SCALE)
    np.testing.assert_allclose(np.asarray(res_given.init_loss), np.asarray(res_enc.init_loss), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(res_given.value), np.asarray(res_enc.value), atol=1e-5)
    assert float(np.min(res_enc.init_loss)) > 1e2 * float(np.max(res_enc.loss))


@pytest.mark.slow
def test_style_loss_gradient_matches_central_differences(toktalk, style_target, float64):
    d, target = toktalk, style_target
    p64, tokens, target, noise = _as64((d.params, d.tokens, target, d.noise))
    rng = np.random.default_rng(3)

    def loss(style):
        return jnp.sum(style_loss(p64, TT_CFG, tokens, target, noise, style, cfg_scale=CFG_SCALE))

    probe = _derivative_probe(loss)
    s0 = jnp.asarray(d.style + 0.3 * rng.normal(size=d.style.shape))
    direction = jnp.asarray(rng.normal(size=d.style.shape))
    _, grad, jvp = probe(s0, direction)
    # The shared attention forms its logits in float32 even under x64 (~1e-7 relative noise in the
    # loss), so the step is large enough to keep the difference quotient clean.
    eps = 1e-3
    fd = (probe(s0 + eps * direction, direction)[0] - probe(s0 - eps * direction, direction)[0]) / (2 * eps)
    assert abs(float(fd)) > 1e-4
    np.testing.assert_allclose(float(jnp.sum(grad * direction)), float(fd), rtol=2e-3)  # what BFGS uses
    np.testing.assert_allclose(float(jvp), float(fd), rtol=2e-3)  # what Levenberg-Marquardt uses


# ---- FreeTalk ATS intensity ------------------------------------------------------------------------


def test_sample_ats_from_noise_reproduces_sample_ats(freetalk):
    d = freetalk
    key = jax.random.key(7)
    cond = d.cond._replace(intensity=jnp.asarray(TRUE_INTENSITY))
    expected = ats.sample(d.params, ATS_CFG, cond, key)
    got = sample_ats_from_noise(d.params, ATS_CFG, cond, ats_noise(ATS_CFG, cond, key))
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_intensity_recovered_from_segment_starts(freetalk):
    d = freetalk
    target = d.target
    res = invert_intensity(d.params, ATS_CFG, d.cond, target, d.noise)
    assert res.all_converged and set(res.results) == {"successful"}
    # Stated tolerance: 1e-4 in intensity; the truth on the upper bound (3.0) included.
    np.testing.assert_allclose(np.asarray(res.value), TRUE_INTENSITY, atol=1e-4)
    assert float(np.max(res.loss)) < 1e-10 < float(np.min(res.init_loss))
    np.testing.assert_allclose(
        np.asarray(res.loss), np.asarray(intensity_loss(d.params, ATS_CFG, d.cond, target, d.noise, res.value)),
        atol=1e-10,
    )
    # One start in each example's own segment (the same compiled program) recovers it too ...
    near = invert_intensity(d.params, ATS_CFG, d.cond, target, d.noise, init=[1.2, 2.9, 2.2])
    np.testing.assert_allclose(np.asarray(near.value), TRUE_INTENSITY, atol=1e-4)
    # ... and, ATS's affect embedding being affine in the intensity (no kinks at the levels), so does a
    # start in the other segment (it may use up the step budget on the flat approach: returned, not raised).
    far = invert_intensity(d.params, ATS_CFG, d.cond, target, d.noise, init=[2.9, 1.1, 1.5], on_failure="return")
    np.testing.assert_allclose(np.asarray(far.value), TRUE_INTENSITY, atol=1e-3)


@pytest.mark.slow
def test_intensity_loss_gradient_matches_central_differences_with_and_without_remat(freetalk, float64):
    d = freetalk
    target = d.target
    params, cond, target, noise = _as64((d.params, d.cond, target, d.noise))

    def loss(intensity, remat=True):
        return jnp.sum(intensity_loss(params, ATS_CFG, cond, target, noise, intensity, remat=remat))

    probe = _derivative_probe(loss)
    # ATS casts the intensity to float32 before interpolating its level embeddings: dyadic points and
    # steps keep every evaluated intensity exact in float32 (and away from the kinks at 1, 2, 3).
    i0 = jnp.asarray([1.75, 2.25, 2.625])
    direction = jnp.asarray([1.0, -1.0, 0.5])
    eps = 2.0**-10
    value, grad, jvp = probe(i0, direction)
    fd = (probe(i0 + eps * direction, direction)[0] - probe(i0 - eps * direction, direction)[0]) / (2 * eps)
    assert abs(float(fd)) > 1e-3
    np.testing.assert_allclose(float(jnp.sum(grad * direction)), float(fd), rtol=2e-3)
    np.testing.assert_allclose(float(jvp), float(fd), rtol=2e-3)
    # jax.checkpoint on the DDIM step changes memory, not the gradient.
    grad_plain = jax.jit(jax.grad(functools.partial(loss, remat=False)))(i0)
    np.testing.assert_allclose(np.asarray(grad_plain), np.asarray(grad), rtol=1e-10, atol=1e-12)


# ---- failures --------------------------------------------------------------------------------------


@pytest.mark.slow
def test_failed_inversions_raise_with_result_code_and_loss(freetalk):
    d = freetalk
    target = d.target
    with pytest.raises(InversionFailedError, match="nonlinear_max_steps_reached.*after 1 steps.*loss") as err:
        invert_intensity(d.params, ATS_CFG, d.cond, target, d.noise, init=1.2, max_steps=1)
    failed = err.value.result
    assert set(failed.results) == {"nonlinear_max_steps_reached"} and not np.any(np.asarray(failed.converged))
    np.testing.assert_array_equal(np.asarray(failed.steps), 1)
    assert np.all(np.isfinite(np.asarray(failed.loss)))
    returned = invert_intensity(d.params, ATS_CFG, d.cond, target, d.noise, init=1.2, max_steps=1,
                                on_failure="return")
    assert not returned.all_converged
    np.testing.assert_array_equal(np.asarray(returned.value), np.asarray(failed.value))
    # A target no intensity can produce: the solver succeeds, the threshold on the loss flags the fit.
    with pytest.raises(InversionFailedError, match="max_loss"):
        invert_intensity(d.params, ATS_CFG, d.cond, target + 0.01, d.noise, max_loss=1e-6)


def test_bad_input_raises_value_errors(toktalk, freetalk):
    t, f = toktalk, freetalk
    target = np.zeros((B, FRAMES, TT_CFG.param_dim), np.float32)
    style_cases = [
        (dict(target=np.where(np.arange(FRAMES)[None, :, None] == 3, np.nan, target)), "NaN or inf on a real frame"),
        (dict(target=target[..., :55]), "target must have shape"),
        (dict(tokens=t.tokens[:, :7]), "cover 14 frames"),
        (dict(tokens=t.tokens[..., :10]), "tokens must have shape"),
        (dict(noise=t.noise[:, :8]), "noise must have the target's shape"),
        (dict(noise=np.full_like(t.noise, np.inf)), "noise holds NaN or inf"),
        (dict(init=np.zeros(TT_CFG.style_vector_dim + 1)), "init must have shape"),
        (dict(mask=np.ones((B, FRAMES), np.int32)), "mask must be a bool array"),
        (dict(mask=np.zeros((B, FRAMES), bool)), "no real frame"),
        (dict(solver="adam"), "solver must be one of"),
        (dict(max_steps=0), "max_steps must be a positive integer"),
        (dict(prior=-1.0), "prior must be a finite scalar >= 0"),
    ]
    for change, message in style_cases:
        kwargs = dict(tokens=t.tokens, target=target, noise=t.noise, init=t.style)
        kwargs.update(change)
        args = [kwargs.pop(k) for k in ("tokens", "target", "noise")]
        with pytest.raises(ValueError, match=message):
            invert_style(t.params, TT_CFG, *args, **kwargs)
    # The encoder needs style_min_frames (8): a 4-frame clip must come with an explicit init.
    with pytest.raises(ValueError, match="style_min_frames"):
        invert_style(t.params, TT_CFG, t.tokens[:, :2], target[:, :4], t.noise[:, :4])

    disp = np.zeros((AB, AT, ATS_CFG.num_landmarks, 3), np.float32)
    nan_disp = disp.copy()
    nan_disp[1, 5, 10, 0] = np.nan
    intensity_cases = [
        (dict(target=nan_disp), "example 1, frame 5"),
        (dict(target=disp[:, :5]), "target must have shape"),
        (dict(noise=np.asarray(f.noise)[..., :3]), "noise must have shape"),
        (dict(init=0.5), r"must lie in \[1, 3\]"),
        (dict(init=[1.0, 2.0]), "init must be a scalar or have shape"),
        (dict(sample_steps=0), "sample_steps must be an integer"),
        (dict(rtol=-1.0), "rtol must be a positive finite number"),
        (dict(on_failure="ignore"), "on_failure must be"),
    ]
    for change, message in intensity_cases:
        kwargs = dict(cond=f.cond, target=disp, noise=f.noise)
        kwargs.update(change)
        args = [kwargs.pop(k) for k in ("cond", "target", "noise")]
        with pytest.raises(ValueError, match=message):
            invert_intensity(f.params, ATS_CFG, *args, **kwargs)
    single_level = ATSConfig.small(num_intensities=1)
    with pytest.raises(ValueError, match="single intensity level"):
        invert_intensity(f.params, single_level, f.cond, disp, f.noise)
    with pytest.raises(ValueError, match="noise must have shape"):
        sample_ats_from_noise(f.params, ATS_CFG, f.cond, np.zeros((AB, AT, 5), np.float32))
