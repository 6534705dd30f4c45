"""``jaxtalk render``: parameters or vertices -> GIF / mp4, side by side, audio, one-line errors."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest
from typer.testing import CliRunner

from jaxtalk.cli import app
from jaxtalk.data.formats import MotionClip, save_npz
from jaxtalk.types import JAW_SLICE

runner = CliRunner()


def _ok(args: list[str]) -> None:
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output


def _user_error(args: list[str], message: str) -> None:
    result = runner.invoke(app, args)
    assert result.exit_code == 2, result.output
    assert result.output.strip().splitlines()[-1].startswith("error:") and message in result.output, result.output
    assert "Traceback" not in result.output


@pytest.fixture(scope="module")
def low_face():
    from jaxtalk.face import builtin_face

    return builtin_face(0, resolution="low")


def _params(frames: int = 3) -> np.ndarray:
    params = np.zeros((frames, 56), np.float32)
    params[:, JAW_SLICE.start] = np.linspace(0.0, 0.35, frames)  # the jaw opens (every frame distinct)
    return params


def test_params_to_gif_shows_the_motion(tmp_path):
    save_npz(tmp_path / "open.npz", MotionClip(name="open", fps=25, params=_params()))
    _ok(["render", str(tmp_path / "open.npz"), "--out", str(tmp_path / "open.gif"), "--size", "48", "--no-captions"])
    frames = iio.imread(tmp_path / "open.gif", index=None)
    assert frames.shape[0] == 3
    closed, half, opened = (f[..., :3].astype(int) for f in frames)
    # The jaw parameter reaches the image, and more opening changes it more.
    assert 0 < np.abs(closed - half).sum() < np.abs(closed - opened).sum()


def test_vertices_side_by_side_doubles_the_width(tmp_path, low_face):
    verts = np.asarray(low_face.vertices_seq(_params(2)), np.float32)
    np.save(tmp_path / "a.npy", verts.reshape(2, -1))  # (T, 3V) is accepted too
    np.save(tmp_path / "b.npy", verts)
    _ok(["render", str(tmp_path / "a.npy"), "--out", str(tmp_path / "one.gif"), "--size", "40", "--no-captions"])
    _ok(["render", str(tmp_path / "a.npy"), "--compare", str(tmp_path / "b.npy"), "--out", str(tmp_path / "two.gif"),
         "--size", "40", "--no-captions"])
    one, two = iio.imread(tmp_path / "one.gif", index=None), iio.imread(tmp_path / "two.gif", index=None)
    assert two.shape[2] == 2 * one.shape[2] and two.shape[1] == one.shape[1]
    w = one.shape[2]
    np.testing.assert_array_equal(two[:, :, :w], two[:, :, w:])  # the same clip twice, same camera


def test_vertices_of_another_mesh_need_faces(tmp_path, low_face):
    verts = np.asarray(low_face.vertices_seq(_params(2)), np.float32)[:, :-1]  # drop one vertex: unknown mesh
    faces = np.asarray(low_face.faces)
    faces = faces[(faces < verts.shape[1]).all(axis=1)]
    np.save(tmp_path / "v.npy", verts)
    np.save(tmp_path / "f.npy", faces)
    _user_error(["render", str(tmp_path / "v.npy"), "--out", str(tmp_path / "v.gif")], "pass --faces")
    _ok(["render", str(tmp_path / "v.npy"), "--faces", str(tmp_path / "f.npy"), "--out", str(tmp_path / "v.gif"),
         "--size", "32"])
    assert iio.imread(tmp_path / "v.gif", index=None).shape[0] == 2


def test_mp4_carries_the_audio_stored_in_the_npz(tmp_path):
    from jaxtalk.render import probe_media

    frames = 10
    audio = (0.1 * np.sin(2 * np.pi * 220 * np.arange(frames * 640) / 16000)).astype(np.float32)
    save_npz(tmp_path / "talk.npz", MotionClip(name="talk", fps=25, params=_params(frames), audio=audio))
    _ok(["render", str(tmp_path / "talk.npz"), "--out", str(tmp_path / "talk.mp4"), "--size", "48"])
    info = probe_media(tmp_path / "talk.mp4")
    assert info.has_audio and info.width > 0 and abs(info.duration_s - frames / 25) < 0.1


def test_render_user_errors(tmp_path):
    save_npz(tmp_path / "p.npz", MotionClip(name="p", fps=25, params=_params()))
    _user_error(["render", str(tmp_path / "missing.npz")], "file not found")
    _user_error(["render", str(tmp_path / "p.npz"), "--out", str(tmp_path / "p.avi")], "must end in .mp4 or .gif")
    (tmp_path / "voice.wav").write_bytes(b"")
    _user_error(["render", str(tmp_path / "p.npz"), "--out", str(tmp_path / "p.gif"), "--audio",
                 str(tmp_path / "voice.wav")], "a GIF has no audio track")
    save_npz(tmp_path / "feat.npz", MotionClip(name="f", fps=25, features=np.zeros((3, 8), np.float32)))
    _user_error(["render", str(tmp_path / "feat.npz"), "--out", str(tmp_path / "f.gif")], "holds no 'params'")
    np.save(tmp_path / "flat.npy", np.zeros((4, 5), np.float32))
    _user_error(["render", str(tmp_path / "flat.npy"), "--out", str(tmp_path / "f.gif")], "vertices must have shape")
    (tmp_path / "clip.txt").write_text("x")
    _user_error(["render", str(tmp_path / "clip.txt"), "--out", str(tmp_path / "f.gif")], "expected .npz parameters")
