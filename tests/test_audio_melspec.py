"""Log-mel front end: against an independent SciPy STFT reference, filterbank properties, framing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.signal import ShortTimeFFT, get_window

from jaxtalk.audio import hz_to_mel, log_mel, mel_filterbank, mel_to_hz


def _reference_log_mel(x, rate=16000, n_mels=80, n_fft=400, hop=160, floor=1e-10):
    """SciPy's ShortTimeFFT (slice p centred on sample p*hop, zeros outside) + the checked filterbank."""
    stft = ShortTimeFFT(get_window("hann", n_fft), hop=hop, fs=rate, mfft=n_fft, scale_to=None)
    spectrum = stft.stft(np.asarray(x, dtype=np.float64), p0=0, p1=1 + len(x) // hop)
    power = np.abs(spectrum.T) ** 2
    return np.log(np.maximum(power @ mel_filterbank(rate, n_fft, n_mels), floor))


def _test_signal(samples, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(samples) / 16000
    chirp = 0.4 * np.sin(2 * np.pi * (200 * t + 1500 * t**2))
    return chirp + 0.05 * rng.standard_normal(samples)


def test_matches_scipy_reference_float64(float64):
    x = _test_signal(8000 + 37)  # not a multiple of the hop
    out = np.asarray(log_mel(jnp.asarray(x)))
    ref = _reference_log_mel(x)
    assert out.shape == ref.shape == (1 + x.size // 160, 80)
    np.testing.assert_allclose(out, ref, atol=1e-4, rtol=0)


def test_matches_scipy_reference_float32():
    x = _test_signal(16000, seed=1)
    out = log_mel(jnp.asarray(x, dtype=jnp.float32))
    assert out.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(out), _reference_log_mel(x), atol=2e-3, rtol=0)


def test_other_settings_match_reference(float64):
    x = _test_signal(3000, seed=2)
    out = np.asarray(log_mel(jnp.asarray(x), n_mels=40, n_fft=512, hop_length=128))
    np.testing.assert_allclose(out, _reference_log_mel(x, n_mels=40, n_fft=512, hop=128), atol=1e-4)


def test_slaney_scale_hand_values():
    # Linear below 1 kHz at 200/3 Hz per mel; 27 mel per factor 6.4 above.
    np.testing.assert_allclose(hz_to_mel([0.0, 500.0, 1000.0, 6400.0]), [0.0, 7.5, 15.0, 42.0])
    f = np.array([30.0, 700.0, 1000.0, 2500.0, 7999.0])
    np.testing.assert_allclose(mel_to_hz(hz_to_mel(f)), f)


def test_filterbank_properties():
    # Fine FFT grid so that sums approximate integrals over frequency.
    rate, n_fft, n_mels = 16000, 16384, 20
    bank = mel_filterbank(rate, n_fft, n_mels)
    df = rate / n_fft
    freqs = np.arange(n_fft // 2 + 1) * df
    edges = mel_to_hz(np.linspace(0.0, hz_to_mel(rate / 2), n_mels + 2))
    assert bank.shape == (n_fft // 2 + 1, n_mels) and np.all(bank >= 0)
    # Slaney normalisation: each triangle has unit area in Hz.
    np.testing.assert_allclose(bank.sum(axis=0) * df, 1.0, rtol=2e-3)
    # Peaks at the mel-spaced centres; support strictly inside the neighbouring edges.
    np.testing.assert_allclose(freqs[bank.argmax(axis=0)], edges[1:-1], atol=df)
    for m in range(n_mels):
        support = freqs[bank[:, m] > 0]
        assert support.min() > edges[m] and support.max() < edges[m + 2]
    # Unnormalised triangles form a partition of unity between the first and last centre.
    unnormalised = bank / (2.0 / (edges[2:] - edges[:-2]))
    inside = (freqs > edges[1]) & (freqs < edges[-2])
    np.testing.assert_allclose(unnormalised[inside].sum(axis=1), 1.0, atol=1e-9)


def test_sine_lights_up_nearest_channel():
    t = np.arange(16000) / 16000
    out = np.asarray(log_mel(jnp.asarray(0.5 * np.sin(2 * np.pi * 1000 * t), dtype=jnp.float32)))
    centres = mel_to_hz(np.linspace(0.0, hz_to_mel(8000.0), 82))[1:-1]
    assert np.all(out[5:-5].argmax(axis=1) == np.argmin(np.abs(centres - 1000.0)))


def test_frame_f_is_centred_on_sample_f_times_hop():
    x = np.zeros(16000, dtype=np.float32)
    x[37 * 160] = 1.0
    energy = np.exp(np.asarray(log_mel(jnp.asarray(x)))).sum(axis=1)
    assert energy.shape == (101,)  # 100 frames/s plus the frame at t = 1 s
    assert energy.argmax() == 37
    # The click is within 200 samples of frames 36..38 only (25 ms window, 10 ms hop).
    lit = np.flatnonzero(energy > 1e-6)  # silent frames sit at 80 * floor = 8e-9
    np.testing.assert_array_equal(lit, [36, 37, 38])


def test_silence_hits_the_floor():
    out = log_mel(jnp.zeros(16000, dtype=jnp.float32))  # same shape as other tests: no new compile
    np.testing.assert_allclose(np.asarray(out), np.log(1e-10), rtol=1e-6)


def test_batched_and_jitted_equal_single():
    rng = np.random.default_rng(3)
    x = jnp.asarray(0.1 * rng.standard_normal((2, 3, 1600)), dtype=jnp.float32)
    out = log_mel(x)
    assert out.shape == (2, 3, 11, 80)
    np.testing.assert_allclose(np.asarray(out[1, 2]), np.asarray(log_mel(x[1, 2])), atol=1e-5)
    jitted = jax.jit(lambda a: log_mel(a, n_mels=64))(x)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(log_mel(x, n_mels=64)), atol=1e-5)
    vmapped = jax.vmap(log_mel)(x[0])
    np.testing.assert_allclose(np.asarray(vmapped), np.asarray(out[0]), atol=1e-5)


def test_reflect_and_uncentred_framing(float64):
    x = _test_signal(2000, seed=4)
    uncentred = np.asarray(log_mel(jnp.asarray(x), center=False))
    centred = np.asarray(log_mel(jnp.asarray(x)))
    # Uncentred frame f covers x[f*hop : f*hop + 400]: brute-force framing + rfft.
    window = get_window("hann", 400)
    frames = np.stack(
        [x[f * 160 : f * 160 + 400] * window for f in range(1 + (x.size - 400) // 160)]
    )
    ref = np.log(np.maximum(np.abs(np.fft.rfft(frames, axis=1)) ** 2 @ mel_filterbank(), 1e-10))
    assert uncentred.shape == (1 + (x.size - 400) // 160, 80)
    np.testing.assert_allclose(uncentred, ref[: uncentred.shape[0]], atol=1e-4)
    reflect = np.asarray(log_mel(jnp.asarray(x), pad_mode="reflect"))
    np.testing.assert_allclose(
        reflect[2:-2], centred[2:-2], atol=1e-9
    )  # padding only touches the edges
    assert not np.allclose(reflect[0], centred[0])


@pytest.mark.parametrize(
    ("audio", "kwargs", "message"),
    [
        (np.zeros(0, np.float32), {}, "samples > 0"),
        (np.array([0.0, np.nan] * 300, np.float32), {}, "NaN"),
        (np.zeros(800, np.float32), {"n_mels": 256}, "too many"),
        (np.zeros(800, np.float32), {"f_max": 9000.0}, "f_max"),
        (np.zeros(800, np.float32), {"win_length": 500}, "win_length"),
        (np.zeros(800, np.float32), {"pad_mode": "edge"}, "pad_mode"),
        (np.zeros(300, np.float32), {"center": False}, "center=False"),
        (np.zeros(100, np.float32), {"pad_mode": "reflect"}, "reflect"),
    ],
)
def test_bad_input_raises(audio, kwargs, message):
    with pytest.raises(ValueError, match=message):
        log_mel(audio, **kwargs)


def test_integer_audio_is_rejected():
    # The jaxtyping checker (tests) or log_mel's own check (library use) rejects non-float audio.
    with pytest.raises((TypeError, ValueError), match="[Ff]loat"):
        log_mel(np.zeros(400, np.int32))
