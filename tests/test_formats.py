"""Dataset readers: DualTalk (real demo clips and synthetic), VOCASET layout, generic npz."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import soundfile as sf

from jaxtalk.data.formats import (
    MotionClip,
    read_clip,
    read_dualtalk,
    read_npz,
    read_vocaset,
    read_vocaset_templates,
    save_npz,
)
from helpers import DUALTALK_SOURCES, bad_numpy_files, dualtalk_folder


def _wav(path, seconds=0.4, rate=16000):
    t = np.arange(int(rate * seconds)) / rate
    sf.write(path, 0.3 * np.sin(2 * np.pi * 220 * t), rate)
    return path


def _dualtalk_npz(path, frames=10, **overrides):
    rng = np.random.default_rng(0)
    data = {
        "exp": rng.standard_normal((frames, 50)).astype(np.float32),
        "pose": rng.standard_normal((frames, 6)).astype(np.float32),
        "shape": np.zeros((frames, 100), np.float32),
    }
    data.update(overrides)
    np.savez(path, **{k: v for k, v in data.items() if v is not None})
    return data


# --- DualTalk ---------------------------------------------------------------------------------


@pytest.mark.parametrize("source", DUALTALK_SOURCES)
def test_dualtalk_demo_layout_clip(source, tmp_path, request):
    """A tracked side of DualTalk's demo (``real``, where ``../shared`` has it) or of the same layout
    exported from SynthTalk."""
    corpus = request.getfixturevalue("synthtalk_tiny") if source == "synthtalk" else None
    conv, k = dualtalk_folder(tmp_path, source, corpus)["train"]
    npz = tmp_path / "train" / f"{conv}_speaker{k}.npz"
    clip = read_dualtalk(npz)
    raw = np.load(npz)
    assert clip.params.shape == (raw["exp"].shape[0], 56) and clip.fps == 25.0
    np.testing.assert_array_equal(clip.params[:, :50], raw["exp"])
    np.testing.assert_array_equal(clip.params[:, 50:53], raw["pose"][:, 3:])  # jaw
    np.testing.assert_array_equal(clip.params[:, 53:], raw["pose"][:, :3])  # neck
    # Audio and motion cover the same time; the partner is the other speaker's track.
    assert clip.audio.dtype == np.float32 and abs(clip.audio.size / 16000 - clip.duration) < 0.1
    assert clip.partner_audio_path == tmp_path / "train" / f"{conv}_speaker{3 - k}.wav"
    if source == "real":
        assert clip.params.shape[0] == 587
        # Real tracks have the ranges SynthTalk is calibrated against (jaw opening below ~0.5 rad).
        assert 0.05 < np.abs(clip.params[:, 50]).max() < 0.6


@pytest.mark.parametrize("source", DUALTALK_SOURCES)
def test_dualtalk_demo_layout_through_read_clip(source, tmp_path, request):
    corpus = request.getfixturevalue("synthtalk_tiny") if source == "synthtalk" else None
    conv, k = dualtalk_folder(tmp_path, source, corpus)["test"]
    npz = tmp_path / "test" / f"{conv}_speaker{k}.npz"
    clip = read_clip(npz, load_audio=False)
    assert clip.params.shape == (np.load(npz)["exp"].shape[0], 56) and clip.audio is None
    np.testing.assert_array_equal(clip.params, read_dualtalk(npz, load_audio=False).params)
    assert clip.audio_path.name == f"{conv}_speaker{k}.wav"
    if source == "real":
        assert clip.params.shape[0] == 750


def test_dualtalk_layout_on_synthetic_file(tmp_path):
    pose = np.concatenate([np.full((10, 3), 7.0), np.full((10, 3), 9.0)], axis=1).astype(np.float32)
    data = _dualtalk_npz(tmp_path / "a_speaker1.npz", pose=pose)
    _wav(tmp_path / "a_speaker1.wav")
    clip = read_dualtalk(tmp_path / "a_speaker1.npz")
    np.testing.assert_array_equal(clip.params[:, :50], data["exp"])
    assert np.all(clip.params[:, 50:53] == 9.0) and np.all(clip.params[:, 53:] == 7.0)
    assert clip.audio.shape == (6400,) and clip.partner_audio_path is None
    assert clip.name == "a_speaker1" and clip.num_frames == 10


def test_dualtalk_missing_audio(tmp_path):
    _dualtalk_npz(tmp_path / "b.npz")
    with pytest.raises(FileNotFoundError, match="b.wav"):
        read_dualtalk(tmp_path / "b.npz")
    clip = read_dualtalk(tmp_path / "b.npz", require_audio=False)
    assert clip.audio is None and clip.audio_path is None


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"pose": None}, r"missing keys \['pose'\]"),
        ({"exp": np.zeros((10, 40), np.float32)}, r"exp \(T, 50\)"),
        ({"pose": np.zeros((9, 6), np.float32)}, "10 frames but pose has 9"),
        ({"exp": np.full((10, 50), np.nan, np.float32)}, "NaN"),
        ({"exp": np.zeros((10,), np.float32)}, "2-D"),
    ],
)
def test_dualtalk_bad_files(tmp_path, overrides, message):
    _dualtalk_npz(tmp_path / "c.npz", **overrides)
    with pytest.raises(ValueError, match=message):
        read_dualtalk(tmp_path / "c.npz", require_audio=False)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.npz"):
        read_dualtalk(tmp_path / "nothing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz' is not an .npz file"):
        read_dualtalk(tmp_path / "junk.npz")


def test_every_bad_numpy_file_is_one_message_naming_it_with_no_advice_to_unpickle(tmp_path):
    from jaxtalk.files import load_npy, load_npz

    for name, words in bad_numpy_files(tmp_path).items():
        load = load_npz if name.endswith(".npz") else load_npy
        with pytest.raises(ValueError) as info:
            load(tmp_path / name)
        message = str(info.value)
        assert str(tmp_path / name) in message and all(w in message for w in words), message
        assert "\n" not in message and "pickle" not in message.lower(), message
    with pytest.raises(FileNotFoundError, match="token file not found: .*absent.npy"):
        load_npy(tmp_path / "absent.npy", what="token file")
    np.savez(tmp_path / "good.npz", params=np.ones((3, 56), np.float32), fps=25)
    assert sorted(load_npz(tmp_path / "good.npz")) == ["fps", "params"]
    np.save(tmp_path / "good.npy", np.ones((3, 4)))
    assert load_npy(tmp_path / "good.npy", mmap=True).sum() == 12


def test_the_readers_and_loaders_report_bad_numpy_files_by_name(tmp_path):
    from jaxtalk.audio.tokenizer import TokenStream, VQTokenizer
    from jaxtalk.models.freetalk.animate import read_landmarks

    bad_numpy_files(tmp_path)
    for read in (read_npz, read_dualtalk, read_clip, VQTokenizer.load):
        with pytest.raises(ValueError, match="objects.npz' holds object arrays"):
            read(tmp_path / "objects.npz")
    for read in (read_vocaset, read_clip, lambda p: TokenStream.from_npy(p, rate=25.0),
                 lambda p: read_landmarks(p, np.zeros((10, 3)))):
        with pytest.raises(ValueError, match="garbage.npy' is not a NumPy .npy file"):
            read(tmp_path / "garbage.npy")


# --- VOCASET ----------------------------------------------------------------------------------


def _vocaset_root(tmp_path, frames=60, verts=5, flat=True):
    """A VOCASET-style tree whose vertices move linearly in time (exact under linear resampling)."""
    root = tmp_path / "vocaset"
    (root / "vertices_npy").mkdir(parents=True)
    (root / "wav").mkdir()
    rng = np.random.default_rng(1)
    template = rng.standard_normal((verts, 3)).astype(np.float32)
    velocity = rng.standard_normal((verts, 3)).astype(np.float32)
    t = np.arange(frames, dtype=np.float32)[:, None, None] / 60.0
    seq = template[None] + t * velocity[None]
    subject = "FaceTalk_170725_00137_TA"
    stem = f"{subject}_sentence01"
    np.save(root / "vertices_npy" / f"{stem}.npy", seq.reshape(frames, -1) if flat else seq)
    with open(root / "templates.pkl", "wb") as handle:
        pickle.dump({subject: template, "FaceTalk_other": template[:3]}, handle)
    _wav(root / "wav" / f"{stem}.wav", seconds=frames / 60.0)
    return root / "vertices_npy" / f"{stem}.npy", template, velocity


@pytest.mark.parametrize("flat", [True, False])
def test_vocaset_resampled_to_25_fps(tmp_path, flat):
    path, template, velocity = _vocaset_root(tmp_path, flat=flat)
    clip = read_vocaset(path)
    assert clip.fps == 25.0 and clip.vertices.shape == (25, 5, 3)
    assert clip.subject == "FaceTalk_170725_00137_TA"
    np.testing.assert_array_equal(clip.template, template)
    t = np.arange(25)[:, None, None] / 25.0
    np.testing.assert_allclose(clip.vertices, template[None] + t * velocity[None], atol=1e-5)
    assert clip.audio.shape == (16000,)


def test_vocaset_native_rate_and_npz_templates(tmp_path):
    path, template, _ = _vocaset_root(tmp_path)
    np.savez(tmp_path / "t.npz", FaceTalk_170725_00137_TA=template)
    clip = read_vocaset(path, templates=tmp_path / "t.npz", target_fps=None, load_audio=False)
    assert clip.fps == 60.0 and clip.vertices.shape == (60, 5, 3) and clip.audio is None
    assert set(read_vocaset_templates(tmp_path / "t.npz")) == {"FaceTalk_170725_00137_TA"}


def test_vocaset_errors(tmp_path):
    path, template, _ = _vocaset_root(tmp_path)
    with pytest.raises(ValueError, match="not in templates"):
        read_vocaset(path, templates={"someone_else": template})
    with pytest.raises(ValueError, match="has 5 vertices"):
        read_vocaset(path, templates={"FaceTalk_170725_00137_TA": template[:4]})
    bad = path.with_name("FaceTalk_x_bad.npy")
    np.save(bad, np.zeros((10, 7), np.float32))
    with pytest.raises(ValueError, match=r"\(T, V\*3\)"):
        read_vocaset(bad)
    with pytest.raises(FileNotFoundError):
        read_vocaset(path.with_name("absent.npy"))
    with pytest.raises(FileNotFoundError, match="absent.wav"):
        read_vocaset(path, wav_path=tmp_path / "absent.wav", require_audio=True)


# --- generic npz --------------------------------------------------------------------------------


def test_generic_npz_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    clip = MotionClip(
        name="gen",
        fps=30.0,
        params=rng.standard_normal((12, 56)).astype(np.float32),
        vertices=rng.standard_normal((12, 4, 3)).astype(np.float32),
        template=rng.standard_normal((4, 3)).astype(np.float32),
        features=rng.standard_normal((12, 9)).astype(np.float32),
        audio=(0.1 * rng.standard_normal(6400)).astype(np.float32),
        sample_rate=16000,
    )
    back = read_npz(save_npz(tmp_path / "clip.npz", clip))
    for field in ("params", "vertices", "template", "features", "audio"):
        np.testing.assert_array_equal(getattr(back, field), getattr(clip, field))
    assert (back.name, back.fps, back.sample_rate) == ("gen", 30.0, 16000)
    assert read_clip(tmp_path / "clip.npz").name == "gen"


def test_generic_npz_audio_path_and_resampling(tmp_path):
    _wav(tmp_path / "voice.wav")
    params = np.tile(np.arange(50, dtype=np.float32)[:, None], (1, 56))
    np.savez(
        tmp_path / "m.npz", fps=np.float64(50.0), params=params, audio_path=np.str_("voice.wav")
    )
    clip = read_npz(tmp_path / "m.npz")
    assert clip.audio_path == tmp_path / "voice.wav" and clip.audio.shape == (6400,)
    at25 = clip.resampled(25)
    assert at25.fps == 25.0 and at25.params.shape == (25, 56)
    np.testing.assert_array_equal(at25.params[:, 0], np.arange(0, 50, 2))


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"params": np.zeros((5, 56))}, r"missing keys \['fps'\]"),
        ({"fps": 25.0, "param": np.zeros((5, 56))}, "at least one of"),
        ({"fps": 25.0, "params": np.zeros((5, 50))}, r"\(frames, 56\)"),
        ({"fps": 25.0, "params": np.zeros((5, 56)), "features": np.zeros((6, 3))}, "disagree"),
        ({"fps": 25.0, "params": np.zeros((5, 56)), "audio": np.zeros(100)}, "sample_rate"),
        ({"fps": np.zeros(2), "params": np.zeros((5, 56))}, "scalar"),
        ({"fps": -1.0, "params": np.zeros((5, 56))}, "fps must be positive"),
        ({"fps": 25.0, "vertices": np.zeros((5, 4, 3)), "template": np.zeros((3, 3))}, "template"),
    ],
)
def test_generic_npz_bad_files(tmp_path, arrays, message):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=message):
        read_npz(tmp_path / "bad.npz")


def test_read_clip_rejects_unknown(tmp_path):
    np.savez(tmp_path / "other.npz", something=np.zeros(3))
    with pytest.raises(ValueError, match="unrecognised"):
        read_clip(tmp_path / "other.npz")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(ValueError, match="unsupported file type"):
        read_clip(tmp_path / "x.txt")
