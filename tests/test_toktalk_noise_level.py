"""A trained TokTalk's mouth in a silent room does not depend on how loud the room's noise is when its
tokens go through the causal noise-floor normaliser, and does without it.

The run is the session's trained tiny TokTalk; its own tokenizer (SynthTalk ``tiny``'s) has no
normaliser. The same model streams the same tokens space fitted WITH the normaliser on the same
corpus audio (same rate, width, codes and seed): steady white noise from -60 to -20 dBFS then reads as
the same tokens, so the streamed motion is bitwise the same at every level.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

SR = 16000
LEVELS_DB = (-60, -40, -20)


def _stream_noise(run, tokenizer, seconds: float = 6.0) -> dict[int, np.ndarray]:
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.sampling import default_grid

    config = dataclasses.replace(run.config, sample_steps=1)
    style = tt.encode_style(run.params, config, np.asarray(run.default_style(), np.float32)[None, : 4 * config.style_frames])
    noise = np.random.default_rng(0).standard_normal(int(seconds * SR))
    noise /= np.sqrt(np.mean(noise ** 2))
    out = {}
    for db in LEVELS_DB:
        tokens = tokenizer.encode((noise * 10 ** (db / 20)).astype(np.float32)).embeddings
        out[db] = np.asarray(tt.stream(run.params, config, np.asarray(tokens, np.float32)[None], style,
                                       jax.random.key(0), ts=default_grid(config, 1)))[0]
    return out


def test_noise_level_leaves_a_trained_models_motion_bitwise_unchanged_with_the_normaliser_only(
        trained_toktalk, synthtalk_tiny):
    from jaxtalk.audio import VQTokenizer
    from jaxtalk.runs import load_run

    run = load_run(trained_toktalk.dir)
    plain = run.tokenizer()
    assert plain.floor_window == 0
    audios = [np.asarray(synthtalk_tiny.audio(i)) for i in synthtalk_tiny.split("train")]
    normalised = VQTokenizer.fit(audios, rate=plain.rate, num_codes=plain.codebook.shape[0],
                                 width=plain.embedding.shape[1], seed=plain.seed, n_mels=plain.n_mels,
                                 stack=plain.stack, floor_window=25)

    with_normaliser = _stream_noise(run, normalised)
    for db in LEVELS_DB[1:]:
        np.testing.assert_array_equal(with_normaliser[db], with_normaliser[LEVELS_DB[0]])
    # Positive control: the same model on the same noise through the tokenizer without the normaliser.
    without = _stream_noise(run, plain)
    moved = max(float(np.abs(without[db] - without[LEVELS_DB[0]]).max()) for db in LEVELS_DB[1:])
    assert moved > 1e-3, moved
