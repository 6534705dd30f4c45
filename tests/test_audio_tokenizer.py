"""VQ tokenizer and token streams: determinism, counts, code assignment, geometry, persistence."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from jaxtalk.audio import TokenStream, VQTokenizer, log_mel

SR = 16000


def _sine(freq, seconds=1.0, amplitude=0.3):
    t = np.arange(int(SR * seconds)) / SR
    return (amplitude * np.sin(2 * np.pi * freq * t)).astype(np.float32)


def _noise(seconds=1.0, seed=0):
    return (0.2 * np.random.default_rng(seed).standard_normal(int(SR * seconds))).astype(np.float32)


def _corpus():
    # Four clearly different sounds, plus a clip that switches between them every 0.2 s.
    mixed = np.concatenate(
        [_sine(300, 0.2), _noise(0.2, 5), _sine(3000, 0.2), np.zeros(3200, np.float32)]
    )
    return [_sine(300), _sine(3000), _noise(), np.zeros(SR, np.float32), mixed]


FIT = dict(rate=25, num_codes=6, width=8, seed=0, n_mels=32)


@pytest.fixture(scope="module")
def tokenizer():
    return VQTokenizer.fit(_corpus(), **FIT)


def _majority(ids):
    return np.bincount(ids[2:-2]).argmax()  # ignore edge tokens (onsets, padding)


def test_fit_and_encode_are_deterministic(tokenizer):
    again = VQTokenizer.fit(_corpus(), **FIT)
    np.testing.assert_array_equal(again.codebook, tokenizer.codebook)
    np.testing.assert_array_equal(again.embedding, tokenizer.embedding)
    a, b = tokenizer.encode(_noise(seed=9)), tokenizer.encode(_noise(seed=9))
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.embeddings, b.embeddings)
    other_seed = VQTokenizer.fit(_corpus(), **{**FIT, "seed": 1})
    assert not np.allclose(other_seed.embedding, tokenizer.embedding)


@pytest.mark.parametrize(
    ("seconds", "rate"), [(2.0, 25), (2.0, 12.5), (1.03, 12.5), (0.5, 25), (0.01, 25)]
)
def test_token_count_is_duration_times_rate(tokenizer, seconds, rate):
    # The token layout depends on the rate only; the codebook is reused (no second k-means fit).
    tok = dataclasses.replace(tokenizer, rate=rate)
    stream = tok.encode(_sine(440, seconds))
    assert len(stream) == math.ceil(round(seconds * SR) * rate / SR)
    assert stream.ids.dtype == np.int32 and stream.embeddings.dtype == np.float32
    assert stream.embeddings.shape == (len(stream), 8) and stream.rate == rate


def test_features_match_brute_force_pooling(tokenizer):
    # Token k averages the log-mel frames centred in each half of [k/rate, (k+1)/rate).
    audio = _noise(0.7, seed=3)
    feats = tokenizer.features(audio)
    tokens = math.ceil(audio.size * 25 / SR)
    padded = np.concatenate([audio, np.zeros(tokens * SR // 25 - audio.size, np.float32)])
    mel = np.asarray(log_mel(padded, n_mels=32))
    times = np.arange(mel.shape[0]) * 0.01
    for k in range(tokens):
        for half in range(2):
            start, stop = (2 * k + half) * 0.02, (2 * k + half + 1) * 0.02
            inside = (times >= start - 1e-9) & (times < stop - 1e-9)
            np.testing.assert_allclose(
                feats[k, half * 32 : (half + 1) * 32], mel[inside].mean(axis=0), atol=1e-4
            )


def test_centroids_map_back_to_their_code(tokenizer):
    raw_centroids = tokenizer.codebook * tokenizer.feature_scale + tokenizer.feature_mean
    np.testing.assert_array_equal(tokenizer.quantize(raw_centroids), np.arange(tokenizer.num_codes))
    # A small perturbation (far less than the distance to other codes) keeps the code.
    jitter = (
        0.01
        * np.random.default_rng(0).standard_normal(raw_centroids.shape)
        * tokenizer.feature_scale
    )
    np.testing.assert_array_equal(
        tokenizer.quantize(raw_centroids + jitter), np.arange(tokenizer.num_codes)
    )


def test_quantize_is_nearest_codebook_entry(tokenizer):
    feats = tokenizer.features(_corpus()[-1])
    z = (feats - tokenizer.feature_mean) / tokenizer.feature_scale
    brute = np.argmin(((z[:, None, :] - tokenizer.codebook[None, :, :]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(tokenizer.quantize(feats), brute)


def test_different_sounds_get_different_ids(tokenizer):
    low, high = tokenizer.encode(_sine(300, 1.0, 0.25)), tokenizer.encode(_sine(3000, 1.0, 0.25))
    noise, silence = tokenizer.encode(_noise(seed=7)), tokenizer.encode(np.zeros(SR, np.float32))
    majorities = [_majority(s.ids) for s in (low, high, noise, silence)]
    assert len(set(majorities)) == 4, majorities
    # A steady sound is one token throughout (away from the edges).
    assert np.all(low.ids[2:-2] == majorities[0])


def test_embeddings_are_the_table_rows(tokenizer):
    stream = tokenizer.encode(_corpus()[-1])
    np.testing.assert_array_equal(stream.embeddings, tokenizer.embedding[stream.ids])
    np.testing.assert_array_equal(tokenizer.lookup(stream.ids), stream.embeddings)
    np.testing.assert_allclose(np.sqrt(np.mean(tokenizer.embedding**2)), 1.0, rtol=1e-5)
    with pytest.raises(ValueError, match="token ids"):
        tokenizer.lookup(np.array([0, tokenizer.num_codes]))


def test_wide_embedding_is_isometric_to_codebook():
    # width >= features: embedding distances are exactly proportional to centroid distances.
    tok = VQTokenizer.fit(_corpus(), **{**FIT, "width": 2 * FIT["n_mels"]})  # features = 2 * n_mels

    def pairwise(a):
        return np.linalg.norm(a[:, None, :] - a[None, :, :], axis=-1)

    d_code, d_emb = (
        pairwise(tok.codebook.astype(np.float64)),
        pairwise(tok.embedding.astype(np.float64)),
    )
    off = ~np.eye(tok.num_codes, dtype=bool)
    ratio = d_emb[off] / d_code[off]
    np.testing.assert_allclose(ratio, ratio.mean(), rtol=1e-4)


def test_save_load_round_trip(tokenizer, tmp_path):
    path = tokenizer.save(tmp_path / "tok_a")
    assert path.suffix == ".npz"
    loaded = VQTokenizer.load(path)
    for field in ("codebook", "feature_mean", "feature_scale", "embedding"):
        np.testing.assert_array_equal(getattr(loaded, field), getattr(tokenizer, field))
    for field in ("rate", "sample_rate", "n_mels", "n_fft", "hop_length", "stack", "seed"):
        assert getattr(loaded, field) == getattr(tokenizer, field)
    audio = _corpus()[-1]
    np.testing.assert_array_equal(loaded.encode(audio).ids, tokenizer.encode(audio).ids)


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        VQTokenizer.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, codebook=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="missing keys"):
        VQTokenizer.load(bad)


def test_fit_errors():
    with pytest.raises(ValueError, match="non-empty list"):
        VQTokenizer.fit([], **FIT)
    nan_clip = _sine(300)
    nan_clip[10] = np.nan
    with pytest.raises(ValueError, match=r"audios\[1\].*NaN"):
        VQTokenizer.fit([_sine(300), nan_clip], **FIT)
    with pytest.raises(ValueError, match="sub-windows"):
        VQTokenizer.fit(_corpus(), **{**FIT, "rate": 80})
    with pytest.raises(ValueError, match="distinct token features"):
        VQTokenizer.fit([np.zeros(SR, np.float32)], **FIT)


def test_encode_rejects_bad_audio(tokenizer):
    with pytest.raises(ValueError, match="empty"):
        tokenizer.encode(np.zeros(0, np.float32))
    with pytest.raises(ValueError, match="NaN"):
        tokenizer.encode(np.full(100, np.nan, np.float32))


def test_token_stream_from_npy(tmp_path):
    emb = np.random.default_rng(0).standard_normal((25, 7))
    np.save(tmp_path / "llm.npy", emb)
    stream = TokenStream.from_npy(tmp_path / "llm.npy", rate=12.5)
    assert stream.ids is None and stream.embeddings.dtype == np.float32
    np.testing.assert_array_equal(stream.embeddings, emb.astype(np.float32))
    assert stream.duration == 2.0 and stream.width == 7
    motion = np.asarray(stream.to_frame_rate(25))
    assert motion.shape == (50, 7)
    np.testing.assert_allclose(motion[::2], emb.astype(np.float32), atol=1e-6)
    with pytest.raises(FileNotFoundError):
        TokenStream.from_npy(tmp_path / "none.npy", rate=12.5)
    np.save(tmp_path / "flat.npy", np.zeros(5))
    with pytest.raises(ValueError, match="frames, width"):
        TokenStream.from_npy(tmp_path / "flat.npy", rate=12.5)
    emb[3, 1] = np.nan
    np.save(tmp_path / "nan.npy", emb)
    with pytest.raises(ValueError, match="NaN"):
        TokenStream.from_npy(tmp_path / "nan.npy", rate=12.5)
    with pytest.raises(ValueError, match="rate"):
        TokenStream.from_npy(tmp_path / "llm.npy", rate=0)


def test_a_token_reads_audio_up_to_its_lookahead_past_its_window_and_no_further(tokenizer):
    # 25 Hz tokens: token 4's window is [0.16, 0.20) s; its last mel frame is centred at sample 3040 and
    # its 400-sample STFT ends at 3240: 40 samples (2.5 ms) past the window.
    assert tokenizer.lookahead_s == pytest.approx(0.0025)
    audio = _noise(1.0, seed=3)
    end = int(SR * 0.20)
    base = tokenizer.features(audio)
    inside = audio.copy()
    inside[end + 30 : end + 38] += 1.0  # within the look-ahead: token 4 changes
    beyond = audio.copy()
    beyond[end + int(SR * tokenizer.lookahead_s) :] += 1.0  # past it: tokens 0..4 do not
    assert not np.allclose(tokenizer.features(inside)[4], base[4])
    np.testing.assert_array_equal(tokenizer.features(beyond)[:5], base[:5])
