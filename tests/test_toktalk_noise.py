"""TokTalk's starting noise: white by default (bitwise jax.random.normal), or Gaussian-smoothed over time
with unit variance per frame and the analytic autocorrelation exp(-lag^2 / (4 s^2)), also across the
streaming buffer's wrap-around."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.noise import cyclic_prior_noise, noise_kernel, prior_noise


def test_zero_correlation_is_plain_white_noise():
    key = jax.random.key(3)
    np.testing.assert_array_equal(np.asarray(prior_noise(key, (2, 7, 5), 0.0)),
                                  np.asarray(jax.random.normal(key, (2, 7, 5))))
    np.testing.assert_array_equal(np.asarray(cyclic_prior_noise(key, (2, 7, 5), 0.0)),
                                  np.asarray(jax.random.normal(key, (2, 7, 5))))


@pytest.mark.slow
@pytest.mark.parametrize("frames", [1.0, 2.5])
def test_smoothed_noise_has_unit_variance_and_gaussian_autocorrelation(frames):
    k = noise_kernel(frames)
    assert np.sum(k * k) == pytest.approx(1.0) and k.shape[0] == 2 * int(np.ceil(3 * frames)) + 1
    for draw in (prior_noise, cyclic_prior_noise):
        z = np.asarray(draw(jax.random.key(0), (256, 120, 16), frames), np.float64)
        assert z.shape == (256, 120, 16)
        np.testing.assert_allclose(z.var(axis=(0, 2)), 1.0, atol=0.08)  # every frame, edges included
        for lag in range(1, 6):
            corr = np.mean(z[:, lag:] * z[:, :-lag])
            # The truncated kernel's exact autocorrelation is the analytic one to ~1e-3.
            assert corr == pytest.approx(np.exp(-lag * lag / (4 * frames * frames)), abs=0.02), (draw.__name__, lag)
    # The buffer wraps: its last row correlates with its first as neighbours do.
    z = np.asarray(cyclic_prior_noise(jax.random.key(1), (4096, 16, 16), frames), np.float64)
    assert np.mean(z[:, -1] * z[:, 0]) == pytest.approx(np.exp(-1 / (4 * frames * frames)), abs=0.015)


def test_noise_frames_reaches_training_sampling_and_streaming_and_is_validated():
    with pytest.raises(ValueError, match="noise_frames"):
        tt.TokTalkConfig.tiny(noise_frames=-1.0)
    cfg = tt.TokTalkConfig.tiny(noise_frames=1.5)
    state = tt.init_stream(cfg, jax.random.key(0), buffer_frames=64)
    np.testing.assert_array_equal(np.asarray(state.noise),
                                  np.asarray(cyclic_prior_noise(jax.random.key(0), (1, 64, 56), 1.5)))
    with pytest.raises(ValueError, match="shorter than the noise kernel"):
        cyclic_prior_noise(jax.random.key(0), (1, 3, 56), 1.5)
