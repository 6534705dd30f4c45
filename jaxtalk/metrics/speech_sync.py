"""How a predicted mouth follows real speech: jaw opening against a tracked jaw or the sound itself.

Real recordings come without the generator's ground truth, and often without any tracked motion, so
these metrics need only the jaw opening (``params[:, JAW_OPEN_INDEX]``, radians) and the audio:

* :func:`frame_loudness`: the speech's log loudness per motion frame (dB re. full scale). It is also
  the *loudness follower*, the baseline every lip-sync model must beat: a mouth that opens with the
  sound's level.
* :func:`lagged_correlation`: Pearson correlation of a prediction with a reference at every lag, and
  the lag of the best one (positive: the prediction is late).
* :func:`voice_activity`: speech vs silence frames from the loudness (an energy detector with a
  noise floor read from the recording itself).
* :func:`speech_sync`: all of it for one clip, beside the loudness follower.
* :func:`style_rest_jaw`: the jaw opening a reference (style) clip rests at, the target of a mouth in
  silence.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from jaxtyping import Bool, Float

from jaxtalk.checks import check_finite

__all__ = ["SpeechSync", "frame_loudness", "lagged_correlation", "voice_activity", "speech_sync",
           "style_rest_jaw", "SILENCE_DB", "SPEECH_ABOVE_FLOOR_DB", "REST_PERCENTILE"]

# Frames quieter than this (dBFS) are silence whatever the recording: -40 dBFS background noise is
# silence, the quietest speech of a close microphone is well above it.
SILENCE_DB = -40.0
# Speech stands this far above the recording's noise floor (its 10th loudness percentile).
SPEECH_ABOVE_FLOOR_DB = 15.0
# A speaker's rest jaw is the low end of its jaw opening over a clip: the jaw only opens from rest to
# speak, and every clip of talk has pauses in which it returns there.
REST_PERCENTILE = 5.0
_EPS_POWER = 1e-10  # -100 dBFS: digital silence stays finite


def _check_1d(x: np.ndarray, name: str, min_len: int = 1, unit: str = "frame") -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional ({unit}s,), got shape {x.shape}")
    if x.shape[0] < min_len:
        raise ValueError(f"{name} needs at least {min_len} {unit}(s), got {x.shape[0]}")
    check_finite(x, name)
    return x.astype(np.float64)


def frame_loudness(audio: Float[np.ndarray, " samples"], sample_rate: int, num_frames: int,
                   fps: float | int = 25.0) -> Float[np.ndarray, " frames"]:
    """Log loudness of each motion frame: ``10 log10(mean(x^2))`` over the frame's samples (dBFS).

    Frame ``k`` covers samples ``[k * sample_rate / fps, (k + 1) * sample_rate / fps)``; frames past
    the audio's end are digital silence (-100 dBFS).

    Args:
        audio: mono waveform in [-1, 1].
        sample_rate: its rate in Hz.
        num_frames: how many motion frames to measure.
        fps: the motion's frame rate.

    Raises:
        ValueError: for a non-1-D, empty or non-finite waveform, a non-positive rate or frame count.
    """
    audio = _check_1d(audio, "audio", unit="sample")
    if sample_rate <= 0 or fps <= 0 or num_frames < 1:
        raise ValueError(f"sample_rate, fps and num_frames must be positive, got {sample_rate}, {fps}, {num_frames}")
    bounds = np.round(np.arange(num_frames + 1) * (sample_rate / fps)).astype(np.int64)
    power = np.full(num_frames, _EPS_POWER)
    squares = np.concatenate([[0.0], np.cumsum(audio ** 2)])
    lo, hi = np.minimum(bounds[:-1], audio.shape[0]), np.minimum(bounds[1:], audio.shape[0])
    inside = hi > lo
    power[inside] = np.maximum((squares[hi[inside]] - squares[lo[inside]]) / (hi[inside] - lo[inside]), _EPS_POWER)
    return 10.0 * np.log10(power)


def lagged_correlation(pred: Float[np.ndarray, " frames"], ref: Float[np.ndarray, " frames"],
                       max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """Pearson correlation of ``pred[t + lag]`` with ``ref[t]`` for every lag in ``[-max_lag, max_lag]``.

    A positive best lag means the prediction is late: it does at ``t + lag`` what the reference does
    at ``t``. Each lag correlates only the frames both sequences have (the overlap shrinks by
    ``|lag|``). A constant overlap has no correlation: NaN.

    Returns:
        ``(lags, r)``: the ``2 max_lag + 1`` lags and their correlations.

    Raises:
        ValueError: for sequences of different lengths, too short for the lags, or non-finite.
    """
    pred, ref = _check_1d(pred, "pred"), _check_1d(ref, "ref")
    if pred.shape != ref.shape:
        raise ValueError(f"pred and ref must have the same length, got {pred.shape[0]} and {ref.shape[0]}")
    if max_lag < 0 or pred.shape[0] < max_lag + 3:
        raise ValueError(f"need a max_lag >= 0 and at least max_lag + 3 frames, got max_lag {max_lag} "
                         f"and {pred.shape[0]} frames")
    lags = np.arange(-max_lag, max_lag + 1)
    r = np.empty(len(lags))
    n = pred.shape[0]
    for i, lag in enumerate(lags):
        a, b = (pred[lag:], ref[:n - lag]) if lag >= 0 else (pred[:n + lag], ref[-lag:])
        # Constant is decided on the values themselves: centring a constant seldom gives exact zeros
        # (its mean is rounded), and two such remainders correlate at +-1.
        if a.min() == a.max() or b.min() == b.max():
            r[i] = np.nan
            continue
        a, b = a - a.mean(), b - b.mean()
        r[i] = float(a @ b) / math.sqrt(float(a @ a) * float(b @ b))
    return lags, r


def voice_activity(loudness_db: Float[np.ndarray, " frames"], *, hangover: int = 2) -> Bool[np.ndarray, " frames"]:
    """Speech frames of a recording from its per-frame loudness (:func:`frame_loudness`).

    A frame is speech when it is louder than :data:`SILENCE_DB` and :data:`SPEECH_ABOVE_FLOOR_DB`
    above the recording's noise floor (its 10th loudness percentile); speech is then extended by
    ``hangover`` frames on both sides (a syllable's quiet edges belong to it).

    Raises:
        ValueError: for a non-1-D, empty or non-finite loudness, or a negative ``hangover``.
    """
    db = _check_1d(loudness_db, "loudness_db")
    if hangover < 0:
        raise ValueError(f"hangover must be >= 0 frames, got {hangover}")
    floor = float(np.percentile(db, 10))
    speech = (db > SILENCE_DB) & (db > floor + SPEECH_ABOVE_FLOOR_DB)
    if hangover > 0 and speech.any():
        # Frame i is speech when any of i - hangover .. i + hangover is: the full convolution, cut to
        # the input's frames (mode "same" returns the kernel's length for inputs shorter than it).
        kernel = np.ones(2 * hangover + 1)
        speech = np.convolve(speech.astype(np.float64), kernel)[hangover:hangover + db.shape[0]] > 0
    return speech


@dataclasses.dataclass(frozen=True)
class SpeechSync:
    """What :func:`speech_sync` measured on one clip (correlations are Pearson's r; lags in frames,
    positive = late; jaw values in radians).

    Attributes:
        frames: frames measured.
        speech_frames: frames :func:`voice_activity` calls speech.
        jaw_silence, jaw_speech: the predicted jaw's mean over silent and speech frames (NaN where
            there are none).
        corr: the predicted jaw against the tracked jaw at lag 0 (NaN without a tracked jaw).
        best_lag, best_corr: the lag of the highest correlation with the tracked jaw and its value.
        loudness_corr, loudness_best_lag, loudness_best_corr: the same for the loudness follower
            (the log loudness against the tracked jaw).
        speech_corr, loudness_speech_corr: the predicted jaw and the loudness against the tracked jaw
            at lag 0 over the speech frames only (NaN with fewer than 3 or a constant track). ``corr``
            mixes two things: whether the mouth is open in speech and shut in silence, and how it
            moves with the syllables while talking; these measure the second alone.
        loudness_pred_corr, loudness_pred_best_lag: the predicted jaw against the log loudness (the
            timing measure of a recording without tracked motion: a mouth that opens on the sound's
            syllables peaks at a lag near 0 or slightly negative, since lips lead sound).
    """

    frames: int
    speech_frames: int
    jaw_silence: float
    jaw_speech: float
    corr: float
    best_lag: int | None
    best_corr: float
    loudness_corr: float
    loudness_best_lag: int | None
    loudness_best_corr: float
    speech_corr: float
    loudness_speech_corr: float
    loudness_pred_corr: float
    loudness_pred_best_lag: int | None

    def to_dict(self) -> dict:
        """JSON-ready (NaN -> None)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in dataclasses.asdict(self).items()}


def _best(lags: np.ndarray, r: np.ndarray) -> tuple[int | None, float]:
    if not np.isfinite(r).any():
        return None, float("nan")
    i = int(np.nanargmax(r))
    return int(lags[i]), float(r[i])


def speech_sync(jaw: Float[np.ndarray, " frames"], audio: Float[np.ndarray, " samples"], sample_rate: int, *,
                tracked_jaw: Float[np.ndarray, " frames"] | None = None, fps: float | int = 25.0,
                max_lag: int = 8) -> SpeechSync:
    """Measure how a predicted jaw opening follows a recording's speech (see :class:`SpeechSync`).

    Args:
        jaw: the prediction's jaw opening per frame (``params[:, JAW_OPEN_INDEX]``).
        audio: the mono waveform it was animated from.
        sample_rate: its rate.
        tracked_jaw: the speaker's tracked jaw opening over the same frames, when there is one.
        fps: the motion's frame rate.
        max_lag: lags searched, in frames, both ways (8 = 320 ms at 25 fps).

    Raises:
        ValueError: for mismatched lengths, non-finite values, or clips too short for ``max_lag``.
    """
    jaw = _check_1d(jaw, "jaw", max_lag + 3)
    n = jaw.shape[0]
    db = frame_loudness(audio, sample_rate, n, fps)
    speech = voice_activity(db)
    nan = float("nan")
    silence_mean = float(jaw[~speech].mean()) if (~speech).any() else nan
    speech_mean = float(jaw[speech].mean()) if speech.any() else nan
    lags, r_ld = lagged_correlation(jaw, db, max_lag)
    ld_lag, _ = _best(lags, r_ld)
    values = dict(corr=nan, best_lag=None, best_corr=nan, loudness_corr=nan, loudness_best_lag=None,
                  loudness_best_corr=nan, speech_corr=nan, loudness_speech_corr=nan)
    if tracked_jaw is not None:
        tracked = _check_1d(tracked_jaw, "tracked_jaw")
        if tracked.shape[0] != n:
            raise ValueError(f"tracked_jaw has {tracked.shape[0]} frames, the prediction {n}")
        _, r = lagged_correlation(jaw, tracked, max_lag)
        _, r_loud = lagged_correlation(db, tracked, max_lag)
        best_lag, best_corr = _best(lags, r)
        loud_lag, loud_corr = _best(lags, r_loud)
        values = dict(corr=float(r[max_lag]), best_lag=best_lag, best_corr=best_corr,
                      loudness_corr=float(r_loud[max_lag]), loudness_best_lag=loud_lag,
                      loudness_best_corr=loud_corr)
        if speech.sum() >= 3:
            values["speech_corr"] = float(lagged_correlation(jaw[speech], tracked[speech], 0)[1][0])
            values["loudness_speech_corr"] = float(lagged_correlation(db[speech], tracked[speech], 0)[1][0])
    return SpeechSync(frames=n, speech_frames=int(speech.sum()), jaw_silence=silence_mean,
                      jaw_speech=speech_mean, loudness_pred_corr=float(r_ld[max_lag]),
                      loudness_pred_best_lag=ld_lag, **values)


def style_rest_jaw(jaw: Float[np.ndarray, " frames"]) -> float:
    """The jaw opening a reference clip rests at: the :data:`REST_PERCENTILE` th percentile of its jaw
    opening (``style[:, JAW_OPEN_INDEX]``, radians).

    A speaker opens the jaw from rest to speak and returns to it in every pause, so the low end of a
    clip's jaw is its rest; on SynthTalk it is the speaker's generated rest jaw. A mouth animated in
    this style should hold this opening in silence.

    Raises:
        ValueError: an empty or non-finite jaw track.
    """
    jaw = _check_1d(jaw, "jaw")
    return float(np.percentile(jaw, REST_PERCENTILE))
