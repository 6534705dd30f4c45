"""The tokenizer's causal noise-floor normaliser: its floor by hand, gain and noise-level invariance,
causality (bitwise), streamed == offline, and persistence."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.audio import VQTokenizer
from jaxtalk.audio.tokenizer import FLOOR_MIN, above_floor, noise_floor

SR = 16000
FIT = dict(rate=25, num_codes=6, width=8, seed=0, n_mels=32, floor_window=10)


def _speechlike(seconds: float, seed: int, noise_db: float | None = None, gain: float = 1.0) -> np.ndarray:
    # Bursts of harmonic sound separated by pauses, over an optional steady white-noise background.
    n = int(SR * seconds)
    t = np.arange(n) / SR
    envelope = (np.sin(2 * np.pi * 2.0 * t) > 0.2).astype(np.float64)
    voice = sum(np.sin(2 * np.pi * f * t) / k for k, f in enumerate((220, 440, 660, 1320), 1))
    x = 0.1 * envelope * voice
    if noise_db is not None:
        x = x + 10 ** (noise_db / 20) * np.random.default_rng(seed + 100).standard_normal(n)
    return (gain * x).astype(np.float32)


@pytest.fixture(scope="module")
def tokenizer():
    clips = [_speechlike(2.0, s, noise_db=db) for s, db in enumerate((-70, -55, -45))]
    return VQTokenizer.fit(clips + [np.zeros(SR, np.float32)], **FIT)


def test_noise_floor_is_the_windowed_minimum_per_mel_channel_by_hand():
    rng = np.random.default_rng(0)
    raw = rng.uniform(-14, -2, (7, 2 * 3)).astype(np.float32)  # 7 tokens, stack 2, 3 mels
    raw[3, 1] = -30.0  # below FLOOR_MIN: the floor stops there
    floor = noise_floor(raw, window=3, n_mels=3)
    for k in range(7):
        for m in range(3):
            rows = raw[max(0, k - 2):k + 1]
            want = max(min(rows[:, m].min(), rows[:, 3 + m].min()), FLOOR_MIN)
            assert floor[k, m] == floor[k, 3 + m] == np.float32(want), (k, m)


def test_noise_floor_with_history_equals_the_floor_of_the_whole_sequence():
    raw = np.random.default_rng(1).uniform(-15, -3, (20, 8)).astype(np.float32)
    whole = noise_floor(raw, window=5, n_mels=4)
    np.testing.assert_array_equal(noise_floor(raw[12:], 5, 4, past=raw[:12]), whole[12:])


def test_normalised_tokens_ignore_the_recording_gain_over_a_noise_floor(tokenizer):
    quiet = _speechlike(2.0, 7, noise_db=-60)
    loud = quiet * np.float32(10 ** (12 / 20))  # +12 dB: speech and room alike
    a, b = tokenizer.normalise(tokenizer.features(quiet)), tokenizer.normalise(tokenizer.features(loud))
    # log power moves by exactly 12 dB on both sides of the subtraction (float rounding aside)
    np.testing.assert_allclose(a, b, atol=1e-3)
    np.testing.assert_array_equal(tokenizer.encode(quiet).ids, tokenizer.encode(loud).ids)


def test_steady_noise_at_any_level_normalises_to_near_zero(tokenizer):
    for db in (-60, -40, -25):
        noise = (10 ** (db / 20) * np.random.default_rng(db + 200).standard_normal(3 * SR)).astype(np.float32)
        z = tokenizer.normalise(tokenizer.features(noise))[10:]  # once the window has filled
        # natural-log units: 1.0 = 4.3 dB; a narrow low mel channel of noise fluctuates more
        assert np.median(z) < 1.0 and z.mean(axis=1).max() < 1.2, db
    raw = tokenizer.features(_speechlike(2.0, 3, noise_db=-40))
    assert np.percentile(tokenizer.normalise(raw), 95) > 3.0  # speech stands above the floor


def test_without_normaliser_the_raw_features_are_quantised():
    plain = VQTokenizer.fit([_speechlike(2.0, 0, -60), _speechlike(2.0, 1)], **{**FIT, "floor_window": 0})
    raw = plain.features(_speechlike(1.0, 2))
    np.testing.assert_array_equal(plain.normalise(raw), raw)


def test_normalised_tokens_are_causal_bitwise(tokenizer):
    audio = _speechlike(3.0, 11, noise_db=-50)
    changed = audio.copy()
    changed[2 * SR:] = _speechlike(1.0, 99, noise_db=-30)  # a different, louder future
    a, b = tokenizer.encode(audio), tokenizer.encode(changed)
    # token k reads audio up to (k + 1) / rate plus the STFT's half window; token 49 ends at 2.0 s
    past = int(2.0 * 25) - 1
    np.testing.assert_array_equal(a.ids[:past], b.ids[:past])
    np.testing.assert_array_equal(a.embeddings[:past], b.embeddings[:past])
    assert not np.array_equal(a.ids[past:], b.ids[past:])


@pytest.mark.parametrize("piece", [321, 4000])
def test_streamed_normalised_tokens_equal_offline(tokenizer, piece):
    audio = _speechlike(2.3, 5, noise_db=-45)
    stream = tokenizer.stream(group=3)
    ids = []
    for start in range(0, audio.size, piece):
        ids.append(stream.push(audio[start:start + piece])[0])
    ids.append(stream.finish()[0])
    np.testing.assert_array_equal(np.concatenate(ids), tokenizer.encode(audio).ids)


def test_normaliser_round_trips_and_old_files_load_without_it(tokenizer, tmp_path):
    back = VQTokenizer.load(tokenizer.save(tmp_path / "tok"))
    assert back.floor_window == 10
    audio = _speechlike(1.5, 4, noise_db=-50)
    np.testing.assert_array_equal(back.encode(audio).ids, tokenizer.encode(audio).ids)
    with np.load(tmp_path / "tok.npz") as z:
        old = {k: z[k] for k in z.files if k != "floor_window"}
    old["format_version"] = np.int64(1)
    np.savez(tmp_path / "old.npz", **old)
    assert VQTokenizer.load(tmp_path / "old.npz").floor_window == 0
    assert back.floor_clip


def test_version_2_files_keep_their_unclipped_normaliser(tokenizer, tmp_path):
    tokenizer.save(tmp_path / "tok")
    with np.load(tmp_path / "tok.npz") as z:
        v2 = {k: z[k] for k in z.files if k != "floor_clip"}
    v2["format_version"] = np.int64(2)
    np.savez(tmp_path / "v2.npz", **v2)
    old = VQTokenizer.load(tmp_path / "v2.npz")
    assert old.floor_window == 10 and not old.floor_clip
    raw = np.full((4, 2 * FIT["n_mels"]), FLOOR_MIN - 3.0, np.float32)
    np.testing.assert_array_equal(old.normalise(raw), np.full_like(raw, -3.0))
    np.testing.assert_array_equal(tokenizer.normalise(raw), np.zeros_like(raw))


def test_everything_below_the_lowest_floor_reads_as_zero_by_hand(tokenizer):
    # Channel levels under FLOOR_MIN (digital zero's log floor, a dither) are raised to it: zero above
    # the floor. A level above it over a floor under it reads as its height above FLOOR_MIN.
    raw = np.full((3, 2 * FIT["n_mels"]), FLOOR_MIN - 7.0, np.float32)
    raw[1, 0] = FLOOR_MIN - 1.0
    raw[2, 1] = FLOOR_MIN + 2.5
    z = above_floor(raw, window=10, n_mels=FIT["n_mels"])
    want = np.zeros_like(raw)
    want[2, 1] = 2.5
    np.testing.assert_array_equal(z, want)


def test_digital_silence_and_a_dither_give_the_same_tokens(tokenizer):
    n = 2 * 16000
    dither = (10 ** (-90 / 20) * np.random.default_rng(0).standard_normal(n)).astype(np.float32)
    zero = tokenizer.normalise(tokenizer.features(np.zeros(n, np.float32)))
    np.testing.assert_array_equal(zero, np.zeros_like(zero))
    np.testing.assert_array_equal(tokenizer.encode(dither).ids, tokenizer.encode(np.zeros(n, np.float32)).ids)


def test_bad_floor_window_is_refused(tokenizer):
    import dataclasses

    with pytest.raises(ValueError, match="floor_window"):
        dataclasses.replace(tokenizer, floor_window=-1)
