"""Audio file reading (formats, channels), polyphase resampling, and input validation."""

from __future__ import annotations

import numpy as np
import pytest
import soundfile as sf

from jaxtalk.audio import load_audio, rational_ratio, resample_audio, save_audio


def _tone(freq, rate, seconds, amplitude=0.5, phase=0.3):
    t = np.arange(int(round(rate * seconds))) / rate
    return amplitude * np.sin(2 * np.pi * freq * t + phase)


def _fit_sinusoid(x, freq, rate):
    """Least-squares amplitude of a freq-Hz sinusoid in x, and the RMS of what it leaves."""
    t = np.arange(x.size) / rate
    basis = np.stack([np.sin(2 * np.pi * freq * t), np.cos(2 * np.pi * freq * t)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, x.astype(np.float64), rcond=None)
    residual = x - basis @ coef
    return float(np.hypot(*coef)), float(np.sqrt(np.mean(residual**2)))


@pytest.mark.parametrize(
    ("suffix", "subtype", "tolerance"),
    [
        (".wav", "PCM_16", 1.0 / 32768),
        (".wav", "PCM_32", 1e-7),
        (".wav", "FLOAT", 0.0),
        (".flac", "PCM_16", 1.0 / 32768),
        (".flac", "PCM_24", 1.0 / 2**23),
    ],
)
def test_formats_read_back_at_native_rate(tmp_path, suffix, subtype, tolerance):
    signal = _tone(440.0, 16000, 0.25).astype(np.float32)
    path = tmp_path / f"tone_{subtype}{suffix}"
    sf.write(path, signal, 16000, subtype=subtype)
    assert sf.info(path).subtype == subtype  # the file really is in the format under test
    out = load_audio(path)
    assert out.dtype == np.float32 and out.shape == signal.shape
    np.testing.assert_allclose(out, signal, atol=tolerance + 1e-8, rtol=0)


def test_stereo_is_averaged_to_mono(tmp_path):
    left = _tone(300.0, 16000, 0.2, amplitude=0.6)
    right = _tone(1200.0, 16000, 0.2, amplitude=0.2)
    path = tmp_path / "stereo.wav"
    sf.write(path, np.stack([left, right], axis=1), 16000, subtype="FLOAT")
    np.testing.assert_allclose(load_audio(path), (left + right) / 2, atol=1e-7)


def test_resampling_keeps_frequency_and_amplitude(tmp_path):
    path = tmp_path / "cd.wav"
    sf.write(path, _tone(1000.0, 44100, 1.0, amplitude=0.5), 44100, subtype="FLOAT")
    out = load_audio(path, target_rate=16000)
    assert out.shape == (16000,)
    middle = out[2000:-2000]  # away from the filter's edge transients
    amplitude, residual = _fit_sinusoid(middle, 1000.0, 16000)
    assert amplitude == pytest.approx(0.5, rel=2e-3)
    # A shifted frequency would leave a large residual: at 1001 Hz over 0.75 s it is ~0.3.
    assert residual < 2e-3
    assert _fit_sinusoid(middle, 1005.0, 16000)[1] > 0.1


def test_content_above_new_nyquist_is_attenuated(tmp_path):
    # 12 kHz at 48 kHz: naive decimation by 3 would alias it to 4 kHz at full amplitude.
    path = tmp_path / "hi.wav"
    sf.write(path, _tone(12000.0, 48000, 0.5, amplitude=0.5), 48000, subtype="FLOAT")
    out = load_audio(path, target_rate=16000, allow_silence=True)
    naive = _tone(12000.0, 48000, 0.5, amplitude=0.5)[::3]
    assert _fit_sinusoid(naive, 4000.0, 16000)[0] > 0.45  # the alias the filter must remove
    body = out[500:-500]
    assert np.sqrt(np.mean(body**2)) < 0.5 / np.sqrt(2) * 1e-2  # > 40 dB down
    assert _fit_sinusoid(body, 4000.0, 16000)[0] < 5e-3


def test_upsampling_keeps_tone():
    out = resample_audio(_tone(1000.0, 8000, 0.5), 8000, 16000)
    assert out.shape == (8000,) and out.dtype == np.float32
    amplitude, residual = _fit_sinusoid(out[500:-500], 1000.0, 16000)
    assert amplitude == pytest.approx(0.5, rel=2e-3) and residual < 2e-3


def test_rational_ratio():
    assert rational_ratio(44100, 16000) == (160, 441)
    assert rational_ratio(48000, 16000) == (1, 3)
    assert rational_ratio(22050, 16000) == (320, 441)
    assert rational_ratio(8000, 16000) == (2, 1)
    assert rational_ratio(16001, 16000) == (16000, 16001)  # odd integer rates stay exact
    up, down = rational_ratio(44100.123, 16000)  # no exact ratio within bounds: best approximation
    assert down <= 2**15 and abs(up / down - 16000 / 44100.123) < 1e-8
    with pytest.raises(ValueError, match="src_rate"):
        rational_ratio(0, 16000)


def test_save_audio_round_trip(tmp_path):
    signal = _tone(500.0, 16000, 0.1).astype(np.float32)
    path = save_audio(tmp_path / "x.wav", signal, subtype="FLOAT")
    np.testing.assert_array_equal(load_audio(path), signal)
    with pytest.raises(ValueError, match="NaN"):
        save_audio(tmp_path / "bad.wav", np.array([0.0, np.nan], dtype=np.float32))


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.wav"):
        load_audio(tmp_path / "nope.wav")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.wav"
    sf.write(path, np.zeros(0, dtype=np.float32), 16000)
    with pytest.raises(ValueError, match="empty"):
        load_audio(path)


def test_silent_file(tmp_path):
    path = tmp_path / "silent.wav"
    sf.write(path, np.zeros(16000, dtype=np.float32), 16000)
    with pytest.raises(ValueError, match="silent"):
        load_audio(path)
    assert np.all(load_audio(path, allow_silence=True) == 0)


def test_nan_file(tmp_path):
    signal = _tone(440.0, 16000, 0.1).astype(np.float32)
    signal[100] = np.nan
    path = tmp_path / "nan.wav"
    sf.write(path, signal, 16000, subtype="FLOAT")
    with pytest.raises(ValueError, match="NaN/inf samples \\(first at index 100\\)"):
        load_audio(path)


def test_too_short_file(tmp_path):
    path = tmp_path / "short.wav"
    sf.write(path, _tone(440.0, 16000, 0.01), 16000)  # 10 ms < one 25 ms window
    with pytest.raises(ValueError, match="too short"):
        load_audio(path)
    assert load_audio(path, min_duration=0.005).shape == (160,)


def test_undecodable_file_and_bad_rate(tmp_path):
    path = tmp_path / "text.wav"
    path.write_text("not audio")
    with pytest.raises(ValueError, match="cannot decode"):
        load_audio(path)
    good = tmp_path / "good.wav"
    sf.write(good, _tone(440.0, 16000, 0.1), 16000)
    with pytest.raises(ValueError, match="target_rate"):
        load_audio(good, target_rate=0)
