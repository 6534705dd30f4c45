"""``jaxtalk.metrics.speech_sync`` against hand computations on short synthetic clips.

Levels are made exact: a square wave of amplitude ``a`` (alternating sign every sample) has a mean
square of exactly ``a^2`` over any run of samples, so its loudness is ``20 log10(a)`` dB in every
frame; a sine over whole periods has ``a^2 / 2``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxtalk.metrics.speech_sync import (SILENCE_DB, SPEECH_ABOVE_FLOOR_DB, frame_loudness, lagged_correlation, style_rest_jaw,
                                         speech_sync, voice_activity)




def _square(db: float, samples: int) -> np.ndarray:
    """``samples`` of a +-a square wave at ``db`` dBFS (mean square exactly ``a^2``)."""
    a = 10.0 ** (db / 20.0)
    return a * np.where(np.arange(samples) % 2 == 0, 1.0, -1.0)


def _frames_at(levels_db: list[float], samples_per_frame: int) -> np.ndarray:
    """One square-wave frame per level (``None``: digital silence)."""
    return np.concatenate([np.zeros(samples_per_frame) if db is None else _square(db, samples_per_frame)
                           for db in levels_db])


# ------------------------------------------------------------------------------------ frame_loudness


def test_frame_loudness_of_a_sine_and_a_half_silent_frame():
    sr, fps = 16000, 25  # 640 samples per frame; a 100-Hz sine has 4 whole periods in each
    t = np.arange(3 * 640) / sr
    x = 0.5 * np.sin(2 * np.pi * 100 * t)
    x[640:960] = 0.0  # frame 1: its first half silent
    db = frame_loudness(x, sr, 3, fps)
    full = 10 * math.log10(0.5 ** 2 / 2)  # -9.0309 dB
    np.testing.assert_allclose(db, [full, 10 * math.log10(0.5 ** 2 / 4), full], atol=1e-9)
    assert db[1] == pytest.approx(full - 10 * math.log10(2), abs=1e-9)  # half the power: -3.01 dB


def test_frame_loudness_frame_boundaries_at_sample_rate_over_fps():
    # 1000 Hz at 30 fps: 33.33 samples per frame, frame k starts at round(33.33 k): 0, 33, 67, 100.
    sr, fps = 1000, 30.0
    for sample, frame, width in ((32, 0, 33), (33, 1, 34), (66, 1, 34), (67, 2, 33)):
        x = np.zeros(100)
        x[sample] = 1.0
        db = frame_loudness(x, sr, 3, fps)
        np.testing.assert_allclose(db[frame], 10 * math.log10(1.0 / width), atol=1e-9)
        np.testing.assert_array_equal(np.delete(db, frame), -100.0)  # the other frames: digital silence


def test_frame_loudness_past_the_end_is_minus_100_db_and_a_partial_frame_averages_what_it_has():
    sr, fps = 1000, 25  # 40 samples per frame
    x = _square(-20.0, 1020)  # 25 whole frames, then 20 samples of frame 25
    db = frame_loudness(x, sr, 30, fps)
    np.testing.assert_allclose(db[:26], -20.0, atol=1e-9)  # frame 25: the mean over its 20 samples
    np.testing.assert_array_equal(db[26:], -100.0)
    np.testing.assert_array_equal(frame_loudness(np.zeros(400), sr, 10, fps), -100.0)  # digital silence


def test_frame_loudness_user_errors(no_typecheck):
    with pytest.raises(ValueError, match="one-dimensional"):
        frame_loudness(np.zeros((10, 2)), 16000, 1)
    with pytest.raises(ValueError, match="at least 1 sample"):
        frame_loudness(np.zeros(0), 16000, 1)
    with pytest.raises(ValueError, match="non-finite"):
        frame_loudness(np.array([0.1, np.nan]), 16000, 1)
    for sr, frames, fps in ((0, 1, 25.0), (16000, 0, 25.0), (16000, 1, 0.0)):
        with pytest.raises(ValueError, match="must be positive"):
            frame_loudness(np.zeros(640), sr, frames, fps)


# -------------------------------------------------------------------------------- lagged_correlation


@pytest.mark.parametrize("k", [1, 3, 5])
def test_lagged_correlation_of_a_shifted_copy_peaks_at_its_shift(k):
    n, max_lag = 40, 6
    s = np.random.default_rng(k).normal(size=n + k)
    ref, late = s[k:], s[:n]  # late[t + k] == ref[t]: the prediction is k frames late
    lags, r = lagged_correlation(late, ref, max_lag)
    np.testing.assert_array_equal(lags, np.arange(-max_lag, max_lag + 1))
    assert lags[np.argmax(r)] == k and r[np.argmax(r)] == pytest.approx(1.0, abs=1e-12)
    # Every lag: Pearson's r of pred[t + lag] with ref[t] on the frames both have, by hand.
    for lag, value in zip(lags, r):
        t = np.arange(max(0, -lag), min(n, n - lag))
        assert value == pytest.approx(np.corrcoef(late[t + lag], ref[t])[0, 1], abs=1e-12), lag
    # The other direction: a prediction k frames early peaks at -k.
    lags, r = lagged_correlation(ref, late, max_lag)
    assert lags[np.argmax(r)] == -k and r[np.argmax(r)] == pytest.approx(1.0, abs=1e-12)


def test_lagged_correlation_of_a_constant_overlap_is_nan():
    ramp = np.arange(20.0)
    # A constant whose centring is not exact in floating point (0.512 - mean != 0): still no correlation.
    for c in (0.1, 0.5118216247002567, np.float32(0.37)):
        _, r = lagged_correlation(np.full(20, c), ramp, 3)
        assert np.isnan(r).all(), c
        _, r = lagged_correlation(np.full(20, c), np.full(20, 0.9504636963259353), 3)
        assert np.isnan(r).all(), c  # two constants: NaN, not +-1
    # Constant only on the overlap of some lags: those lags are NaN, the others are not.
    pred = np.concatenate([np.full(10, 0.3), [1.0, 2.0, 0.5]])
    lags, r = lagged_correlation(pred, ramp[:13], 3)
    assert np.isnan(r[lags <= -3]).all() and np.isfinite(r[lags >= 0]).all()


def test_lagged_correlation_user_errors(no_typecheck):
    x = np.arange(10.0)
    with pytest.raises(ValueError, match="same length, got 10 and 9"):
        lagged_correlation(x, x[:9], 2)
    with pytest.raises(ValueError, match="at least max_lag \\+ 3 frames"):
        lagged_correlation(x, x, 8)  # 10 frames: at most max_lag 7
    lagged_correlation(x, x, 7)
    with pytest.raises(ValueError, match="max_lag >= 0"):
        lagged_correlation(x, x, -1)
    with pytest.raises(ValueError, match="pred contains 1 non-finite"):
        lagged_correlation(np.where(x == 3, np.nan, x), x, 2)
    with pytest.raises(ValueError, match="ref must be one-dimensional"):
        lagged_correlation(x, x[:, None], 2)


# ------------------------------------------------------------------------------------ voice_activity


def test_voice_activity_on_a_loud_quiet_noise_signal():
    sr, fps, spf = 16000, 25, 640
    # Frames: 0-9 quiet room (-60 dB), 10-12 speech (-10 dB), 13-22 quiet, 23-27 a -30 dB murmur (30 dB
    # above the floor and above -40: speech), 28-37 quiet, 38 digital silence.
    levels = [-60.0] * 10 + [-10.0] * 3 + [-60.0] * 10 + [-30.0] * 5 + [-60.0] * 10 + [None]
    db = frame_loudness(_frames_at(levels, spf), sr, len(levels), fps)
    np.testing.assert_allclose(db, [-100.0 if v is None else v for v in levels], atol=1e-9)
    expected = np.zeros(len(levels), bool)
    expected[8:15] = True  # 10-12, two frames of hangover either side
    expected[21:30] = True  # 23-27
    np.testing.assert_array_equal(voice_activity(db), expected)
    np.testing.assert_array_equal(voice_activity(db, hangover=0), [v is not None and v > -40 for v in levels])


def test_voice_activity_absolute_rule_minus_40_dbfs():
    # Floor -80 dB: a -42 dB hum is 38 dB above it, yet below -40 dBFS: silence; -38 dB is speech.
    db = np.array([-80.0] * 10 + [-42.0] * 3 + [-80.0] * 5 + [-38.0] * 2 + [-80.0] * 5)
    assert SILENCE_DB == -40.0
    speech = voice_activity(db, hangover=0)
    np.testing.assert_array_equal(np.flatnonzero(speech), [18, 19])


def test_voice_activity_relative_rule_above_the_noise_floor():
    # A noisy recording (floor -35 dB, all above -40): 10 dB above the floor is noise, 20 dB is speech.
    db = np.array([-35.0] * 12 + [-25.0] * 3 + [-35.0] * 3 + [-15.0] * 2 + [-35.0] * 5)
    assert SPEECH_ABOVE_FLOOR_DB == 15.0
    np.testing.assert_array_equal(np.flatnonzero(voice_activity(db, hangover=0)), [18, 19])
    # Floor -35 + 15 = -20: a frame exactly at -20 is not above it.
    db[18] = -20.0
    np.testing.assert_array_equal(np.flatnonzero(voice_activity(db, hangover=0)), [19])


def test_voice_activity_hangover_at_the_edges_and_on_short_inputs():
    db = np.array([-10.0] + [-80.0] * 9 + [-10.0])
    np.testing.assert_array_equal(np.flatnonzero(voice_activity(db, hangover=3)), [0, 1, 2, 3, 7, 8, 9, 10])
    # Shorter than the hangover's window: one value per frame still.
    short = voice_activity(np.array([-10.0, -80.0, -80.0]), hangover=2)
    np.testing.assert_array_equal(short, [True, True, True])
    assert voice_activity(np.array([-10.0]), hangover=5).shape == (1,)
    np.testing.assert_array_equal(voice_activity(np.full(6, -80.0)), False)  # no speech: nothing to extend


def test_voice_activity_user_errors(no_typecheck):
    with pytest.raises(ValueError, match="one-dimensional"):
        voice_activity(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="at least 1 frame"):
        voice_activity(np.zeros(0))
    with pytest.raises(ValueError, match="non-finite"):
        voice_activity(np.array([-10.0, np.inf]))
    with pytest.raises(ValueError, match="hangover must be >= 0"):
        voice_activity(np.zeros(5), hangover=-1)


# -------------------------------------------------------------------------------------- speech_sync


def _clip() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """50 frames at 1 kHz / 25 fps (40 samples each): silence (-60 dB) but for speech in frames 20-29,
    louder in 24-26; a jaw that opens with it; the loudness per frame."""
    levels = [-60.0] * 20 + [-20.0] * 4 + [-10.0] * 3 + [-20.0] * 3 + [-60.0] * 20
    jaw = np.full(50, 0.02)
    jaw[20:30] = 0.15
    jaw[24:27] = 0.3
    return _frames_at(levels, 40), jaw, np.asarray(levels)


def test_speech_sync_jaw_in_silence_and_speech_by_hand():
    audio, jaw, _ = _clip()
    m = speech_sync(jaw, audio, 1000, max_lag=4)
    # Speech 20-29 plus two frames of hangover: 18-31.
    assert (m.frames, m.speech_frames) == (50, 14)
    assert m.jaw_speech == pytest.approx((4 * 0.02 + 7 * 0.15 + 3 * 0.3) / 14, abs=1e-12)
    assert m.jaw_silence == pytest.approx(0.02, abs=1e-12)
    assert np.isnan(m.corr) and m.best_lag is None and m.loudness_best_lag is None  # no tracked jaw
    d = m.to_dict()
    assert d["corr"] is None and d["best_corr"] is None and d["jaw_speech"] == m.jaw_speech


def test_speech_sync_against_a_tracked_jaw_by_hand():
    audio, jaw, db = _clip()
    tracked = np.roll(jaw, -2)  # the prediction is 2 frames late: jaw[t + 2] == tracked[t]
    tracked[-2:] = 0.02
    m = speech_sync(jaw, audio, 1000, tracked_jaw=tracked, max_lag=4)
    assert m.best_lag == 2 and m.best_corr == pytest.approx(1.0, abs=1e-12)
    assert m.corr == pytest.approx(np.corrcoef(jaw, tracked)[0, 1], abs=1e-12)
    assert m.loudness_corr == pytest.approx(np.corrcoef(db, tracked)[0, 1], abs=1e-9)
    assert m.loudness_pred_corr == pytest.approx(np.corrcoef(jaw, db)[0, 1], abs=1e-9)
    _, r = lagged_correlation(db, tracked, 4)
    assert (m.loudness_best_lag, m.loudness_best_corr) == (int(np.argmax(r)) - 4, pytest.approx(r.max()))
    assert m.loudness_best_lag == 2  # the loudness follows the sound: as late as the prediction here
    # The loudness and the jaw share their timing in this clip: the prediction peaks at lag 0 on it.
    assert m.loudness_pred_best_lag == 0
    # Within speech only, at lag 0: by hand over the frames voice_activity calls speech.
    speech = voice_activity(db)
    assert 3 <= speech.sum() < speech.size
    assert m.speech_corr == pytest.approx(np.corrcoef(jaw[speech], tracked[speech])[0, 1], abs=1e-12)
    assert m.loudness_speech_corr == pytest.approx(np.corrcoef(db[speech], tracked[speech])[0, 1], abs=1e-9)


def test_speech_sync_within_speech_separates_articulation_from_the_speech_silence_contrast():
    # A tracked jaw that is only a speech detector (open while talking, shut in silence) and a
    # prediction that is that detector plus syllable motion: high corr overall, none within speech.
    audio, jaw, db = _clip()
    speech = voice_activity(db)
    tracked = np.where(speech, 0.1, 0.0)
    tracked[np.flatnonzero(speech)[::2]] += 1e-3  # not constant within speech
    syllables = np.where(speech, 0.05 * np.sin(np.arange(speech.size) * 2.1), 0.0)
    m = speech_sync(tracked + syllables, audio, 1000, tracked_jaw=tracked, max_lag=4)
    assert m.corr > 0.8 and abs(m.speech_corr) < 0.5
    assert m.speech_corr == pytest.approx(np.corrcoef((tracked + syllables)[speech], tracked[speech])[0, 1], abs=1e-12)


def test_speech_sync_on_digital_silence_is_all_silence():
    jaw = np.linspace(0.0, 0.1, 30)
    m = speech_sync(jaw, np.zeros(30 * 640), 16000)
    assert m.speech_frames == 0 and m.jaw_silence == pytest.approx(0.05) and np.isnan(m.jaw_speech)
    assert np.isnan(m.loudness_pred_corr) and m.loudness_pred_best_lag is None  # the loudness is constant


def test_speech_sync_user_errors(no_typecheck):
    audio, jaw, _ = _clip()
    with pytest.raises(ValueError, match="jaw must be one-dimensional"):
        speech_sync(np.zeros((50, 56)), audio, 1000)
    with pytest.raises(ValueError, match="jaw needs at least 11 frame"):
        speech_sync(jaw[:10], audio, 1000)  # max_lag 8 needs 11 frames
    with pytest.raises(ValueError, match="jaw contains 1 non-finite"):
        speech_sync(np.where(np.arange(50) == 7, np.nan, jaw), audio, 1000)
    with pytest.raises(ValueError, match="tracked_jaw has 49 frames, the prediction 50"):
        speech_sync(jaw, audio, 1000, tracked_jaw=jaw[:49])
    with pytest.raises(ValueError, match="tracked_jaw contains 1 non-finite"):
        speech_sync(jaw, audio, 1000, tracked_jaw=np.where(np.arange(50) == 3, np.inf, jaw))
    with pytest.raises(ValueError, match="audio contains"):
        speech_sync(jaw, np.full(100, np.nan), 1000)
    with pytest.raises(ValueError, match="must be positive"):
        speech_sync(jaw, audio, 0)


def test_style_rest_jaw_is_the_fifth_percentile_by_hand():
    # 100 frames: 20 at rest (0.03), 80 opening to 0.1..0.4: the 5th percentile lies among the rests.
    jaw = np.concatenate([np.full(20, 0.03), np.linspace(0.1, 0.4, 80)])
    assert style_rest_jaw(np.random.default_rng(0).permutation(jaw)) == pytest.approx(0.03)
    # 0..99: numpy's linear percentile 5 of 0..99 is 4.95.
    assert style_rest_jaw(np.arange(100.0)) == pytest.approx(4.95)


def test_style_rest_jaw_of_neutral_synthtalk_clips_is_their_speakers_generated_rest(synthtalk_tiny):
    from jaxtalk.layout import JAW_OPEN_INDEX

    # An emotion moves a clip's resting face (a drunk jaw hangs open), so neutral clips only.
    neutral = [i for i in range(len(synthtalk_tiny.clips)) if synthtalk_tiny.clips[i].emotion == "neutral"]
    assert len(neutral) >= 3
    for clip in neutral:
        info = synthtalk_tiny.clips[clip]
        rest = synthtalk_tiny.speakers[info.speaker].style.rest[JAW_OPEN_INDEX]
        jaw = np.asarray(synthtalk_tiny.motion(clip))[:, JAW_OPEN_INDEX]
        assert style_rest_jaw(jaw) == pytest.approx(rest, abs=0.005)


def test_style_rest_jaw_user_errors(no_typecheck):
    with pytest.raises(ValueError, match="at least 1"):
        style_rest_jaw(np.zeros(0))
    with pytest.raises(ValueError, match="one-dimensional"):
        style_rest_jaw(np.zeros((4, 56)))
    with pytest.raises(ValueError, match="NaN|finite"):
        style_rest_jaw(np.array([0.1, np.nan]))
