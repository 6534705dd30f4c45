"""TokTalk's starting noise: white by default (bitwise jax.random.normal), or Gaussian-smoothed over time
with unit variance per frame and the analytic autocorrelation exp(-lag^2 / (4 s^2)); the stream's noise
is a function of (key, absolute frame) that does not depend on the window and does not repeat."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.noise import frame_noise, noise_kernel, prior_noise


def test_zero_correlation_is_plain_white_noise():
    key = jax.random.key(3)
    np.testing.assert_array_equal(np.asarray(prior_noise(key, (2, 7, 5), 0.0)),
                                  np.asarray(jax.random.normal(key, (2, 7, 5))))
    z = np.asarray(frame_noise(key, 3, 7, 2, 5, 0.0))
    np.testing.assert_array_equal(z[:, 1], np.asarray(jax.random.normal(jax.random.fold_in(key, 4), (2, 5))))


@pytest.mark.slow
@pytest.mark.parametrize("frames", [1.0, 2.5])
def test_smoothed_noise_has_unit_variance_and_gaussian_autocorrelation(frames):
    k = noise_kernel(frames)
    assert np.sum(k * k) == pytest.approx(1.0) and k.shape[0] == 2 * int(np.ceil(3 * frames)) + 1
    streamed = lambda key, shape, s: frame_noise(key, -7, shape[1], shape[0], shape[2], s)  # noqa: E731
    for name, draw in (("prior_noise", prior_noise), ("frame_noise", streamed)):
        z = np.asarray(draw(jax.random.key(0), (256, 120, 16), frames), np.float64)
        assert z.shape == (256, 120, 16)
        np.testing.assert_allclose(z.var(axis=(0, 2)), 1.0, atol=0.08)  # every frame, edges included
        for lag in range(1, 6):
            corr = np.mean(z[:, lag:] * z[:, :-lag])
            # The truncated kernel's exact autocorrelation is the analytic one to ~1e-3.
            assert corr == pytest.approx(np.exp(-lag * lag / (4 * frames * frames)), abs=0.02), (name, lag)


@pytest.mark.parametrize("frames", [0.0, 2.0])
def test_stream_noise_of_a_frame_is_the_same_from_every_window(frames):
    key = jax.random.key(5)
    whole = np.asarray(frame_noise(key, -10, 60, 2, 4, frames))
    for first, length in ((-10, 7), (0, 20), (33, 17)):
        part = np.asarray(frame_noise(key, first, length, 2, 4, frames))
        np.testing.assert_allclose(part, whole[:, first + 10 : first + 10 + length], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("frames", [0.0, 2.0])
def test_stream_noise_does_not_repeat_forty_seconds_later(frames):
    # A 1,000-frame buffer read at f mod 1000 gave frame f + 1000 (40 s at 25 fps) frame f's noise.
    key = jax.random.key(6)
    early = np.asarray(frame_noise(key, 100, 50, 1, 56, frames))
    late = np.asarray(frame_noise(key, 1100, 50, 1, 56, frames))
    far = np.asarray(frame_noise(key, 100 + 2**20, 50, 1, 56, frames))
    for other in (late, far):
        assert abs(np.corrcoef(early.ravel(), other.ravel())[0, 1]) < 0.1


def test_noise_frames_reaches_training_sampling_and_streaming_and_is_validated():
    with pytest.raises(ValueError, match="noise_frames"):
        tt.TokTalkConfig.tiny(noise_frames=-1.0)
    cfg = tt.TokTalkConfig.tiny(noise_frames=1.5)
    np.testing.assert_array_equal(np.asarray(tt.stream_noise(cfg, jax.random.key(0), 64, first_frame=-3)),
                                  np.asarray(frame_noise(jax.random.key(0), -3, 64, 1, 56, 1.5)))
