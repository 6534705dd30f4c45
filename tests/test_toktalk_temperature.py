"""TokTalk's sampling temperature: the starting noise scaled by it, offline and streamed, traced (a sweep
compiles once), the config's value by default, and bad values refused."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.noise import prior_noise

import jaxtalk.models.toktalk.streaming as stream_mod

CONFIG = tt.TokTalkConfig.tiny(num_mid_blocks=0)


@pytest.fixture(scope="module")
def inputs():
    rng = np.random.default_rng(0)
    params = tt.init_params(CONFIG, jax.random.key(0))
    tokens = rng.normal(size=(2, 10, CONFIG.speech_dim)).astype(np.float32)
    style = rng.normal(size=(2, CONFIG.style_vector_dim)).astype(np.float32)
    return params, tokens, style


def test_offline_temperature_scales_the_starting_noise(inputs):
    params, tokens, style = inputs
    frames = 2 * tokens.shape[1]
    noise = np.asarray(prior_noise(jax.random.key(1), (2, frames, CONFIG.param_dim), CONFIG.noise_frames))
    scaled = tt.sample(params, CONFIG, tokens, style, noise=noise, sample_steps=3, temperature=0.5)
    by_hand = tt.sample(params, CONFIG, tokens, style, noise=np.float32(0.5) * noise, sample_steps=3)
    np.testing.assert_array_equal(np.asarray(scaled), np.asarray(by_hand))
    drawn = tt.sample(params, CONFIG, tokens, style, jax.random.key(1), sample_steps=3, temperature=0.5)
    np.testing.assert_array_equal(np.asarray(drawn), np.asarray(scaled))
    # The config's temperature is the default.
    cooled = dataclasses.replace(CONFIG, temperature=0.5)
    np.testing.assert_array_equal(np.asarray(tt.sample(params, cooled, tokens, style, noise=noise, sample_steps=3)),
                                  np.asarray(scaled))


def test_a_stream_at_temperature_zero_does_not_depend_on_its_key_and_a_sweep_compiles_once(inputs):
    params, tokens, style = inputs
    cold = [np.asarray(tt.stream(params, CONFIG, tokens, style, jax.random.key(k), temperature=0.0)) for k in (1, 2)]
    np.testing.assert_array_equal(cold[0], cold[1])  # no noise left: the flow from the prior's mean
    warm = [np.asarray(tt.stream(params, CONFIG, tokens, style, jax.random.key(k))) for k in (1, 2)]
    assert np.abs(warm[0] - warm[1]).max() > 1e-3  # at the default temperature the key matters
    compiled = stream_mod._stream_step._cache_size()
    for tau in (0.25, 0.5, 2.0):
        out = np.asarray(tt.stream(params, CONFIG, tokens, style, jax.random.key(1), temperature=tau))
        assert np.isfinite(out).all() and not np.array_equal(out, cold[0])
    assert stream_mod._stream_step._cache_size() == compiled


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf")])
def test_a_negative_or_non_finite_temperature_is_refused(inputs, bad):
    params, tokens, style = inputs
    with pytest.raises(ValueError, match="temperature must be a finite number >= 0"):
        tt.sample(params, CONFIG, tokens, style, jax.random.key(0), sample_steps=2, temperature=bad)
    with pytest.raises(ValueError, match="temperature must be a finite number >= 0"):
        tt.stream(params, CONFIG, tokens, style, jax.random.key(0), temperature=bad)
    with pytest.raises(ValueError, match="temperature"):
        dataclasses.replace(CONFIG, temperature=bad)
