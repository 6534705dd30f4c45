"""Recording chains: determinism, each stage's effect measured on known signals, causality."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxtalk.audio.augment import RecordingChain, apply_chain, draw_chain, record

SR = 16000
CLEAN = RecordingChain(rt60=0.0, wet=0.0, band="full", cutoff=8000.0, mulaw=False, gain_db=0.0,
                       noise="white", noise_dbfs=-300.0, seed=0)


def _sine(freq, seconds=1.0, amplitude=0.1):
    t = np.arange(int(SR * seconds)) / SR
    return (amplitude * np.sin(2 * np.pi * freq * t)).astype(np.float32)


def _db(x):
    return 10 * np.log10(np.mean(np.asarray(x, np.float64) ** 2))


def test_same_generator_state_gives_the_same_bytes_and_another_differs():
    x = _sine(440)
    a = record(x, SR, np.random.default_rng(3))
    b = record(x, SR, np.random.default_rng(3))
    c = record(x, SR, np.random.default_rng(4))
    assert a.dtype == np.float32 and a.shape == x.shape
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()


def test_gain_is_exact_in_db():
    x = _sine(440)
    y = apply_chain(x, SR, dataclasses.replace(CLEAN, gain_db=-12.0))
    assert _db(y) - _db(x) == pytest.approx(-12.0, abs=1e-4)


@pytest.mark.parametrize("colour", ["white", "pink", "brown"])
def test_background_noise_has_the_drawn_level_on_silence(colour):
    y = apply_chain(np.zeros(2 * SR, np.float32), SR, dataclasses.replace(CLEAN, noise=colour, noise_dbfs=-40.0))
    assert _db(y) == pytest.approx(-40.0, abs=0.01)


def test_phone_band_keeps_speech_frequencies_and_removes_the_rest():
    chain = dataclasses.replace(CLEAN, band="phone")
    keep, low, high = (apply_chain(_sine(f), SR, chain)[SR // 4:] for f in (1000, 80, 6000))
    assert _db(keep) - _db(_sine(1000)[SR // 4:]) > -1.0
    assert _db(low) - _db(_sine(80)[SR // 4:]) < -20.0
    assert _db(high) - _db(_sine(6000)[SR // 4:]) < -20.0


def test_reverberation_adds_a_decaying_tail_after_the_sound_stops():
    x = np.concatenate([_sine(500, 0.3), np.zeros(SR // 2, np.float32)])
    y = apply_chain(x, SR, dataclasses.replace(CLEAN, rt60=0.5, wet=0.4))
    tail = slice(int(0.35 * SR), int(0.45 * SR))
    later = slice(int(0.65 * SR), int(0.75 * SR))
    assert np.abs(x[tail]).max() == 0 and _db(y[tail]) > -60.0
    assert _db(y[later]) < _db(y[tail]) - 15.0  # 0.3 s later: about 36 dB down at an RT60 of 0.5 s


def test_mulaw_quantises_to_256_levels():
    y = apply_chain(np.linspace(-0.9, 0.9, 5000, dtype=np.float32), SR, dataclasses.replace(CLEAN, mulaw=True))
    assert 200 <= len(np.unique(y)) <= 256


def test_chain_is_causal():
    rng = np.random.default_rng(0)
    x = (0.1 * rng.standard_normal(SR)).astype(np.float32)
    changed = x.copy()
    changed[SR // 2:] = 0.5
    for seed in range(6):
        chain = dataclasses.replace(draw_chain(np.random.default_rng(seed)), mulaw=False)
        a, b = apply_chain(x, SR, chain), apply_chain(changed, SR, chain)
        np.testing.assert_allclose(a[:SR // 2], b[:SR // 2], atol=1e-6)


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="finite 1-D"):
        apply_chain(np.full(10, np.nan, np.float32), SR, CLEAN)
    with pytest.raises(ValueError, match="8000 Hz"):
        apply_chain(np.zeros(10, np.float32), 4000, CLEAN)
    with pytest.raises(ValueError, match="unknown band"):
        apply_chain(np.zeros(10, np.float32), SR, dataclasses.replace(CLEAN, band="radio"))
    with pytest.raises(ValueError, match="unknown noise"):
        apply_chain(np.zeros(10, np.float32), SR, dataclasses.replace(CLEAN, noise="hum"))


def test_a_chain_without_noise_keeps_digital_silence_at_zero():
    chain = dataclasses.replace(CLEAN, noise="none", noise_dbfs=-40.0, gain_db=6.0, rt60=0.3, wet=0.3, band="phone")
    y = apply_chain(np.zeros(SR, np.float32), SR, chain)
    assert np.array_equal(y, np.zeros(SR, np.float32))


def test_about_a_fifth_of_drawn_chains_add_no_noise():
    chains = [draw_chain(np.random.default_rng(s)) for s in range(2000)]
    share = np.mean([c.noise == "none" for c in chains])
    assert 0.17 < share < 0.23
    assert {c.noise for c in chains} == {"white", "pink", "brown", "none"}
    assert all(-75.0 <= c.noise_dbfs <= -38.0 for c in chains)
