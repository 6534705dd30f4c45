"""mp4 (with audio) / GIF / PNG writers: read back with imageio and ffmpeg, the audio-length rule,
atomic writes and errors."""

from __future__ import annotations

import warnings

import imageio
import imageio.v3 as iio
import numpy as np
import pytest

from jaxtalk.render import fit_audio, probe_media, render_clip, save_png, write_gif, write_mp4

SR = 16_000
# imageio's ffmpeg reader (used here to read files back) forks+execs ffmpeg; JAX warns on any fork.
pytestmark = pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")


def _frames(num: int = 12, height: int = 48, width: int = 64) -> np.ndarray:
    """A moving bright square on a gradient: every frame differs from the previous one."""
    frames = np.zeros((num, height, width, 3), np.uint8)
    frames[..., 2] = np.linspace(0, 200, width, dtype=np.uint8)
    for t in range(num):
        frames[t, 10:26, 2 + 4 * t : 18 + 4 * t] = 255
    return frames


def _tone(seconds: float) -> np.ndarray:
    t = np.arange(int(round(seconds * SR))) / SR
    return (0.2 * np.sin(2 * np.pi * 440 * t)).astype(np.float32)


def _count_frames(path) -> int:
    with imageio.get_reader(path, "ffmpeg") as reader:
        return reader.count_frames()


def test_mp4_with_audio_reads_back(tmp_path):
    frames = _frames()
    out = write_mp4(tmp_path / "clip.mp4", frames, audio=_tone(12 / 25))
    assert out.exists() and out.stat().st_size > 0
    info = probe_media(out)
    assert (info.width, info.height, info.fps) == (64, 48, 25.0)
    assert info.has_audio and info.audio_sample_rate == SR and info.audio_codec == "aac"
    assert abs(info.duration_s - 12 / 25) < 0.1
    assert _count_frames(out) == 12
    # The picture survives H.264 at the default quality (the square is where it was drawn).
    with imageio.get_reader(out, "ffmpeg") as reader:
        frame5 = reader.get_data(5)
    assert frame5.shape == (48, 64, 3)
    assert np.abs(frame5.astype(float) - frames[5]).mean() < 6.0
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary file left behind


def test_mp4_without_audio_has_no_audio_stream_and_takes_a_generator(tmp_path):
    out = write_mp4(tmp_path / "silent.mp4", iter(list(_frames(7))), fps=10)
    info = probe_media(out)
    assert not info.has_audio and info.fps == 10.0
    assert _count_frames(out) == 7


def test_odd_sizes_are_padded_to_even(tmp_path):
    out = write_mp4(tmp_path / "odd.mp4", _frames(3, height=33, width=41))
    assert (probe_media(out).width, probe_media(out).height) == (42, 34)


def test_gif_reads_back(tmp_path):
    out = write_gif(tmp_path / "clip.gif", _frames(9))
    frames = iio.imread(out)
    assert frames.shape[:3] == (9, 48, 64)
    assert iio.immeta(out, index=0)["duration"] == 40  # ms per frame at 25 fps


def test_png_reads_back_exactly(tmp_path):
    frame = _frames(1)[0]
    out = save_png(tmp_path / "frame.png", frame)
    np.testing.assert_array_equal(iio.imread(out)[..., :3], frame)


def test_fit_audio_rule():
    # 10 frames at 25 fps = 0.4 s = 6400 samples.
    audio = np.arange(6500, dtype=np.float32) / 1e4
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # within one frame (640 samples): silent
        np.testing.assert_array_equal(fit_audio(audio, 10), audio[:6400])
        padded = fit_audio(audio[:6000], 10)
    assert padded.shape == (6400,)
    np.testing.assert_array_equal(padded[:6000], audio[:6000])
    assert np.all(padded[6000:] == 0)
    with pytest.warns(UserWarning, match="trimmed"):
        assert fit_audio(np.zeros(8000, np.float32), 10).shape == (6400,)
    with pytest.warns(UserWarning, match="padded"):
        assert fit_audio(np.zeros((4000, 2), np.float32), 10).shape == (6400, 2)
    with pytest.raises(ValueError, match="wrong sample_rate"):
        fit_audio(np.zeros(48_000, np.float32), 10)


def test_mp4_audio_off_by_some_frames_warns_once_and_is_trimmed(tmp_path):
    with pytest.warns(UserWarning) as record:
        out = write_mp4(tmp_path / "long.mp4", _frames(10), audio=_tone(0.7))  # video: 0.4 s
    assert len([w for w in record if "trimmed" in str(w.message)]) == 1
    info = probe_media(out)
    assert info.has_audio and abs(info.duration_s - 0.4) < 0.06  # not the 0.7 s of the input audio


def test_errors(tmp_path):
    frames = _frames(4)
    with pytest.raises(ValueError, match="no frames"):
        write_mp4(tmp_path / "a.mp4", frames[:0])
    with pytest.raises(ValueError, match="no frames"):
        write_gif(tmp_path / "a.gif", [])
    with pytest.raises(ValueError, match="uint8"):
        write_mp4(tmp_path / "a.mp4", frames.astype(np.float32))
    with pytest.raises(ValueError, match="unlike the first"):
        write_gif(tmp_path / "a.gif", [frames[0], frames[1, :10]])
    with pytest.raises(ValueError, match="NaN"):
        write_mp4(tmp_path / "a.mp4", frames, audio=np.full(640 * 4, np.nan, np.float32))
    with pytest.raises(ValueError, match="lasts"):
        write_mp4(tmp_path / "a.mp4", frames, audio=_tone(3.0))
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file, not a folder"):
        write_gif(tmp_path / "file" / "a.gif", frames)
    with pytest.raises(ValueError, match=r"\.mp4"):
        write_mp4(tmp_path / "a.avi", frames)
    with pytest.raises(FileNotFoundError):
        probe_media(tmp_path / "nothing.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    # Folders of a named output are created, as every jaxtalk command does.
    write_gif(tmp_path / "new" / "a.gif", frames)
    assert (tmp_path / "new" / "a.gif").is_file()


def test_failure_midway_leaves_no_file(tmp_path):
    target = tmp_path / "clip.mp4"
    target.write_bytes(b"old")

    def frames():
        yield from _frames(3)
        raise RuntimeError("renderer crashed")

    with pytest.raises(RuntimeError, match="crashed"):
        write_mp4(target, frames())
    assert target.read_bytes() == b"old"  # the previous file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]


def test_render_clip_end_to_end(tmp_path):
    # A tiny mesh (a square of two triangles) nodding through 5 frames, with audio.
    base = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]]) * 0.1
    verts = np.stack([base + [0.0, 0.01 * t, 0.002 * t] for t in range(5)])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    out = render_clip(tmp_path / "c.mp4", [verts, verts], faces, audio=_tone(0.2), captions=["a", "b"], size=32)
    info = probe_media(out)
    assert info.has_audio and info.width == 64 and info.height > 32
    assert _count_frames(out) == 5
    gif = render_clip(tmp_path / "c.gif", verts, faces, size=32)
    assert iio.imread(gif).shape[1:3] == (32, 32)
    with pytest.raises(ValueError, match="GIF cannot carry audio"):
        render_clip(tmp_path / "d.gif", verts, faces, audio=_tone(0.2))
