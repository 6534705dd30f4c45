"""Frames -> mp4 (H.264, optional AAC audio track), animated GIF, or PNG; and a small media probe.

Encoding uses the ffmpeg binary shipped with ``imageio-ffmpeg`` (no system ffmpeg needed). Every
writer is atomic: it writes a temporary file beside the target and renames it at the end, so an
error half-way leaves no partial file.

Audio rule (``fit_audio``): the audio track is made exactly as long as the video
(``num_frames / fps`` seconds): a longer track is trimmed at the end, a shorter one padded with
silence at the end. Mismatches up to one video frame are fixed silently (rounding), larger ones up to
``tolerance_s`` with a ``UserWarning``, and larger ones raise ``ValueError`` (usually the wrong
sample rate or the wrong clip).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import subprocess
import tempfile
import warnings
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from jaxtalk.files import atomic_output, check_output_path
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS, Array, Float, Shaped

# Python scalars: beartype (under pytest) does not promote int to float.
Real = int | float

__all__ = ["write_mp4", "write_gif", "save_png", "fit_audio", "probe_media", "MediaInfo"]

ArrayLike = Array | np.ndarray
# Loose on dtype so that non-uint8 input reaches the explicit ValueError (uint8 RGB is required).
Frames = Shaped[np.ndarray, "frames height width channels"] | Iterable[np.ndarray]


def _positive_number(name: str, value: Real) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not value > 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return float(value)


def _check_audio(audio: Shaped[ArrayLike, "..."], sample_rate: int) -> np.ndarray:
    """Audio as float32 ``(samples,)`` or ``(samples, channels)``, validated."""
    if isinstance(sample_rate, bool) or not isinstance(sample_rate, (int, np.integer)) or sample_rate <= 0:
        raise ValueError(f"sample_rate must be a positive integer, got {sample_rate!r}")
    a = np.asarray(audio)
    if a.ndim not in (1, 2) or (a.ndim == 2 and not 1 <= a.shape[1] <= 2):
        raise ValueError(f"audio must have shape (samples,) or (samples, 1|2), got {a.shape}")
    if a.shape[0] == 0:
        raise ValueError("audio is empty")
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"audio must be floating point in [-1, 1], got dtype {a.dtype}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"audio holds NaN or inf (first at sample {int(np.argwhere(~np.isfinite(a))[0, 0])})")
    return a.astype(np.float32, copy=False)


def fit_audio(
    audio: Float[ArrayLike, "..."],
    num_frames: int,
    *,
    fps: Real = MOTION_FPS,
    sample_rate: int = AUDIO_SAMPLE_RATE,
    tolerance_s: Real = 0.5,
) -> Float[np.ndarray, "..."]:
    """Trim or zero-pad an audio track to the duration of ``num_frames`` video frames (module rule).

    Args:
        audio: samples in ``[-1, 1]``, ``(samples,)`` or ``(samples, channels)``.
        num_frames: number of video frames (> 0).
        fps: video frame rate.
        sample_rate: audio sample rate in Hz.
        tolerance_s: largest mismatch in seconds that is fixed (with a warning) instead of raising.

    Returns:
        The audio with exactly ``round(num_frames * sample_rate / fps)`` samples (float32, same
        channel layout).

    Raises:
        ValueError: for malformed audio (shape, empty, non-float, NaN/inf), non-positive sizes or
            rates, or a mismatch larger than ``tolerance_s``.
    """
    a = _check_audio(audio, sample_rate)
    fps = _positive_number("fps", fps)
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames <= 0:
        raise ValueError(f"num_frames must be a positive integer, got {num_frames!r}")
    target = int(round(num_frames * sample_rate / fps))
    diff = a.shape[0] - target
    if abs(diff) > tolerance_s * sample_rate:
        raise ValueError(
            f"audio lasts {a.shape[0] / sample_rate:.3f} s but the {num_frames} frames at {fps:g} fps last "
            f"{target / sample_rate:.3f} s (more than tolerance_s={tolerance_s} apart; wrong sample_rate "
            f"{sample_rate} or wrong clip?)"
        )
    if abs(diff) > sample_rate / fps:
        warnings.warn(
            f"audio ({a.shape[0] / sample_rate:.3f} s) and video ({target / sample_rate:.3f} s) differ by "
            f"{abs(diff) / sample_rate:.3f} s; the audio is {'trimmed' if diff > 0 else 'padded with silence'} "
            f"at the end",
            UserWarning,
            stacklevel=2,
        )
    if diff >= 0:
        return a[:target]
    return np.concatenate([a, np.zeros((-diff, *a.shape[1:]), np.float32)])


def check_audio_duration(
    audio: Float[ArrayLike, "..."],
    num_frames: int,
    *,
    fps: Real = MOTION_FPS,
    sample_rate: int = AUDIO_SAMPLE_RATE,
    tolerance_s: Real = 0.5,
) -> None:
    """Raise now what ``fit_audio`` would raise later (used before spending time on rendering).

    Raises:
        ValueError: as ``fit_audio``; its warning is left for the real call.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        fit_audio(audio, num_frames, fps=fps, sample_rate=sample_rate, tolerance_s=tolerance_s)


def _check_frame(frame: np.ndarray, index: int, shape: tuple[int, ...] | None) -> np.ndarray:
    f = np.asarray(frame)
    if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3:
        raise ValueError(f"frame {index} must be an RGB uint8 image (H, W, 3), got {f.dtype} {f.shape}")
    if shape is not None and f.shape != shape:
        raise ValueError(f"frame {index} has shape {f.shape}, unlike the first frame's {shape}")
    if f.shape[0] == 0 or f.shape[1] == 0:
        raise ValueError(f"frame {index} is empty: {f.shape}")
    return f


def _even(frame: np.ndarray) -> np.ndarray:
    """Pad an odd height/width by repeating the last row/column (H.264 in yuv420p needs even sizes)."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


@contextlib.contextmanager
def _quiet_fork_warning():
    """Silence JAX's os.fork() warning around launching ffmpeg.

    JAX warns on any fork in a process where it runs threads, because a forked child that keeps
    running Python can deadlock. Launching ffmpeg forks and immediately execs a new program, which
    is safe, so the warning is noise here (and only here).
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        yield


def _ffmpeg() -> str:
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def _encode_video(path: Path, frames: Frames, fps: Real, crf: int) -> int:
    """Encode frames to a video-only mp4 at ``path``; returns the number of frames."""
    import imageio_ffmpeg

    writer = None
    shape = None
    count = 0
    try:
        for count, frame in enumerate(frames, start=1):
            f = _check_frame(frame, count - 1, shape)
            if writer is None:
                shape = f.shape
                even = _even(f)
                writer = imageio_ffmpeg.write_frames(
                    str(path),
                    (even.shape[1], even.shape[0]),
                    fps=fps,
                    codec="libx264",
                    pix_fmt_out="yuv420p",
                    quality=None,
                    macro_block_size=1,
                    ffmpeg_log_level="error",
                    output_params=["-crf", str(crf), "-movflags", "+faststart"],
                )
                with _quiet_fork_warning():
                    writer.send(None)  # start the generator (launches ffmpeg)
            writer.send(np.ascontiguousarray(_even(f)))
        if writer is None:
            raise ValueError("no frames to write")
    finally:
        if writer is not None:
            writer.close()
    return count


def write_mp4(
    path: str | os.PathLike,
    frames: Frames,
    *,
    fps: Real = MOTION_FPS,
    audio: Float[ArrayLike, "..."] | None = None,
    sample_rate: int = AUDIO_SAMPLE_RATE,
    audio_tolerance_s: Real = 0.5,
    crf: int = 18,
) -> Path:
    """Encode RGB frames as an H.264 mp4, with an optional AAC audio track, atomically.

    Args:
        path: output file, ending in ``.mp4``.
        frames: ``(T, H, W, 3)`` uint8 array, or any iterable of ``(H, W, 3)`` uint8 frames (e.g.
            ``iter_frames(...)``: frames are encoded as they come, never all held in memory).
            Odd sizes are padded by one edge row/column (yuv420p needs even sizes).
        fps: frame rate.
        audio: optional samples in ``[-1, 1]``, ``(samples,)`` or ``(samples, channels)``, made as long
            as the video by ``fit_audio`` (trim/pad at the end; see the module rule).
        sample_rate: audio sample rate in Hz.
        audio_tolerance_s: passed to ``fit_audio``.
        crf: x264 constant-rate factor (0 lossless .. 51 worst; 18 is visually lossless).

    Returns:
        The written path.

    Raises:
        ValueError: for a bad suffix, no frames, frames that are not uint8 RGB or change size, bad
            fps/crf, malformed audio or audio whose duration is off by more than the tolerance.
        FileNotFoundError, NotADirectoryError, PermissionError: if the directory cannot be written.
        RuntimeError: if ffmpeg fails to mux the audio.
    """
    out = check_output_path(path, (".mp4",))
    fps = _positive_number("fps", fps)
    if isinstance(crf, bool) or not isinstance(crf, (int, np.integer)) or not 0 <= crf <= 51:
        raise ValueError(f"crf must be an integer in [0, 51], got {crf!r}")
    if audio is not None:
        audio = _check_audio(audio, sample_rate)  # fail before encoding anything
        if isinstance(frames, np.ndarray) and frames.ndim == 4 and frames.shape[0] > 0:
            check_audio_duration(audio, frames.shape[0], fps=fps, sample_rate=sample_rate, tolerance_s=audio_tolerance_s)
    with atomic_output(out) as tmp:
        if audio is None:
            _encode_video(tmp, frames, fps, crf)
            return out
        with tempfile.TemporaryDirectory(prefix="jaxtalk_mp4_") as work:
            video = Path(work) / "video.mp4"
            num_frames = _encode_video(video, frames, fps, crf)
            track = fit_audio(audio, num_frames, fps=fps, sample_rate=sample_rate, tolerance_s=audio_tolerance_s)
            wav = Path(work) / "audio.wav"
            import soundfile

            soundfile.write(str(wav), track, sample_rate, subtype="FLOAT")
            cmd = [
                _ffmpeg(), "-y", "-loglevel", "error", "-i", str(video), "-i", str(wav),
                "-map", "0:v:0", "-map", "1:a:0", "-c:v", "copy", "-c:a", "aac", "-b:a", "128k",
                "-movflags", "+faststart", str(tmp),
            ]  # fmt: skip
            with _quiet_fork_warning():
                result = subprocess.run(cmd, capture_output=True, text=True)
            if result.returncode != 0:
                raise RuntimeError(f"ffmpeg failed to mux the audio into {out}: {result.stderr.strip()}")
    return out


def write_gif(path: str | os.PathLike, frames: Frames, *, fps: Real = MOTION_FPS, loop: int = 0) -> Path:
    """Write RGB frames as an animated GIF (Pillow via imageio), atomically.

    GIF frame delays are whole hundredths of a second, so 25 fps (4/100 s) is exact and other rates
    are rounded. Pillow merges identical consecutive frames into one with the summed delay, so a
    clip with still frames reads back with fewer frames but the same timing.

    Args:
        path: output file, ending in ``.gif``.
        frames: ``(T, H, W, 3)`` uint8 array or an iterable of ``(H, W, 3)`` uint8 frames.
        fps: frame rate.
        loop: number of repetitions, 0 = forever.

    Returns:
        The written path.

    Raises:
        ValueError: for a bad suffix, no frames, frames that are not uint8 RGB or change size, bad fps.
        FileNotFoundError, NotADirectoryError, PermissionError: if the directory cannot be written.
    """
    import imageio.v3 as iio

    out = check_output_path(path, (".gif",))
    fps = _positive_number("fps", fps)
    stack: list[np.ndarray] = []
    for i, frame in enumerate(frames):
        stack.append(_check_frame(frame, i, stack[0].shape if stack else None))
    if not stack:
        raise ValueError("no frames to write")
    with atomic_output(out) as tmp:
        iio.imwrite(tmp, np.stack(stack), extension=".gif", duration=1000.0 / fps, loop=loop)
    return out


def save_png(path: str | os.PathLike, image: Shaped[np.ndarray, "..."]) -> Path:
    """Write one RGB frame as a PNG, atomically.

    Args:
        path: output file, ending in ``.png``.
        image: ``(H, W, 3)`` uint8.

    Returns:
        The written path.

    Raises:
        ValueError: for a bad suffix or an image that is not uint8 RGB.
        FileNotFoundError, NotADirectoryError, PermissionError: if the directory cannot be written.
    """
    import imageio.v3 as iio

    out = check_output_path(path, (".png",))
    img = _check_frame(image, 0, None)
    with atomic_output(out) as tmp:
        iio.imwrite(tmp, img, extension=".png")
    return out


@dataclasses.dataclass(frozen=True)
class MediaInfo:
    """What ``probe_media`` reads from a media file's header.

    Attributes:
        width: video width in pixels (0 if no video stream).
        height: video height in pixels.
        fps: video frame rate (0.0 if unknown).
        duration_s: container duration in seconds.
        has_audio: whether there is an audio stream.
        audio_sample_rate: its sample rate in Hz (0 if none).
        audio_codec: its codec name ("" if none).
    """

    width: int
    height: int
    fps: float
    duration_s: float
    has_audio: bool
    audio_sample_rate: int
    audio_codec: str


def probe_media(path: str | os.PathLike) -> MediaInfo:
    """Read a media file's streams with the bundled ffmpeg (``ffmpeg -i``).

    Args:
        path: an existing video/audio file.

    Returns:
        ``MediaInfo``.

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: if ffmpeg cannot read it.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no such media file: {str(p)!r}")
    with _quiet_fork_warning():
        text = subprocess.run([_ffmpeg(), "-hide_banner", "-i", str(p)], capture_output=True, text=True).stderr
    duration = re.search(r"Duration: (\d+):(\d+):(\d+(?:\.\d+)?)", text)
    if duration is None:
        raise ValueError(f"ffmpeg cannot read {str(p)!r}: {text.strip()[-300:]}")
    h, m, s = duration.groups()
    video = re.search(r"Stream #\S+.*?: Video: .*?, (\d+)x(\d+)[ ,].*", text)
    fps = re.search(r"Stream #\S+.*?: Video: .*?([\d.]+) fps", text)
    audio = re.search(r"Stream #\S+.*?: Audio: (\w+).*?, (\d+) Hz", text)
    return MediaInfo(
        width=int(video.group(1)) if video else 0,
        height=int(video.group(2)) if video else 0,
        fps=float(fps.group(1)) if fps else 0.0,
        duration_s=int(h) * 3600 + int(m) * 60 + float(s),
        has_audio=audio is not None,
        audio_sample_rate=int(audio.group(2)) if audio else 0,
        audio_codec=audio.group(1) if audio else "",
    )
