"""Real recordings to measure a model's jaw on: a ``--real-voice`` folder, read and checked once.

A folder holds recordings (``.wav``, ``.flac``...; any rate, mono or stereo), each optionally with its
speaker's tracked motion beside it under the same name (``STEM.npz`` holding DualTalk's ``pose (T, 6)``,
jaw = ``pose[:, 3]``, or jaxtalk's ``params (T, 56)``, jaw = ``params[:, 50]``, at 25 fps).
``jaxtalk eval --real-voice`` and TokTalk's real-voice validation during training
(:func:`jaxtalk.models.toktalk.validation.real_voice_validation`) both read it here and measure a
prediction the same way:

* :func:`read_recordings`: the folder's :class:`Recording` s (audio at 16 kHz, tracked jaw or None),
  every bad file refused with a one-line ``ValueError`` naming it.
* :func:`recording_sync`: :func:`~jaxtalk.metrics.speech_sync.speech_sync` of a prediction for one
  recording (cut to the tracked motion's frames, lags up to :data:`MAX_LAG`).
* :func:`sync_row` and :func:`mean_row`: a recording's measures as a table row, and the recordings'
  mean (the tracked-jaw columns over the recordings with tracked motion).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float

from jaxtalk.metrics.speech_sync import SpeechSync, speech_sync

__all__ = ["Recording", "read_recordings", "recording_sync", "sync_row", "mean_row", "SYNC_COLUMNS", "MAX_LAG"]

# Frames of difference between a tracked motion file and its recording's duration still accepted
# (trackers and encoders round the last frame differently).
_MOTION_SLACK_FRAMES = 2
# The lags speech_sync searches, both ways (8 frames = 320 ms at 25 fps).
MAX_LAG = 8


@dataclasses.dataclass(frozen=True)
class Recording:
    """One real recording of a ``--real-voice`` folder.

    Attributes:
        name: its file's stem.
        path: the audio file.
        audio: the waveform, mono 16 kHz.
        tracked_jaw: the speaker's tracked jaw opening per 25-fps frame (radians), or None.
        motion: the tracked-motion file it came from, or None.
    """

    name: str
    path: Path
    audio: np.ndarray
    tracked_jaw: np.ndarray | None
    motion: Path | None


def _tracked_jaw(path: Path, audio_frames: float) -> np.ndarray:
    """The jaw opening of a tracked-motion ``.npz``: DualTalk's ``pose[:, 3]`` or jaxtalk's ``params[:, 50]``."""
    from jaxtalk.files import load_npz
    from jaxtalk.layout import JAW_OPEN_INDEX
    from jaxtalk.types import MOTION_FPS, PARAM_DIM

    data = load_npz(path, what="motion file")
    if "pose" in data:
        motion, key, width, column = data["pose"], "pose", 6, 3
    elif "params" in data:
        motion, key, width, column = data["params"], "params", PARAM_DIM, JAW_OPEN_INDEX
    else:
        raise ValueError(f"{str(path)!r} holds neither 'pose' (frames, 6) nor 'params' (frames, {PARAM_DIM}); "
                         f"found {sorted(data)}")
    if motion.ndim != 2 or motion.shape[1] != width or not np.issubdtype(motion.dtype, np.number):
        raise ValueError(f"{str(path)!r}: {key} must have shape (frames, {width}), got {motion.shape}")
    if "fps" in data and float(data["fps"]) != MOTION_FPS:
        raise ValueError(f"{str(path)!r} is tracked at {float(data['fps']):g} fps; real-voice evaluation compares "
                         f"{MOTION_FPS}-fps motion")
    bad = int(np.size(motion) - np.count_nonzero(np.isfinite(motion)))
    if bad:
        raise ValueError(f"{str(path)!r}: {key} contains {bad} NaN or inf value(s)")
    if abs(motion.shape[0] - audio_frames) > _MOTION_SLACK_FRAMES:
        raise ValueError(f"{str(path)!r} has {motion.shape[0]} frames, its recording lasts {audio_frames:.1f} frames "
                         f"at {MOTION_FPS} fps (more than {_MOTION_SLACK_FRAMES} apart): not the same take, or not "
                         f"{MOTION_FPS} fps")
    return np.asarray(motion[:, column], np.float64)


def read_recordings(folder: str | Path, *, min_frames: int = MAX_LAG + 3,
                    echo: Callable[[str], None] = print) -> list[Recording]:
    """The recordings of a ``--real-voice`` folder, each with its tracked jaw where ``STEM.npz`` is beside it.

    Args:
        folder: the folder (not searched recursively).
        min_frames: the shortest recording accepted, in 25-fps frames.
        echo: where notes go (motion files that match no recording).

    Returns:
        :class:`Recording` per audio file, in name order.

    Raises:
        FileNotFoundError / NotADirectoryError: no such folder.
        ValueError: an empty folder, no audio file in it, an unreadable or too short recording, a
            motion file without ``pose``/``params``, with NaN, at another frame rate, or whose frame
            count differs from its recording's duration by more than 2 frames.
    """
    from jaxtalk.audio.io import AUDIO_SUFFIXES, load_audio
    from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

    folder = Path(folder)
    if not folder.exists():
        raise FileNotFoundError(f"--real-voice folder not found: {str(folder)!r}")
    if not folder.is_dir():
        raise NotADirectoryError(f"--real-voice takes a folder of recordings, got the file {str(folder)!r}")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise ValueError(f"the --real-voice folder {str(folder)!r} is empty: put recordings in it "
                         f"({', '.join(AUDIO_SUFFIXES)}), each optionally with its tracked motion as STEM.npz")
    audio_files = [p for p in files if p.suffix.lower() in AUDIO_SUFFIXES]
    if not audio_files:
        raise ValueError(f"the --real-voice folder {str(folder)!r} has no audio file ({', '.join(AUDIO_SUFFIXES)}); "
                         f"found {', '.join(p.name for p in files[:5])}{' ...' if len(files) > 5 else ''}")
    stems = [p.stem for p in audio_files]
    twice = sorted({s for s in stems if stems.count(s) > 1})
    if twice:
        raise ValueError(f"{str(folder)!r} has several audio files named {', '.join(twice)} (one motion file each "
                         "could belong to): keep one")
    recordings = []
    for path in audio_files:
        audio = load_audio(path)
        frames = audio.shape[0] / AUDIO_SAMPLE_RATE * MOTION_FPS
        if frames < min_frames:
            raise ValueError(f"{str(path)!r} lasts {audio.shape[0] / AUDIO_SAMPLE_RATE:.2f} s; real-voice evaluation "
                             f"needs at least {min_frames / MOTION_FPS:g} s ({min_frames} frames)")
        motion = path.with_suffix(".npz")
        tracked = _tracked_jaw(motion, frames) if motion.is_file() else None
        recordings.append(Recording(path.stem, path, audio, tracked, motion if tracked is not None else None))
    unmatched = [p.name for p in files if p.suffix.lower() == ".npz" and p.stem not in stems]
    if unmatched:
        echo(f"note: {', '.join(unmatched)} match(es) no recording (motion goes beside its audio as STEM.npz)")
    return recordings


def recording_sync(recording: Recording, motion: Float[np.ndarray, "frames 56"]) -> SpeechSync:
    """How a prediction's jaw follows one recording: :func:`~jaxtalk.metrics.speech_sync.speech_sync` of
    ``motion[:, JAW_OPEN_INDEX]`` against the recording's audio and its tracked jaw (when it has one),
    over the frames both have (a tracker may give a frame more or less than the audio), lags up to
    :data:`MAX_LAG`.

    Args:
        recording: the recording.
        motion: ``(T, 56)`` head parameters at 25 fps animated from ``recording.audio``.

    Returns:
        :class:`~jaxtalk.metrics.speech_sync.SpeechSync`.

    Raises:
        ValueError: fewer than ``MAX_LAG + 3`` frames, non-finite values.
    """
    from jaxtalk.layout import JAW_OPEN_INDEX
    from jaxtalk.types import AUDIO_SAMPLE_RATE

    tracked = recording.tracked_jaw
    n = motion.shape[0] if tracked is None else min(motion.shape[0], tracked.shape[0])
    return speech_sync(np.asarray(motion)[:n, JAW_OPEN_INDEX], recording.audio, AUDIO_SAMPLE_RATE,
                       tracked_jaw=None if tracked is None else tracked[:n], max_lag=MAX_LAG)


# The columns of a real-voice row after the recording and its frames (SpeechSync's fields).
SYNC_COLUMNS = ("speech_frames", "corr", "best_lag", "best_corr", "loudness_corr", "loudness_best_lag",
                "speech_corr", "loudness_speech_corr", "loudness_pred_corr", "loudness_pred_best_lag",
                "jaw_silence", "jaw_speech")


def sync_row(name: str, tracked: str | None, sync: SpeechSync) -> dict[str, Any]:
    """One recording's row: ``recording``, ``tracked`` (``"yes"``/``"no"``, None for a row that is no
    recording), ``frames`` and the :data:`SYNC_COLUMNS` of a ``SpeechSync`` (None where it has no value)."""
    values = sync.to_dict()
    return {"recording": name, "tracked": tracked, "frames": values["frames"],
            **{k: values[k] for k in SYNC_COLUMNS}}


def mean_row(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The recordings' plain mean per column over those that have it (the tracked-jaw columns: the
    recordings with tracked motion; None where none has it); ``frames`` and ``speech_frames`` summed,
    ``tracked`` says how many of the rows are tracked."""
    tracked = sum(r["tracked"] == "yes" for r in rows)
    out: dict[str, Any] = {"recording": "mean", "tracked": f"{tracked} of {len(rows)}",
                           "frames": sum(r["frames"] for r in rows),
                           "speech_frames": sum(r["speech_frames"] for r in rows)}
    for key in SYNC_COLUMNS[1:]:
        values = [r[key] for r in rows if r[key] is not None]
        out[key] = float(np.mean(values)) if values else None
    return out
