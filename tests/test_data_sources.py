"""Dataset sources: layout detection, clip listing (names, speakers, splits, partners) and reading for
DualTalk, VOCASET, the generic layout and SynthTalk; the per-clip checks of ``check_clip``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from jaxtalk.audio.io import resample_audio
from jaxtalk.data.prepare import PrepareSettings, prepare
from jaxtalk.data.sources import BadClip, RawClip, check_clip, open_source
from jaxtalk.data.sources.clip import MAX_SKEW_SECONDS

FAST = PrepareSettings(tokens="none", landmarks=False)


# ------------------------------------------------------------------------------------------ writers
def _wav(path: Path, seconds: float, rate: int = 16000, seed: int = 0) -> np.ndarray:
    audio = (0.1 * np.random.default_rng(seed).standard_normal(int(round(seconds * rate)))).astype(np.float32)
    sf.write(str(path), audio, rate, subtype="FLOAT")
    return audio


def _dualtalk_side(folder: Path, stem: str, frames: int | None, seconds: float, seed: int) -> dict:
    """A side with motion (``frames``) or audio-only (None); wav at 22050 Hz to exercise resampling."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    out = {"audio": _wav(folder / f"{stem}.wav", seconds, rate=22050, seed=seed)}
    if frames is not None:
        out["exp"] = rng.standard_normal((frames, 50)).astype(np.float32)
        out["pose"] = rng.standard_normal((frames, 6)).astype(np.float32)
        np.savez(folder / f"{stem}.npz", exp=out["exp"], pose=out["pose"], shape=np.zeros((frames, 100), np.float32))
    return out


@pytest.fixture(scope="module")
def dualtalk_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("dualtalk")
    sides = {
        "vidA_sub_video_1_speaker1": _dualtalk_side(root / "train", "vidA_sub_video_1_speaker1", 50, 2.0, 1),
        "vidA_sub_video_1_speaker2": _dualtalk_side(root / "train", "vidA_sub_video_1_speaker2", 50, 2.0, 2),
        "vidA_sub_video_2_speaker1": _dualtalk_side(root / "train", "vidA_sub_video_2_speaker1", 60, 2.4, 3),
        "vidA_sub_video_2_speaker2": _dualtalk_side(root / "train", "vidA_sub_video_2_speaker2", None, 2.4, 4),
        "conv9_speaker1": _dualtalk_side(root / "test", "conv9_speaker1", None, 2.0, 5),
        "conv9_speaker2": _dualtalk_side(root / "test", "conv9_speaker2", 50, 2.0, 6),
    }
    (root / "train" / "notes.txt").write_text("not a clip")
    return root, sides


# ------------------------------------------------------------------------------------------ DualTalk
def test_dualtalk_layout_is_detected_and_lists_every_side_with_split_partner_and_video_group(dualtalk_dir):
    root, _ = dualtalk_dir
    src = open_source(root)
    assert src.layout == "dualtalk"
    assert src.spec == str(root.absolute())
    got = {e.name: e for e in src.entries}
    assert [e.name for e in src.entries] == [  # split folder order, then name
        "vidA_sub_video_1_speaker1", "vidA_sub_video_1_speaker2", "vidA_sub_video_2_speaker1",
        "vidA_sub_video_2_speaker2", "conv9_speaker1", "conv9_speaker2"]
    assert {n: e.split for n, e in got.items()} == {
        "vidA_sub_video_1_speaker1": "train", "vidA_sub_video_1_speaker2": "train",
        "vidA_sub_video_2_speaker1": "train", "vidA_sub_video_2_speaker2": "train",
        "conv9_speaker1": "test", "conv9_speaker2": "test"}
    assert got["vidA_sub_video_1_speaker1"].partner == "vidA_sub_video_1_speaker2"
    assert got["vidA_sub_video_1_speaker2"].partner == "vidA_sub_video_1_speaker1"
    assert got["conv9_speaker2"].partner == "conv9_speaker1"
    assert all(e.requires_partner for e in src.entries)
    assert {e.speaker for e in src.entries} == set(got)  # each side is its own speaker
    # Sub-clips of one video share its people: one split group per video.
    assert got["vidA_sub_video_1_speaker1"].split_group == got["vidA_sub_video_2_speaker2"].split_group == "vidA"
    assert got["conv9_speaker1"].split_group == "conv9"
    # An audio-only side is identified by its wav alone.
    assert [p.name for p in got["vidA_sub_video_2_speaker2"].files] == ["vidA_sub_video_2_speaker2.wav"]
    assert [p.name for p in got["vidA_sub_video_1_speaker1"].files] == [
        "vidA_sub_video_1_speaker1.npz", "vidA_sub_video_1_speaker1.wav"]


def test_dualtalk_read_gives_params56_exp_jaw_neck_and_16khz_audio(dualtalk_dir):
    root, sides = dualtalk_dir
    got = {e.name: e for e in open_source(root).entries}
    side = sides["vidA_sub_video_2_speaker1"]
    raw = got["vidA_sub_video_2_speaker1"].read()
    assert raw.fps == 25.0 and raw.num_frames == 60
    expected = np.concatenate([side["exp"], side["pose"][:, 3:], side["pose"][:, :3]], axis=1)
    np.testing.assert_array_equal(raw.params, expected)
    assert raw.params.dtype == np.float32 and raw.params.shape == (60, 56)
    # 22050 Hz resampled to 16 kHz (2.4 s -> 38400 samples), exactly as resample_audio does it.
    assert raw.audio.shape == (38400,)
    np.testing.assert_array_equal(raw.audio, resample_audio(side["audio"], 22050, 16000))
    check_clip(raw, min_frames=25)


def test_dualtalk_audio_only_side_reads_without_motion_and_passes_as_partner(dualtalk_dir):
    root, _ = dualtalk_dir
    got = {e.name: e for e in open_source(root).entries}
    raw = got["vidA_sub_video_2_speaker2"].read()
    assert raw.params is None and raw.vertices is None and raw.num_frames == 0
    assert raw.audio.shape == (38400,)
    check_clip(raw, min_frames=25, motion_required=False)
    with pytest.raises(BadClip, match="no motion"):
        check_clip(raw, min_frames=25)


def test_dualtalk_prepare_keeps_audio_only_sides_with_has_motion_false(dualtalk_dir, tmp_path):
    root, sides = dualtalk_dir
    result = prepare(root, tmp_path / "p", FAST, progress=False, echo=lambda s: None)
    assert result.skipped == [] and result.clips == 6
    manifest = json.loads((tmp_path / "p" / "manifest.json").read_text())
    motion = {c["name"]: c["has_motion"] for c in manifest["clips"]}
    assert motion == {n: s.get("exp") is not None for n, s in sides.items()}
    frames = {c["name"]: c["frames"] for c in manifest["clips"]}
    assert frames["vidA_sub_video_2_speaker1"] == 60 and frames["vidA_sub_video_2_speaker2"] == 60  # 2.4 s of audio
    # The layout's splits are kept: only train and test.
    assert set(manifest["splits"]["test"]) == {"conv9_speaker1", "conv9_speaker2"}
    assert not manifest["splits"]["ood"]
    assert set(manifest["splits"]["train"]) | set(manifest["splits"]["val"]) == {n for n in sides if n.startswith("vidA")}


def test_dualtalk_same_name_in_two_splits_is_an_error(tmp_path):
    _dualtalk_side(tmp_path / "train", "c_speaker1", 50, 2.0, 0)
    _dualtalk_side(tmp_path / "test", "c_speaker1", 50, 2.0, 0)
    with pytest.raises(ValueError, match="two clips are named 'c_speaker1'"):
        open_source(tmp_path)


# ------------------------------------------------------------------------------------------ VOCASET
@pytest.fixture
def vocaset_dir(tmp_path):
    rng = np.random.default_rng(0)
    (tmp_path / "vertices_npy").mkdir()
    (tmp_path / "wav").mkdir()
    templates = {"FaceTalk_A_TA": rng.standard_normal((7, 3)).astype(np.float32),
                 "FaceTalk_B_TA": rng.standard_normal((7, 3)).astype(np.float32)}
    np.savez(tmp_path / "templates.npz", **templates)
    verts = {}
    for stem, frames in (("FaceTalk_A_TA_sentence01", 120), ("FaceTalk_A_TA_sentence02", 150),
                         ("FaceTalk_B_TA_sentence01", 90)):
        v = rng.standard_normal((frames, 21)).astype(np.float32)  # (T, V*3) at 60 fps
        np.save(tmp_path / "vertices_npy" / f"{stem}.npy", v)
        _wav(tmp_path / "wav" / f"{stem}.wav", frames / 60)
        verts[stem] = v
    return tmp_path, templates, verts


def test_vocaset_layout_lists_subjects_and_reads_60fps_vertices_with_template(vocaset_dir):
    root, templates, verts = vocaset_dir
    src = open_source(root)
    assert src.layout == "vocaset"
    assert [e.name for e in src.entries] == ["FaceTalk_A_TA_sentence01", "FaceTalk_A_TA_sentence02", "FaceTalk_B_TA_sentence01"]
    assert [e.speaker for e in src.entries] == ["FaceTalk_A_TA", "FaceTalk_A_TA", "FaceTalk_B_TA"]
    assert all(e.split is None and e.partner is None and not e.requires_partner for e in src.entries)
    assert [p.name for p in src.entries[0].files] == ["FaceTalk_A_TA_sentence01.npy", "FaceTalk_A_TA_sentence01.wav",
                                                      "templates.npz"]
    raw = src.entries[2].read()
    assert raw.fps == 60.0 and raw.params is None
    np.testing.assert_array_equal(raw.vertices, verts["FaceTalk_B_TA_sentence01"].reshape(90, 7, 3))
    np.testing.assert_array_equal(raw.template, templates["FaceTalk_B_TA"])
    assert raw.audio.shape == (24000,)
    check_clip(raw, min_frames=25)


def test_vocaset_prepare_resamples_vertices_to_25fps_and_draws_speaker_disjoint_splits(vocaset_dir, tmp_path):
    root, templates, verts = vocaset_dir
    prepare(root, tmp_path / "p", FAST, progress=False, echo=lambda s: None)
    from jaxtalk.data.loader import PreparedData

    data = PreparedData(tmp_path / "p")
    frames = {c["name"]: c["frames"] for c in data.clips}
    # round(T * 25 / 60), halves up: 120 -> 50, 150 -> 62.5 -> 63, 90 -> 37.5 -> 38.
    assert frames == {"FaceTalk_A_TA_sentence01": 50, "FaceTalk_A_TA_sentence02": 63, "FaceTalk_B_TA_sentence01": 38}
    rec = data.record(data.index("FaceTalk_A_TA_sentence01"))
    assert rec["vertices"].shape == (50, 7, 3) and "motion" not in rec
    # Output frame j sits at input frame 2.4 j: frame 5 is input frame 12 exactly.
    src = verts["FaceTalk_A_TA_sentence01"].reshape(120, 7, 3)
    np.testing.assert_allclose(rec["vertices"][[0, 5, 10]], src[[0, 12, 24]], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(rec["template"], templates["FaceTalk_A_TA"])
    assert all(c["has_vertices"] and not c["has_motion"] for c in data.clips)
    split_of = {c["speaker"]: set() for c in data.clips}
    for c in data.clips:
        split_of[c["speaker"]].add(c["split"])
    assert all(len(s) == 1 for s in split_of.values())  # a speaker never straddles splits


# ------------------------------------------------------------------------------------------ generic
@pytest.fixture
def generic_dir(tmp_path):
    rng = np.random.default_rng(0)
    arrays = {
        "a": {"params56": rng.standard_normal((50, 56)).astype(np.float32), "fps": np.float64(25)},
        "b": {"exp": rng.standard_normal((30, 50)).astype(np.float32),
              "pose": rng.standard_normal((30, 6)).astype(np.float32), "fps": np.int64(15)},
        "c": {"vertices": rng.standard_normal((100, 4, 3)).astype(np.float32),
              "template": rng.standard_normal((4, 3)).astype(np.float32), "fps": np.float32(50)},
    }
    for name, arrs in arrays.items():
        np.savez(tmp_path / f"{name}.npz", **arrs)
        _wav(tmp_path / f"{name}.wav", 2.0, rate=48000)
    tokens = rng.standard_normal((25, 8)).astype(np.float32)
    np.save(tmp_path / "a.tokens.npy", tokens)
    (tmp_path / "tokens.json").write_text(json.dumps({"rate": 12.5}))
    (tmp_path / "metadata.csv").write_text(
        "clip,speaker,emotion,intensity,split,partner\n"
        "a,alice,happy,2,train,b\n"
        "b,bob,,,test,a\n"
        "c,carol,sad,0.5,,\n"
    )
    return tmp_path, arrays, tokens


def test_generic_layout_lists_metadata_speakers_splits_partners_and_emotions(generic_dir):
    root, _, _ = generic_dir
    src = open_source(root)
    assert src.layout == "generic"
    e = {x.name: x for x in src.entries}
    assert list(e) == ["a", "b", "c"]
    assert [e[n].speaker for n in "abc"] == ["alice", "bob", "carol"]
    assert [e[n].split for n in "abc"] == ["train", "test", None]
    assert [e[n].partner for n in "abc"] == ["b", "a", None]
    assert [e[n].requires_partner for n in "abc"] == [True, True, False]
    assert [e[n].emotion for n in "abc"] == ["happy", None, "sad"]
    assert [e[n].intensity for n in "abc"] == [2.0, None, 0.5]
    assert [p.name for p in e["a"].files] == ["a.npz", "a.wav", "a.tokens.npy"]
    assert [p.name for p in e["b"].files] == ["b.npz", "b.wav"]


def test_generic_read_params56_exp_pose_and_vertices_with_tokens(generic_dir):
    root, arrays, tokens = generic_dir
    e = {x.name: x for x in open_source(root).entries}
    a, b, c = e["a"].read(), e["b"].read(), e["c"].read()
    np.testing.assert_array_equal(a.params, arrays["a"]["params56"])
    assert a.fps == 25.0 and isinstance(a.fps, float)
    np.testing.assert_array_equal(a.tokens, tokens)
    assert a.token_rate == 12.5
    assert b.tokens is None and b.token_rate is None
    expected = np.concatenate([arrays["b"]["exp"], arrays["b"]["pose"][:, 3:], arrays["b"]["pose"][:, :3]], axis=1)
    np.testing.assert_array_equal(b.params, expected)
    assert b.fps == 15.0
    assert c.params is None and c.fps == 50.0
    np.testing.assert_array_equal(c.vertices, arrays["c"]["vertices"])
    np.testing.assert_array_equal(c.template, arrays["c"]["template"])
    for raw in (a, b, c):
        assert raw.audio.dtype == np.float32 and raw.audio.shape == (32000,)  # 48 kHz -> 16 kHz
        check_clip(raw, min_frames=25)


def test_generic_listing_ignores_tokenizer_npz_and_hidden_temporary_files(generic_dir):
    root, _, _ = generic_dir
    np.savez(root / "tokenizer.npz", codebook=np.zeros((4, 2), np.float32))
    np.savez(root / ".d.tmp.npz", fps=np.float64(25))  # an interrupted export
    assert [e.name for e in open_source(root).entries] == ["a", "b", "c"]
    only = root / "only_tokenizer"
    only.mkdir()
    np.savez(only / "tokenizer.npz", codebook=np.zeros((4, 2), np.float32))
    with pytest.raises(ValueError, match="no clips in a known layout"):
        open_source(only)


def test_generic_without_metadata_makes_every_clip_its_own_speaker(generic_dir):
    root, _, _ = generic_dir
    (root / "metadata.csv").unlink()
    src = open_source(root)
    assert [(x.name, x.speaker, x.split, x.partner, x.requires_partner) for x in src.entries] == [
        ("a", "a", None, None, False), ("b", "b", None, None, False), ("c", "c", None, None, False)]


def test_generic_metadata_with_unknown_column_or_duplicate_clip_is_rejected(generic_dir):
    root, _, _ = generic_dir
    (root / "metadata.csv").write_text("clip,speaker,mood\na,x,happy\n")
    with pytest.raises(ValueError, match="unknown columns"):
        open_source(root)
    (root / "metadata.csv").write_text("clip,speaker\na,x\na,y\n")
    with pytest.raises(ValueError, match="listed twice"):
        open_source(root)


# ------------------------------------------------------------------------------------------ detection
def test_detection_prefers_dualtalk_then_vocaset_then_generic_and_layout_can_be_forced(tmp_path, dualtalk_dir):
    root, _ = dualtalk_dir
    assert open_source(root).layout == "dualtalk"
    # VOCASET structure next to a stray npz is still VOCASET.
    v = tmp_path / "v"
    (v / "vertices_npy").mkdir(parents=True)
    (v / "wav").mkdir()
    np.save(v / "vertices_npy" / "S_sentence01.npy", np.zeros((60, 9), np.float32))
    np.savez(v / "stray.npz", fps=np.float64(25))
    assert open_source(v).layout == "vocaset"
    assert open_source(v, layout="generic").layout == "generic"
    assert [e.name for e in open_source(v, layout="generic").entries] == ["stray"]


def test_open_source_errors_for_missing_empty_or_unknown(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_source(tmp_path / "nope")
    with pytest.raises(ValueError, match="no clips in a known layout"):
        open_source(tmp_path)
    (tmp_path / "x.npz").write_bytes(b"")
    with pytest.raises(ValueError, match="unknown layout"):
        open_source(tmp_path, layout="lrs3")
    with pytest.raises(ValueError, match="seed must be an integer"):
        open_source("synthtalk:tiny:abc")


def test_synthtalk_source_lists_corpus_clips_with_splits_partners_and_fingerprints(synthtalk_tiny, tmp_path):
    from jaxtalk.data.sources.synthtalk import synthtalk_entries

    entries = synthtalk_entries(synthtalk_tiny)
    assert len(entries) == len(synthtalk_tiny.clips)
    for e, info in zip(entries, synthtalk_tiny.clips):
        assert e.name == f"clip{info.index:05d}" and e.split == info.split
        assert e.speaker == f"spk{info.speaker:03d}"
        assert e.partner == (f"clip{info.partner:05d}" if info.partner >= 0 else None)
        assert e.requires_partner == (info.partner >= 0)
        assert e.files == () and e.content_hash() == f"synthtalk:{synthtalk_tiny.key}:{info.index}"
    raw = entries[0].read()
    np.testing.assert_array_equal(raw.params, synthtalk_tiny.motion(0))
    np.testing.assert_array_equal(raw.audio, synthtalk_tiny.audio(0))
    assert raw.token_rate == 12.5 and raw.tokens.shape[1] == 64
    check_clip(raw, min_frames=25)


def test_synthtalk_dualtalk_export_reads_back_the_corpus_conversations_exactly(synthtalk_tiny, tmp_path):
    from jaxtalk.data.sources.synthtalk import export_dualtalk

    export_dualtalk(synthtalk_tiny, tmp_path)
    src = open_source(tmp_path)
    assert src.layout == "dualtalk"
    pairs = list(synthtalk_tiny.conversations())
    assert len(src.entries) == 2 * len(pairs)
    entries = {e.name: e for e in src.entries}
    for a, b in pairs:
        for side, clip in (("1", a), ("2", b)):
            e = entries[f"clip{a:05d}_conv_speaker{side}"]
            assert e.split == synthtalk_tiny.clips[clip].split
            assert e.partner == f"clip{a:05d}_conv_speaker{'2' if side == '1' else '1'}"
            raw = e.read()
            np.testing.assert_array_equal(raw.params, np.asarray(synthtalk_tiny.motion(clip), np.float32))
            np.testing.assert_array_equal(raw.audio, np.asarray(synthtalk_tiny.audio(clip), np.float32))
            check_clip(raw, min_frames=25)


# ------------------------------------------------------------------------------------------ check_clip
def _raw(**changes) -> RawClip:
    base = dict(fps=25.0, params=np.zeros((50, 56), np.float32), audio=np.full(32000, 0.01, np.float32))
    return RawClip(**{**base, **changes})


@pytest.mark.parametrize("changes, message", [
    (dict(fps=1000.0), "fps"),
    (dict(fps=0.04), "fps"),
    (dict(fps=float("nan")), "fps"),
    (dict(params=np.zeros((50, 55), np.float32)), r"params must be \(frames, 56\)"),
    (dict(params=None), "no motion"),
    (dict(params=np.full((50, 56), np.nan, np.float32)), "params contains 2800 NaN/inf"),
    (dict(audio=np.r_[np.zeros(31999, np.float32), np.float32(np.inf)]), "audio contains 1 NaN/inf"),
    (dict(audio=None), "no audio"),
    (dict(audio=np.zeros(32000 + int(16000 * (MAX_SKEW_SECONDS + 0.05)), np.float32)), "differ by more than"),
    (dict(params=np.zeros((20, 56), np.float32), audio=np.zeros(12800, np.float32)), "too short: 20 frames"),
    (dict(fps=50.0, params=np.zeros((40, 56), np.float32), audio=np.zeros(12800, np.float32)), "too short: 20 frames"),
    (dict(tokens=np.zeros((25, 8), np.float32), token_rate=None), "positive rate"),
    (dict(tokens=np.zeros((50, 8), np.float32), token_rate=12.5), "tokens last 4.00 s"),
    (dict(tokens=np.zeros((0, 8), np.float32), token_rate=12.5), "non-empty"),
])
def test_check_clip_rejects_each_problem_with_its_reason(changes, message):
    with pytest.raises(BadClip, match=message):
        check_clip(_raw(**changes), min_frames=25)


def test_check_clip_accepts_skew_within_limit_and_exact_minimum_length():
    check_clip(_raw(audio=np.zeros(32000 + int(16000 * (MAX_SKEW_SECONDS - 0.05)), np.float32)), min_frames=25)
    check_clip(_raw(params=np.zeros((25, 56), np.float32), audio=np.zeros(16000, np.float32)), min_frames=25)
    check_clip(_raw(fps=60.0, params=None, vertices=np.zeros((120, 5, 3), np.float32)), min_frames=50)
    check_clip(_raw(tokens=np.zeros((25, 8), np.float32), token_rate=12.5), min_frames=25)


def test_synthtalk_source_names_a_corpus_by_size_and_seed_unless_told_and_lists_every_clip(synthtalk_tiny):
    from jaxtalk.data.sources import synthtalk_source

    source = synthtalk_source(synthtalk_tiny)
    assert source.spec == f"synthtalk:{synthtalk_tiny.size}:{synthtalk_tiny.seed}" and source.layout == "synthtalk"
    assert len(source.entries) == len(synthtalk_tiny.clips)
    assert synthtalk_source(synthtalk_tiny, "synthtalk:tiny:0 emotion_gain=5").spec == "synthtalk:tiny:0 emotion_gain=5"
