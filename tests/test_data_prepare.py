"""``prepare``: broken clips reported while the good ones are prepared (and ``strict`` stopping at the
first), incremental and resumable runs (content hashes, killed runs, orphan shards), SynthTalk
prepared from disk and from memory giving identical records and windows, and the real DualTalk demo
clips."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from jaxtalk.data import prepare as prepare_mod
from jaxtalk.data.loader import PreparedData
from jaxtalk.data.prepare import PrepareSettings, prepare
from jaxtalk.data.sources import BadClip, open_source
from jaxtalk.data.sources.synthtalk import export_generic, synthtalk_entries
from helpers import DUALTALK_SOURCES, dualtalk_folder

FAST = PrepareSettings(tokens="none", landmarks=False)


def _quiet(*args, **kwargs):
    return prepare(*args, progress=False, echo=lambda s: None, **kwargs)


def _clip(root: Path, name: str, *, frames: int = 50, fps: float = 25.0, audio_seconds: float | None = None,
          seed: int = 0, wav: bool = True, **arrays) -> None:
    """A generic-layout clip: random params56 at ``fps`` and noise audio as long as the motion."""
    rng = np.random.default_rng(seed)
    params = arrays.pop("params56", rng.standard_normal((frames, 56)).astype(np.float32))
    np.savez(root / f"{name}.npz", params56=params, fps=np.float64(fps), **arrays)
    if wav:
        seconds = frames / fps if audio_seconds is None else audio_seconds
        audio = (0.1 * rng.standard_normal(int(round(seconds * 16000)))).astype(np.float32)
        sf.write(str(root / f"{name}.wav"), audio, 16000, subtype="FLOAT")


def _manifest(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())


def _report(out: Path) -> list[dict[str, str]]:
    with open(out / "report.csv", newline="") as handle:
        return list(csv.DictReader(handle))


def _records(out: Path) -> dict[str, dict[str, np.ndarray]]:
    data = PreparedData(out)
    return {c["name"]: data.record(i) for i, c in enumerate(data.clips)}


def _assert_records_equal(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert a[k].tobytes() == b[k].tobytes(), k


# ------------------------------------------------------------------------------------------ records
def test_record_encoding_round_trips_every_array_bitwise():
    from jaxtalk.data.prepare import decode_array, encode_array

    rng = np.random.default_rng(0)
    arrays = {"motion": rng.standard_normal((50, 56)).astype(np.float32), "index": np.arange(7),
              "scalar": np.asarray(np.float32(3.5)), "fortran": np.asfortranarray(rng.standard_normal((3, 4))),
              "empty": np.zeros((0, 5), np.float32), "mask": np.arange(10) < 3,
              "big_endian": rng.standard_normal((3, 4, 5)).astype(">f8"), "half": np.ones((2, 3), np.float16)}
    for k, v in arrays.items():
        got = decode_array(encode_array(v))
        assert got.dtype == np.asarray(v).dtype and got.shape == np.shape(v), k
        np.testing.assert_array_equal(got, v)
        assert got.flags.writeable
        view = decode_array(encode_array(v), copy=False)
        np.testing.assert_array_equal(view, v)
        assert not view.flags.writeable


# ------------------------------------------------------------------------------------------ broken clips
@pytest.fixture
def broken_generic(tmp_path):
    """Good clips ``good*`` and one clip per kind of problem (the names sort ``bad_*`` first)."""
    root = tmp_path / "src"
    root.mkdir()
    for k in range(3):
        _clip(root, f"good{k}", seed=k)
    (root / "bad_a_garbage.npz").write_bytes(b"this is not a zip file at all" * 10)
    sf.write(str(root / "bad_a_garbage.wav"), np.zeros(32000, np.float32), 16000)
    nan = np.random.default_rng(9).standard_normal((50, 56)).astype(np.float32)
    nan[10, 3] = np.nan
    _clip(root, "bad_b_nan", params56=nan)
    _clip(root, "bad_c_inf_audio", wav=False)
    audio = np.full(32000, 0.01, np.float32)
    audio[100] = np.inf
    sf.write(str(root / "bad_c_inf_audio.wav"), audio, 16000, subtype="FLOAT")
    _clip(root, "bad_d_skew", audio_seconds=2.5)
    _clip(root, "bad_e_fps_high", frames=50, fps=1000.0, audio_seconds=2.0)
    _clip(root, "bad_f_fps_low", frames=50, fps=0.04, audio_seconds=2.0)
    _clip(root, "bad_g_short", frames=20)
    _clip(root, "bad_h_no_wav", wav=False)
    _clip(root, "bad_i_lonely")
    (root / "metadata.csv").write_text("clip,speaker,partner\nbad_i_lonely,s9,ghost\ngood0,s0,\ngood1,s1,good2\ngood2,s2,good1\n")
    expect = {  # clip -> what its report reason must say
        "bad_a_garbage": "unreadable", "bad_b_nan": "NaN", "bad_c_inf_audio": "NaN/inf",
        "bad_d_skew": "differ", "bad_e_fps_high": "fps", "bad_f_fps_low": "fps", "bad_g_short": "too short",
        "bad_h_no_wav": "missing", "bad_i_lonely": "missing partner",
    }
    return root, expect


def test_broken_clips_are_reported_with_their_reason_and_only_good_clips_are_prepared(broken_generic, tmp_path):
    root, expect = broken_generic
    result = _quiet(root, tmp_path / "out", FAST)
    rows = _report(tmp_path / "out")
    assert [Path(r["file"]).name for r in rows] == [f"{n}.npz" for n in sorted(expect)]
    for row in rows:
        name = Path(row["file"]).stem
        assert expect[name] in row["reason"], (name, row["reason"])
    assert "0.04" in rows[5]["reason"] and "1000" in rows[4]["reason"]
    assert "20 frames" in rows[6]["reason"]
    assert "ghost" in rows[8]["reason"]
    assert "wav" in rows[7]["reason"]
    assert sorted(result.skipped) == sorted((r["file"], r["reason"]) for r in rows)
    m = _manifest(tmp_path / "out")
    assert [c["name"] for c in m["clips"]] == ["good0", "good1", "good2"]
    assert result.clips == 3 and result.new == 3
    assert m["clips"][1]["partner"] == "good2" and m["clips"][0]["partner"] is None


def test_broken_clips_do_not_stick_and_are_reported_again_on_the_next_run(broken_generic, tmp_path):
    root, expect = broken_generic
    _quiet(root, tmp_path / "out", FAST)
    result = _quiet(root, tmp_path / "out", FAST)
    assert result.new == 0 and result.clips == 3
    assert len(_report(tmp_path / "out")) == len(expect)
    # Fixing a clip brings it in (and only it is prepared).
    _clip(root, "bad_g_short", frames=30, seed=4)
    result = _quiet(root, tmp_path / "out", FAST)
    assert result.new == 1 and "bad_g_short" in [c["name"] for c in _manifest(tmp_path / "out")["clips"]]
    assert len(_report(tmp_path / "out")) == len(expect) - 1


def test_strict_raises_badclip_naming_the_first_bad_clips_file(broken_generic, tmp_path):
    root, _ = broken_generic
    with pytest.raises(BadClip) as err:
        _quiet(root, tmp_path / "out", FAST, strict=True)
    assert str(err.value).startswith(str(root / "bad_a_garbage.npz") + ": unreadable")
    # Without the first one, the next one is named.
    (root / "bad_a_garbage.npz").unlink()
    (root / "bad_a_garbage.wav").unlink()
    with pytest.raises(BadClip, match=r"bad_b_nan\.npz: params contains 1 NaN/inf"):
        _quiet(root, tmp_path / "out", FAST, strict=True)


def test_dualtalk_missing_partner_missing_wav_and_sides_of_bad_partners_are_reported(tmp_path):
    rng = np.random.default_rng(0)
    root = tmp_path / "dt"
    (root / "train").mkdir(parents=True)

    def side(stem, npz=True, wav=True, nan=False):
        if npz:
            exp = rng.standard_normal((50, 50)).astype(np.float32)
            exp[3, 3] = np.nan if nan else exp[3, 3]
            np.savez(root / "train" / f"{stem}.npz", exp=exp, pose=rng.standard_normal((50, 6)).astype(np.float32))
        if wav:
            sf.write(str(root / "train" / f"{stem}.wav"), (0.1 * rng.standard_normal(44100)).astype(np.float32), 22050)

    side("alone_speaker1")  # its partner's files are absent
    side("nowav_speaker1", wav=False)  # motion without audio
    side("nowav_speaker2")  # a side with motion whose partner has no wav
    side("ok_speaker1")
    side("ok_speaker2", npz=False)  # audio-only partner
    side("sick_speaker1", nan=True)
    side("sick_speaker2", npz=False)  # an audio-only side whose partner's motion is broken
    result = _quiet(root, tmp_path / "out", FAST)
    rows = _report(tmp_path / "out")
    assert [Path(r["file"]).name for r in rows] == [  # source order
        "alone_speaker1.npz", "nowav_speaker1.npz", "nowav_speaker2.npz", "sick_speaker1.npz", "sick_speaker2.wav"]
    reasons = {Path(r["file"]).stem: r["reason"] for r in rows}
    assert reasons["alone_speaker1"].startswith("missing partner") and "alone_speaker2" in reasons["alone_speaker1"]
    assert "missing file" in reasons["nowav_speaker1"] and "nowav_speaker1.wav" in reasons["nowav_speaker1"]
    assert reasons["nowav_speaker2"].startswith("missing partner") and "nowav_speaker1" in reasons["nowav_speaker2"]
    assert "NaN" in reasons["sick_speaker1"]
    assert reasons["sick_speaker2"].startswith("missing partner") and "sick_speaker1" in reasons["sick_speaker2"]
    clips = {c["name"]: c for c in _manifest(tmp_path / "out")["clips"]}
    assert sorted(clips) == ["ok_speaker1", "ok_speaker2"]
    assert clips["ok_speaker1"]["partner"] == "ok_speaker2" and clips["ok_speaker2"]["partner"] == "ok_speaker1"
    assert (result.clips, result.new) == (2, 2)
    # Fixing the broken motion brings both sides back; only it is prepared (its partner's record was kept).
    side("sick_speaker1")
    result = _quiet(root, tmp_path / "out", FAST)
    assert (result.clips, result.new) == (4, 1)
    assert len(_report(tmp_path / "out")) == 3
    with pytest.raises(BadClip, match=r"alone_speaker1\.npz: missing partner"):
        _quiet(root, tmp_path / "strict", FAST, strict=True)


# ------------------------------------------------------------------------------------------ incremental
@pytest.fixture
def six_clips(tmp_path):
    root = tmp_path / "src"
    root.mkdir()
    for k in range(6):
        _clip(root, f"c{k}", frames=40 + 5 * k, seed=k)
    return root


def test_second_run_prepares_nothing_and_rewrites_identical_manifest(six_clips, tmp_path):
    out = tmp_path / "out"
    first = _quiet(six_clips, out, FAST, shard_clips=4)
    text = (out / "manifest.json").read_text()
    shards = {p.name: p.stat().st_mtime_ns for p in (out / "shards").iterdir()}
    second = _quiet(six_clips, out, FAST, shard_clips=4)
    assert (first.new, first.clips) == (6, 6)
    assert (second.new, second.clips) == (0, 6)
    assert (out / "manifest.json").read_text() == text
    assert {p.name: p.stat().st_mtime_ns for p in (out / "shards").iterdir()} == shards
    assert sorted(shards) == ["00000.array_record", "00000.json", "00001.array_record", "00001.json"]


def test_edited_clip_is_reprepared_alone_and_the_manifest_points_at_its_new_record(six_clips, tmp_path):
    out = tmp_path / "out"
    _quiet(six_clips, out, FAST)
    before = _manifest(out)
    old = _records(out)
    name = before["splits"]["train"][1]  # a training clip: the statistics must follow the edit
    edited = np.random.default_rng(77).standard_normal((50, 56)).astype(np.float32)
    _clip(six_clips, name, params56=edited, seed=2)
    result = _quiet(six_clips, out, FAST)
    assert (result.new, result.clips) == (1, 6)
    after = _manifest(out)
    entry = {c["name"]: c for c in after["clips"]}[name]
    assert entry["shard"] == "00001.array_record" and entry["index"] == 0 and entry["frames"] == 50
    assert entry["hash"] != {c["name"]: c for c in before["clips"]}[name]["hash"]
    assert after["shards"] == ["00000.array_record", "00001.array_record"]
    new = _records(out)
    np.testing.assert_array_equal(new[name]["motion"], edited)
    for other in new:
        if other != name:
            _assert_records_equal(new[other], old[other])
    assert after["stats"] != before["stats"]
    assert [{k: v for k, v in c.items() if k not in ("shard", "index", "hash", "frames")} for c in after["clips"]] == [
        {k: v for k, v in c.items() if k not in ("shard", "index", "hash", "frames")} for c in before["clips"]]


def test_clip_that_turns_bad_leaves_the_manifest(six_clips, tmp_path):
    out = tmp_path / "out"
    _quiet(six_clips, out, FAST)
    broken = np.zeros((55, 56), np.float32)
    broken[0, 0] = np.nan
    _clip(six_clips, "c3", params56=broken, seed=3)
    result = _quiet(six_clips, out, FAST)
    assert [Path(r["file"]).name for r in _report(out)] == ["c3.npz"]
    assert "c3" not in [c["name"] for c in _manifest(out)["clips"]]
    assert result.clips == 5 and "c3" not in (PreparedData(out).manifest["splits"]["train"]
                                              + PreparedData(out).manifest["splits"]["val"])


def test_added_clip_is_prepared_alone(six_clips, tmp_path):
    out = tmp_path / "out"
    _quiet(six_clips, out, FAST)
    _clip(six_clips, "c9", frames=70, seed=9)
    result = _quiet(six_clips, out, FAST)
    assert (result.new, result.clips) == (1, 7)
    clips = {c["name"]: c for c in _manifest(out)["clips"]}
    assert clips["c9"]["frames"] == 70 and clips["c9"]["shard"] == "00001.array_record"


def test_removed_clip_disappears_from_the_manifest(six_clips, tmp_path):
    out = tmp_path / "out"
    _quiet(six_clips, out, FAST)
    (six_clips / "c4.npz").unlink()
    (six_clips / "c4.wav").unlink()
    result = _quiet(six_clips, out, FAST)
    m = _manifest(out)
    assert (result.new, result.clips) == (0, 5)
    assert [c["name"] for c in m["clips"]] == ["c0", "c1", "c2", "c3", "c5"]
    assert all("c4" not in names for names in m["splits"].values())


def test_changed_feature_settings_reprepare_every_clip(six_clips, tmp_path):
    out = tmp_path / "out"
    _quiet(six_clips, out, FAST)
    result = _quiet(six_clips, out, dataclasses.replace(FAST, vq_width=32))
    assert result.new == 6
    assert [p.name for p in sorted((out / "shards").iterdir())] == ["00000.array_record", "00000.json"]


def test_preparation_of_an_older_format_is_refused_by_the_reader_and_prepared_again_in_full(six_clips, tmp_path):
    out = tmp_path / "out"
    _quiet(six_clips, out, FAST)
    before = _records(out)
    # What format 1 left: a manifest and shard indices without the format field.
    manifest = _manifest(out)
    (out / "manifest.json").write_text(json.dumps({**manifest, "format": 1}))
    index = out / "shards" / "00000.json"
    index.write_text(json.dumps({k: v for k, v in json.loads(index.read_text()).items() if k != "format"}))
    assert not prepare_mod.is_current(out)
    with pytest.raises(ValueError, match="format 1, this jaxtalk reads 2; prepare again"):
        PreparedData(out)
    result = _quiet(six_clips, out, FAST)
    assert (result.new, result.clips) == (6, 6) and prepare_mod.is_current(out)
    after = _records(out)
    for name in before:
        _assert_records_equal(before[name], after[name])


def test_clip_records_are_one_array_each_and_an_arrays_chunks_concatenate_back_to_it():
    from jaxtalk.data.prepare import decode_array, encode_clip, record_positions

    rng = np.random.default_rng(0)
    arrays = {"motion": rng.standard_normal((60, 56)).astype(np.float32),
              "tokens": rng.standard_normal((30, 4)).astype(np.float32),
              "speech": rng.standard_normal((60, 8)).astype(np.float32),
              "oracle": rng.standard_normal((47, 56)).astype(np.float32),  # shorter than the clip
              "template": np.ones((5, 3), np.float32)}
    records, layout = encode_clip(arrays, chunk_frames=25)
    assert layout == {"head": ["tokens", "template"], "framed": ["motion", "speech", "oracle"], "chunks": 3}
    assert len(records) == 2 + 3 * 3
    clip = {**layout, "index": 10}
    where = record_positions(clip, ["oracle", "tokens", "nope", "motion"], range(1, 3))
    assert where == [("tokens", -1, 10), ("oracle", 1, 17), ("motion", 1, 15), ("oracle", 2, 20), ("motion", 2, 18)]
    for k in ("tokens", "template"):
        (_, _, index), = record_positions(clip, [k], range(0))
        assert decode_array(records[index - 10]).tobytes() == arrays[k].tobytes()
    for k in ("motion", "speech", "oracle"):
        pieces = [decode_array(records[index - 10]) for _, _, index in record_positions(clip, [k], range(3))]
        assert [len(p) for p in pieces] == ([25, 22, 0] if k == "oracle" else [25, 25, 10])
        whole = np.concatenate(pieces)
        assert whole.dtype == arrays[k].dtype and whole.tobytes() == arrays[k].tobytes(), k
    # A clip without per-frame arrays still has one chunk (of nothing); a chunk size below 1 is refused.
    assert encode_clip({"tokens": arrays["tokens"]})[1] == {"head": ["tokens"], "framed": [], "chunks": 1}
    with pytest.raises(ValueError, match="chunk_frames must be >= 1"):
        encode_clip(arrays, chunk_frames=0)


def test_killed_run_keeps_its_first_shard_and_the_rerun_prepares_only_the_rest(six_clips, tmp_path):
    src = open_source(six_clips)

    def interrupted():
        raise KeyboardInterrupt

    broken = dataclasses.replace(src, entries=tuple(
        dataclasses.replace(e, read=interrupted) if k == 2 else e for k, e in enumerate(src.entries)))
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        _quiet(broken, out, FAST, shard_clips=2)
    shard, index = out / "shards" / "00000.array_record", out / "shards" / "00000.json"
    stat = [(p.stat().st_ino, p.stat().st_mtime_ns) for p in (shard, index)]
    assert sorted(p.name for p in (out / "shards").iterdir()) == ["00000.array_record", "00000.json"]
    assert not (out / "manifest.json").exists()

    result = _quiet(src, out, FAST, shard_clips=2)
    assert (result.new, result.clips) == (4, 6)
    assert [(p.stat().st_ino, p.stat().st_mtime_ns) for p in (shard, index)] == stat
    clean = tmp_path / "clean"
    _quiet(src, clean, FAST, shard_clips=2)
    assert _manifest(out)["clips"] == _manifest(clean)["clips"]  # same shards and indices, too
    assert _manifest(out)["stats"] == _manifest(clean)["stats"]
    resumed, fresh = _records(out), _records(clean)
    assert list(resumed) == list(fresh) == [f"c{k}" for k in range(6)]
    for name in fresh:
        _assert_records_equal(resumed[name], fresh[name])


def test_orphan_shard_without_its_index_is_removed_on_the_next_run(six_clips, tmp_path, monkeypatch):
    out = tmp_path / "out"
    real = prepare_mod.atomic_write_text

    def killed_before_second_index(path, text):
        if path.name == "00001.json":
            raise KeyboardInterrupt  # killed between the shard's rename and its index's
        real(path, text)

    monkeypatch.setattr(prepare_mod, "atomic_write_text", killed_before_second_index)
    src = open_source(six_clips)
    with pytest.raises(KeyboardInterrupt):
        _quiet(src, out, FAST, shard_clips=3)
    monkeypatch.setattr(prepare_mod, "atomic_write_text", real)
    assert sorted(p.name for p in (out / "shards").iterdir()) == ["00000.array_record", "00000.json", "00001.array_record"]
    # Temporary files of a kill during a write go too.
    (out / "shards" / ".00002.array_record.tmp").write_bytes(b"half a shard")
    (out / "shards" / ".00002.json.123.tmp").write_text("{")
    # The next run, over the clips of the finished shard only, writes nothing: the orphan must go.
    first_three = dataclasses.replace(src, entries=src.entries[:3])
    result = _quiet(first_three, out, FAST, shard_clips=3)
    assert (result.new, result.clips) == (0, 3)
    assert sorted(p.name for p in (out / "shards").iterdir()) == ["00000.array_record", "00000.json"]
    assert _manifest(out)["shards"] == ["00000.array_record"]
    # And with every clip again, the missing three are prepared (not taken from the orphan).
    result = _quiet(src, out, FAST, shard_clips=3)
    assert (result.new, result.clips) == (3, 6)
    assert sorted(p.name for p in (out / "shards").glob("*.array_record")) == ["00000.array_record", "00001.array_record"]


# ------------------------------------------------------------------------------------------ SynthTalk
@pytest.fixture(scope="module")
def synth_pair(synthtalk_tiny, prepared_tiny, tmp_path_factory):
    """The tiny corpus prepared from memory (the session's ``prepared_tiny``: a ``Source`` of
    ``synthtalk_entries`` with default settings) and from its generic-layout export."""
    base = tmp_path_factory.mktemp("synth_pair")
    exported = export_generic(synthtalk_tiny, base / "export")
    _quiet(exported, base / "from_disk")
    return prepared_tiny, PreparedData(base / "from_disk"), exported


def test_synthtalk_export_lists_the_corpus_as_generic_clips(synth_pair, synthtalk_tiny):
    _, _, exported = synth_pair
    src = open_source(exported)
    mem = synthtalk_entries(synthtalk_tiny)
    assert src.layout == "generic"
    fields = ("name", "speaker", "split", "emotion", "intensity", "partner", "requires_partner")
    assert [tuple(getattr(e, f) for f in fields) for e in src.entries] == [tuple(getattr(e, f) for f in fields) for e in mem]


def test_synthtalk_prepared_from_disk_and_memory_have_identical_clips_splits_stats_and_records(synth_pair):
    mem, disk, _ = synth_pair
    assert mem.manifest["source"] == {"spec": "synthtalk:tiny:0", "layout": "synthtalk"}
    assert disk.manifest["source"]["layout"] == "generic"
    drop = ("hash",)
    assert [{k: v for k, v in c.items() if k not in drop} for c in mem.clips] == [
        {k: v for k, v in c.items() if k not in drop} for c in disk.clips]
    assert len(mem.clips) == 42
    for key in ("splits", "stats", "settings", "settings_hash", "token_rate", "token_dim", "speech_dim",
                "turn_speech_dim", "shards", "tokenizer"):
        assert mem.manifest[key] == disk.manifest[key], key
    assert mem.manifest["settings"]["tokens"] == "clip" and mem.manifest["token_rate"] == 12.5
    assert mem.manifest["tokenizer"] == "tokenizer.npz"
    with np.load(mem.root / "tokenizer.npz") as a, np.load(disk.root / "tokenizer.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k])
    assert (mem.root / "report.csv").read_text() == (disk.root / "report.csv").read_text() == "file,reason\n"
    for name in ("clip00000", "clip00017", "clip00024", "clip00034", "clip00041"):
        a, b = mem.record(mem.index(name)), disk.record(disk.index(name))
        assert set(a) == {"motion", "oracle", "speech", "turn_speech", "landmarks", "tokens"}
        _assert_records_equal(a, b)


def test_synthtalk_recipe_windows_are_bitwise_equal_from_disk_and_memory(synth_pair):
    from jaxtalk.models.freetalk.recipe import ATSWindows, fit_displacement_stats
    from jaxtalk.models.timar.config import TimarConfig
    from jaxtalk.models.timar.recipe import make_windows
    from jaxtalk.models.toktalk.config import TokTalkConfig
    from jaxtalk.models.toktalk.recipe import TokTalkWindows

    mem, disk = synth_pair[:2]
    recipes = [
        (TokTalkWindows(TokTalkConfig(), 100), TokTalkWindows(TokTalkConfig(), 100)),
        (make_windows(TimarConfig(), mem), make_windows(TimarConfig(), disk)),
        (ATSWindows(50, fit_displacement_stats(mem)), ATSWindows(50, fit_displacement_stats(disk))),
    ]
    for rm, rd in recipes:
        for split in ("train", "val"):
            tm, td = rm.table(mem, split), rd.table(disk, split)
            assert len(tm) > 0
            np.testing.assert_array_equal(tm, td)
            for row in tm[:: max(len(tm) // 6, 1)]:
                _assert_records_equal(rm.example(mem, row), rd.example(disk, row))


@pytest.mark.slow
# ------------------------------------------------------------------------------------------ real data
@pytest.mark.parametrize("source", DUALTALK_SOURCES)
def test_dualtalk_demo_layout_prepares_four_sides_with_exact_motion_turn_speech_and_vq_tokens(source, tmp_path, request):
    """DualTalk's demo clips (``real``, where ``../shared`` has them) or the same layout exported from
    SynthTalk: two conversations, each with one side tracked."""
    from jaxtalk.data.formats import read_dualtalk

    root = tmp_path / "dualtalk"
    corpus = request.getfixturevalue("synthtalk_tiny") if source == "synthtalk" else None
    convs = dualtalk_folder(root, source, corpus)
    (train_conv, train_k), (test_conv, _) = convs["train"], convs["test"]
    result = _quiet(root, tmp_path / "out")
    assert result.skipped == [] and result.clips == 4
    data = PreparedData(tmp_path / "out")
    m = data.manifest
    motion = {c["name"]: c["has_motion"] for c in data.clips}
    assert motion == {f"{conv}_speaker{k}": k == with_motion for conv, with_motion in convs.values() for k in (1, 2)}
    assert m["splits"]["train"] == [f"{train_conv}_speaker1", f"{train_conv}_speaker2"]
    assert m["splits"]["test"] == [f"{test_conv}_speaker1", f"{test_conv}_speaker2"]
    assert m["settings"]["tokens"] == "vq" and m["tokenizer"] == "tokenizer.npz"
    assert m["token_rate"] == 12.5 and m["token_dim"] == 64
    assert data.tokenizer() is not None
    for c in data.clips:
        rec = data.record(data.index(c["name"]))
        T = c["frames"]
        assert rec["turn_speech"].shape == (T // 25 * 25, 80)
        assert rec["speech"].shape == (T, 320)
        assert rec["tokens"].shape[1] == 64 and rec["tokens"].shape[0] == c["tokens"]
        assert abs(rec["tokens"].shape[0] - T / 2) <= 1  # 12.5 Hz: one token per two frames
        assert all(np.isfinite(v).all() for v in rec.values())
        if c["has_motion"]:
            clip = read_dualtalk(root / c["split"] / f"{c['name']}.npz", load_audio=False)
            assert rec["motion"].dtype == np.float32
            np.testing.assert_array_equal(rec["motion"], clip.params)
            assert rec["landmarks"].shape == (T, 68, 3)
        else:
            assert "motion" not in rec and "landmarks" not in rec
    if source == "real":
        assert {c["name"]: c["frames"] for c in data.clips if c["has_motion"]} == {
            "UbjUDM1MiGE_sub_video_72_speaker2": 587, "xkHwlcDSOjc_sub_video_109_000_speaker1": 750}
    tracked = f"{train_conv}_speaker{train_k}"
    assert data.partner(data.index(tracked)) == data.index(f"{train_conv}_speaker{3 - train_k}")
    # Training statistics come from the one training side with motion.
    train = data.record(data.index(tracked))["motion"].astype(np.float64)
    np.testing.assert_allclose(m["stats"]["motion_mean"], train.mean(0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m["stats"]["motion_std"], train.std(0), rtol=1e-6, atol=1e-9)
