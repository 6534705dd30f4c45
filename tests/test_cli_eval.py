"""``jaxtalk eval`` on prepared data: every model's table, its baselines checked by hand, and user errors.

Tiny TokTalk, TIMAR and ATS runs are trained through the CLI for two steps on SynthTalk tiny, once per
session (``trained_toktalk``, ``trained_timar``, ``trained_ats`` in conftest); STM, whose training renders
several meshes (minutes), is evaluated from its initial parameters saved as a step-0 checkpoint. Scores of
two-step models mean nothing, so the checks are on the wiring: the tables' shape, finite numbers, the
mean-pose rows recomputed by hand from
the data, and the oracle beating the mean pose on SynthTalk. The real DualTalk demo clips (no oracle,
audio-only partners) run through prepare, train and eval when ``../shared`` is present.
"""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from helpers import (DUALTALK_SOURCES, TINY_TRAIN_ARGS, dualtalk_folder, cli_ok as _ok,
                     cli_error as _user_error, real_voices, syllables, SR)


# The real-data test's own runs (the other tests read the session's runs).
SMALL = {
    "toktalk": [*TINY_TRAIN_ARGS["toktalk"], "--set", "batch_size=4"],
    "timar": [*TINY_TRAIN_ARGS["timar"], "--set", "batch_size=2"],
}


def _table(output: str, title: str, key: str = "method") -> tuple[list[str], dict[str, list[str]]]:
    """``(columns, {row's key cell: cells})`` of the printed table whose title starts with ``title``."""
    lines = output.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(title))
    columns = [c.strip() for c in lines[start + 1].split("|")]
    rows = {}
    for line in lines[start + 3:]:
        cells = [c.strip() for c in line.split("|")]
        if len(cells) != len(columns):
            break
        rows[cells[columns.index(key)]] = cells
    return columns, rows



@pytest.fixture(scope="module")
def runs(trained_toktalk, trained_timar, trained_ats):
    """The session's two-step TokTalk, TIMAR and ATS runs on SynthTalk tiny, trained through the CLI."""
    return {"toktalk": trained_toktalk.dir, "timar": trained_timar.dir, "ats": trained_ats.dir}


def _report(path: Path) -> dict:
    report = json.loads(path.read_text())
    for table in report["tables"]:
        for row in table["rows"]:
            assert all(v is None or isinstance(v, str) or np.isfinite(v) for v in row.values()), row
    return report


def _rows(table: dict) -> dict[str, dict]:
    return {row["method"]: row for row in table["rows"]}


# ------------------------------------------------------------------------------------------ TokTalk


@pytest.mark.slow
def test_toktalk_eval_table_and_mean_pose_by_hand(runs, prepared_tiny, tmp_path):
    from jaxtalk.face import builtin_face

    output = _ok(["eval", runs["toktalk"], "--max-clips", "2", "--json", tmp_path / "r.json"])
    columns, printed = _table(output, "TokTalk on test")
    assert columns == ["method", "clips", "frames", "MSE", "LVE_mm2", "MVE_mm", "FDD_mm2", "MOD_mm", "jitter_mm"]
    assert list(printed) == ["toktalk (streamed, 3 steps)", "mean pose", "oracle", "ground truth"]  # tiny: 3 steps
    report = _report(tmp_path / "r.json")
    assert (report["model"], report["step"], report["split"], report["items"]) == ("toktalk", 2, "test", 2)
    assert report["data"] == str(prepared_tiny.root)
    rows = _rows(report["tables"][0])
    assert all(rows[m][k] is not None for m in ("toktalk (streamed, 3 steps)", "mean pose", "oracle") for k in columns[3:])

    # The mean-pose row from the data: the training mean repeated over the frames the tokens cover.
    data, face = prepared_tiny, builtin_face(0)
    mean = data.motion_stats()["mean"]
    lips = np.asarray(face.regions["lips"])
    mse, mve, lve, frames = [], [], [], []
    for i in [i for i in data.split("test") if data.clips[i]["tokens"]][:2]:
        t = min(2 * data.clips[i]["tokens"], data.clips[i]["frames"])  # 12.5-Hz tokens, 25 fps
        gt = data.record(i, ("motion",))["motion"][:t]
        dist = np.linalg.norm(np.asarray(face.vertices_seq(gt)) - np.asarray(face.vertices(mean))[None], axis=-1)
        mse.append(np.mean((gt - mean) ** 2))
        mve.append(dist.mean() * 1e3)
        lve.append((dist[:, lips] ** 2).max(axis=1).mean() * 1e6)
        frames.append(t)
    assert rows["mean pose"]["frames"] == sum(frames)
    for key, values in (("MSE", mse), ("MVE_mm", mve), ("LVE_mm2", lve)):
        assert rows["mean pose"][key] == pytest.approx(np.average(values, weights=frames), rel=1e-4), key
    assert rows["mean pose"]["jitter_mm"] == 0.0
    # SynthTalk's oracle (the deterministic part of the motion) is far closer than the mean pose.
    for key in ("MSE", "LVE_mm2", "MVE_mm", "MOD_mm"):
        assert rows["oracle"][key] < rows["mean pose"][key], key
    assert rows["ground truth"]["MSE"] is None and rows["ground truth"]["jitter_mm"] > 0


@pytest.mark.slow
def test_toktalk_eval_rows_per_step_count_streamed_and_offline(runs, tmp_path):
    from jaxtalk.runs import load_run

    _ok(["eval", runs["toktalk"], "--max-clips", "1", "--sample-steps", "1", "--sample-steps", "2", "--offline", "--best",
         "--json", tmp_path / "r.json"])
    rows = _rows(_report(tmp_path / "r.json")["tables"][0])
    names = ["toktalk (streamed, 1 step)", "toktalk (streamed, 2 steps)", "toktalk (offline, 1 step)",
             "toktalk (offline, 2 steps)"]
    assert list(rows)[:4] == names
    # The step count reaches the sampler, and offline (full attention) is another computation.
    assert len({rows[n]["LVE_mm2"] for n in names}) == 4
    assert load_run(runs["toktalk"], best=True).step <= load_run(runs["toktalk"]).step
    _user_error(["eval", runs["toktalk"], "--sample-steps", "x"], "must be a whole number of steps")
    _user_error(["eval", runs["toktalk"], "--sample-steps", "1,10"], "repeat it: --sample-steps 1 --sample-steps 10")


def _fake_flame(folder: Path, num_verts: int = 120) -> Path:
    """A small random FLAME-format model file and FLAME_masks.pkl (plain NumPy, no chumpy)."""
    import scipy.sparse

    rng = np.random.default_rng(0)
    regressor = np.abs(rng.normal(size=(5, num_verts))) + 1e-3
    weights = rng.random((num_verts, 5)) ** 3
    model = {
        "v_template": rng.normal(scale=0.05, size=(num_verts, 3)),
        "f": rng.integers(0, num_verts, size=(200, 3)).astype(np.uint32),
        "shapedirs": 0.01 * rng.normal(size=(num_verts, 3, 400)),
        "posedirs": 0.01 * rng.normal(size=(num_verts, 3, 36)),
        "J_regressor": scipy.sparse.csc_matrix(regressor / regressor.sum(axis=1, keepdims=True)),
        "weights": weights / weights.sum(axis=1, keepdims=True),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.int64),
    }
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "generic_model.pkl").write_bytes(pickle.dumps(model, protocol=2))
    masks = {"lips": np.arange(20), "forehead": np.arange(60, 90), "eye_region": np.arange(90, 110)}
    (folder / "FLAME_masks.pkl").write_bytes(pickle.dumps(masks, protocol=2))
    return folder / "generic_model.pkl"


@pytest.mark.slow
def test_toktalk_eval_on_flame_with_its_masks(runs, tmp_path):
    flame = _fake_flame(tmp_path / "flame")
    output = _ok(["eval", runs["toktalk"], "--max-clips", "1", "--flame", flame, "--json", tmp_path / "r.json"])
    assert "vertices on FLAME" in output and "MOD left out" in output
    rows = _rows(_report(tmp_path / "r.json")["tables"][0])
    assert rows["toktalk (streamed, 3 steps)"]["MOD_mm"] is None
    assert rows["toktalk (streamed, 3 steps)"]["LVE_mm2"] > 0 and rows["mean pose"]["FDD_mm2"] is not None
    (tmp_path / "flame" / "FLAME_masks.pkl").unlink()
    output = _ok(["eval", runs["toktalk"], "--max-clips", "1", "--flame", flame, "--json", tmp_path / "r.json"])
    assert "LVE and FDD (lip and upper-face regions) left out" in output
    rows = _rows(_report(tmp_path / "r.json")["tables"][0])
    assert rows["toktalk (streamed, 3 steps)"]["LVE_mm2"] is None and rows["toktalk (streamed, 3 steps)"]["MVE_mm"] > 0


# -------------------------------------------------------------------------------------------- TIMAR


@pytest.mark.slow
def test_timar_eval_groups_and_mean_pose_by_hand(runs, prepared_tiny, tmp_path):
    from jaxtalk.runs import RunRecord
    from jaxtalk.models.timar.data import Normalizer
    from jaxtalk.models.timar.recipe import agent_sides

    output = _ok(["eval", runs["timar"], "--max-clips", "2", "--json", tmp_path / "r.json"])
    for group in ("exp", "jaw", "pose"):
        columns, printed = _table(output, f"TIMAR on test (synthtalk-tiny-seed0), {group}")
        assert columns == ["method", "sides", "frames", "FD", "P-FD", "MSE", "SID", "rPCC"]
        assert list(printed) == ["timar (streamed)", "mean pose", "oracle"]
    assert "jaw (FD x1000, P-FD x1000, MSE x1000, rPCC x10)" in output  # the published scaling
    report = _report(tmp_path / "r.json")
    assert [t["title"].split(", ")[1].split(" ")[0] for t in report["tables"]] == ["exp", "jaw", "pose"]
    tables = {t["title"].split(", ")[1].split(" ")[0]: _rows(t) for t in report["tables"]}
    assert all(v is not None for rows in tables.values() for row in rows.values() for v in row.values())

    # The mean pose is the run's normaliser mean; MSE per side over the whole side (the frames after
    # its last whole turn included: TIMAR's protocol pads them with the last prediction), then averaged.
    data = prepared_tiny
    norm = Normalizer.from_dict(RunRecord.load(runs["timar"]).extra["normalizer"])
    per_side = {"exp": [], "jaw": [], "pose": []}
    totals = []
    for i, j in agent_sides(data, "test")[:2]:
        agent, user = data.record(i, ("motion",)), data.record(j, ("motion",))
        total = min(agent["motion"].shape[0], user["motion"].shape[0])
        totals.append(total)
        err = (agent["motion"][:total] - norm.motion_mean) ** 2
        for group, sl in (("exp", slice(0, 50)), ("jaw", slice(50, 53)), ("pose", slice(53, 56))):
            per_side[group].append(err[:, sl].mean())
    assert any(t % 25 for t in totals) and "repeat the last prediction" in output  # a partial last turn
    for group, scale in (("exp", 10.0), ("jaw", 1e3), ("pose", 1e2)):
        assert tables[group]["timar (streamed)"]["frames"] == sum(totals)
        assert tables[group]["mean pose"]["MSE"] == pytest.approx(scale * np.mean(per_side[group]), rel=1e-4)
        assert tables[group]["oracle"]["MSE"] < tables[group]["mean pose"]["MSE"]
        assert tables[group]["mean pose"]["SID"] == pytest.approx(0.0, abs=1e-5)  # one pose, one cluster


def test_fit_length_repeats_the_last_predicted_frame_to_the_side_length():
    from jaxtalk.data.batching import fit_length as pad_with_last

    pred = np.arange(12, dtype=np.float32).reshape(4, 3)
    padded = pad_with_last(pred, 7)
    np.testing.assert_array_equal(padded[:4], pred)
    np.testing.assert_array_equal(padded[4:], np.repeat(pred[-1:], 3, axis=0))
    np.testing.assert_array_equal(pad_with_last(pred, 4), pred)


# ---------------------------------------------------------------------------------------------- ATS


@pytest.mark.slow
def test_ats_eval_landmark_table_and_baselines_by_hand(runs, prepared_tiny, tmp_path):
    from jaxtalk.runs import RunRecord
    from jaxtalk.data.batching import window_starts

    output = _ok(["eval", runs["ats"], "--max-clips", "1", "--json", tmp_path / "r.json"])
    columns, printed = _table(output, "ATS on test")
    assert columns == ["method", "windows", "frames", "LVE_mm2", "LE_mm", "jitter_mm"]
    assert list(printed) == ["ats (sampled)", "mean pose", "neutral", "oracle", "ground truth"]
    rows = _rows(_report(tmp_path / "r.json")["tables"][0])

    data = prepared_tiny
    extra = RunRecord.load(runs["ats"]).extra
    window, mean = extra["window"], np.asarray(extra["stats"]["mean"], np.float32)
    clip = data.split("test")[0]
    lms = data.record(clip, ("landmarks",))["landmarks"]
    starts = window_starts(lms.shape[0], window, window, pad_short=False)
    assert rows["neutral"]["windows"] == len(starts) and rows["neutral"]["frames"] == len(starts) * window
    for name, base in (("neutral", np.zeros_like(mean)), ("mean pose", mean)):
        dist = [np.linalg.norm(lms[s:s + window] - base, axis=-1) for s in starts]
        assert rows[name]["LE_mm"] == pytest.approx(1e3 * np.mean([d.mean() for d in dist]), rel=1e-4)
        lve = [(d[:, 48:68] ** 2).max(axis=1).mean() for d in dist]
        assert rows[name]["LVE_mm2"] == pytest.approx(1e6 * np.mean(lve), rel=1e-4)
    assert rows["oracle"]["LE_mm"] < rows["mean pose"]["LE_mm"] < rows["neutral"]["LE_mm"]
    assert rows["ats (sampled)"]["jitter_mm"] > 0


@pytest.mark.slow
def test_ats_trained_on_whole_clips_is_scored_on_whole_clips(prepared_tiny, tmp_path):
    from jaxtalk.runs import RunRecord

    run = tmp_path / "ats-whole"
    _ok(["train", "ats", "--data", "synthtalk:tiny", "--cache-dir", prepared_tiny.root.parent, "--steps", "2",
         *TINY_TRAIN_ARGS["ats"], "--set", "batch_size=2", "--set", "window_frames=0", "--no-progress", "--out", run])
    assert RunRecord.load(run).extra["window"] == 0
    output = _ok(["eval", run, "--max-clips", "2", "--json", tmp_path / "r.json"])
    assert "whole clips (at most 300 frames)" in output
    rows = _rows(_report(tmp_path / "r.json")["tables"][0])
    clips = prepared_tiny.split("test")[:2]
    lengths = [min(prepared_tiny.clips[i]["frames"], 300) for i in clips]  # tiny clips are under 300 frames
    assert all(prepared_tiny.clips[i]["frames"] <= 300 for i in clips)
    assert rows["ats (sampled)"]["windows"] == 2 and rows["ats (sampled)"]["frames"] == sum(lengths)


# ---------------------------------------------------------------------------------------------- STM


@pytest.mark.slow
def test_stm_eval_maps_true_landmarks_on_the_run_meshes(stm_run, prepared_tiny, tmp_path):
    from jaxtalk.models.freetalk.data import face_mesh, without_head_pose

    output = _ok(["eval", stm_run, "--max-clips", "1", "--json", tmp_path / "r.json"])
    columns, printed = _table(output, "STM on test")
    assert columns == ["mesh", "method", "clips", "frames", "MVE_mm", "LVE_mm2", "jitter_mm"]
    assert list(printed) == ["stm", "neutral", "ground truth"]
    rows = _rows(_report(tmp_path / "r.json")["tables"][0])
    assert rows["stm"]["mesh"] == "id1/decimated (451 v)"
    fm = face_mesh(1, "decimated")
    motion = prepared_tiny.record(prepared_tiny.split("test")[0], ("motion",))["motion"]
    _, verts = fm.motion(without_head_pose(motion))
    dist = np.linalg.norm(verts, axis=-1)  # the neutral mesh is zero displacement
    assert rows["neutral"]["frames"] == motion.shape[0]
    assert rows["neutral"]["MVE_mm"] == pytest.approx(1e3 * dist.mean(), rel=1e-4)
    assert rows["neutral"]["LVE_mm2"] == pytest.approx(1e6 * (dist[:, fm.region("lips")] ** 2).max(axis=1).mean(), rel=1e-4)
    assert rows["stm"]["MVE_mm"] > 0 and rows["ground truth"]["jitter_mm"] > 0


# ------------------------------------------------------------------------------------------- errors


def _copy_prepared(data, out: Path, edit) -> Path:
    """A prepared folder sharing ``data``'s shards with an edited manifest."""
    out.mkdir(parents=True)
    (out / "shards").symlink_to(data.root / "shards", target_is_directory=True)
    manifest = json.loads((data.root / "manifest.json").read_text())
    edit(manifest)
    (out / "manifest.json").write_text(json.dumps(manifest))
    return out


@pytest.mark.slow
def test_eval_user_errors_are_one_line(runs, prepared_tiny, tmp_path):
    tok, timar = runs["toktalk"], runs["timar"]
    _user_error(["eval", tmp_path], "is not a training run")
    untrained = tmp_path / "untrained"
    untrained.mkdir()
    for name in ("run.json", "features.json"):
        shutil.copy(timar / name, untrained / name)
    _user_error(["eval", untrained], "is not trained yet")
    _user_error(["eval", timar, "--split", "dev"], "unknown split 'dev'; known: train, val, test, ood")
    _user_error(["eval", timar, "--max-clips", "0"], "--max-clips must be >= 1")
    _user_error(["eval", timar, "--flame", tmp_path / "model.pkl"], "--flame poses TokTalk's parameters")
    _user_error(["eval", tok, "--flame", tmp_path / "model.pkl"], "FLAME model file not found")
    _user_error(["eval", tok, "--data", tmp_path / "nowhere"], "is not a prepared dataset")
    _user_error(["eval", timar, "--scoring", "calc_metric"], "--scoring must be jaxtalk, public or both")
    _user_error(["eval", tok, "--scoring", "public"], "--scoring chooses how TIMAR and DualTalk baseline score")

    def empty_test(m):
        for c in m["clips"]:
            c["split"] = "train" if c["split"] == "test" else c["split"]
        m["splits"]["test"] = []

    def narrow_tokens(m):
        m["token_dim"] = 32

    def hubert(m):
        m["settings"]["audio"], m["turn_speech_dim"] = "hubert:/models/hubert", 768

    empty = _copy_prepared(prepared_tiny, tmp_path / "empty", empty_test)
    _user_error(["eval", tok, "--data", empty], "has no clip with motion and tokens")
    _user_error(["eval", timar, "--data", empty], "has no conversation side")
    _user_error(["eval", tok, "--data", _copy_prepared(prepared_tiny, tmp_path / "narrow", narrow_tokens)],
                "has tokens of width 32 at 12.5 Hz, the run was trained on width 64 at 12.5 Hz")
    _user_error(["eval", timar, "--data", _copy_prepared(prepared_tiny, tmp_path / "hubert", hubert)],
                "has 768-d 'hubert:/models/hubert' speech features, the run was trained on 80-d 'logmel'")


def test_timar_eval_scores_both_ways_with_public_scoring_on_the_whole_seconds(runs, prepared_tiny, tmp_path):
    from jaxtalk.models.timar.recipe import agent_sides

    _ok(["eval", runs["timar"], "--max-clips", "2", "--scoring", "both", "--json", tmp_path / "r.json"])
    report = _report(tmp_path / "r.json")
    titles = [t["title"] for t in report["tables"]]
    assert len(titles) == 6 and sum("[jaxtalk scoring" in s for s in titles) == sum("[public scoring" in s for s in titles) == 3
    frames = {("public" if "[public" in t["title"] else "jaxtalk"): _rows(t)["timar (streamed)"]["frames"]
              for t in report["tables"]}
    def length(clip):
        return prepared_tiny.record(clip, ("motion",))["motion"].shape[0]

    totals = [min(length(i), length(j)) for i, j in agent_sides(prepared_tiny, "test")[:2]]
    assert frames == {"jaxtalk": sum(totals), "public": sum(t // 25 * 25 for t in totals)}
    assert frames["public"] < frames["jaxtalk"]


# ---------------------------------------------------------------------------------------- real data


@pytest.mark.slow  # two trainings and evaluations
@pytest.mark.parametrize("source", DUALTALK_SOURCES)
def test_dualtalk_demo_layout_timar_and_toktalk_eval(source, tmp_path, request):
    """DualTalk's demo clips (``real``, where ``../shared`` has them) or the same layout exported from
    SynthTalk: one tracked side per conversation, no validation split, no oracle."""
    from jaxtalk.data.loader import PreparedData

    root = tmp_path / "dualtalk"
    corpus = request.getfixturevalue("synthtalk_tiny") if source == "synthtalk" else None
    test_conv, test_k = dualtalk_folder(root, source, corpus)["test"]
    prepared, run = tmp_path / "prepared", tmp_path / "run"
    _ok(["prepare", root, "--out", prepared, "--no-progress"])
    _ok(["train", "timar", "--data", prepared, "--steps", "2", *SMALL["timar"], "--no-progress", "--out", run])
    output = _ok(["eval", run, "--split", "test", "--json", tmp_path / "r.json"])
    assert "1 of 1 partners have no tracked motion" in output
    report = _report(tmp_path / "r.json")
    assert report["items"] == 1 and len(report["tables"]) == 3
    data = PreparedData(prepared)
    agent, partner = (data.index(f"{test_conv}_speaker{k}") for k in (test_k, 3 - test_k))
    # The partner has no motion: the agent's whole side is scored, the frames after its last whole turn
    # (the partner's speech ends first: real, 29.95 s) repeating the last prediction.
    frames = data.clips[agent]["frames"]
    for group, table in zip(("exp", "jaw", "pose"), report["tables"]):
        assert f", {group}" in table["title"]
        columns, printed = _table(output, table["title"])
        assert columns == ["method", "sides", "frames", "FD", "P-FD", "MSE", "SID", "rPCC"]
        assert list(printed) == ["timar (streamed)", "mean pose"]  # real data: no oracle
        assert all(row["frames"] == frames and all(row[k] is not None for k in columns[3:]) for row in table["rows"])
    _user_error(["eval", run, "--split", "ood"], "has no conversation side")
    # TokTalk on the same folder: DualTalk has no audio-LLM tokens, so prepare fitted a VQ tokenizer
    # on the training split, which the run keeps for new audio.
    tok = tmp_path / "tok"
    _ok(["train", "toktalk", "--data", prepared, "--steps", "2", *SMALL["toktalk"],
         "--no-progress", "--out", tok])
    assert (tok / "tokenizer.npz").is_file()
    output = _ok(["eval", tok, "--split", "test", "--json", tmp_path / "t.json"])
    (table,) = _report(tmp_path / "t.json")["tables"]
    columns, printed = _table(output, table["title"])
    assert {"LVE_mm2", "MVE_mm", "FDD_mm2", "MOD_mm", "jitter_mm"} <= set(columns)
    assert list(printed)[:2] == ["toktalk (streamed, 3 steps)", "mean pose"] and "oracle" not in printed
    assert all(np.isfinite(row["MVE_mm"]) for row in table["rows"] if row.get("MVE_mm") is not None)


# ------------------------------------------------------------------------------------- real voices


def _hand_loudness(audio: np.ndarray, frames: int) -> np.ndarray:
    """dBFS per 25-fps frame (640 samples at 16 kHz), digital silence -100 dB, by hand."""
    out = np.full(frames, -100.0)
    for k in range(frames):
        chunk = audio[640 * k:640 * (k + 1)].astype(np.float64)
        if chunk.size:
            out[k] = max(10 * np.log10(max(np.mean(chunk ** 2), 1e-10)), -100.0)
    return out


_REAL_VOICE_COLUMNS = ["recording", "tracked", "frames", "speech_frames", "corr", "best_lag", "best_corr",
                       "loudness_corr", "loudness_best_lag", "speech_corr", "loudness_speech_corr",
                       "loudness_pred_corr", "loudness_pred_best_lag", "jaw_silence", "jaw_speech"]


@pytest.mark.slow
def test_toktalk_real_voice_table_by_hand(runs, tmp_path):
    from jaxtalk.audio import load_audio
    from jaxtalk.commands.inference import SampleOptions, stream_audio
    from jaxtalk.data.formats import read_npz
    from jaxtalk.metrics.speech_sync import voice_activity
    from jaxtalk.runs import load_run

    folder = tmp_path / "voices"
    jaws = real_voices(folder)
    before = sorted(p.name for p in folder.iterdir())
    output = _ok(["eval", runs["toktalk"], "--real-voice", folder, "--json", tmp_path / "r.json"])
    assert sorted(p.name for p in folder.iterdir()) == before  # nothing written beside the recordings
    columns, printed = _table(output, "TokTalk on real voices (voices)", "recording")
    assert columns == _REAL_VOICE_COLUMNS and list(printed) == ["a", "b", "c", "mean", "digital silence (3 s)"]
    report = _report(tmp_path / "r.json")
    assert (report["model"], report["split"], report["data"], report["items"]) == ("toktalk", None, str(folder), 3)
    (table,) = report["tables"]
    rows = {row["recording"]: row for row in table["rows"]}
    assert list(rows) == ["a", "b", "c", "mean", "digital silence (3 s)"]
    assert [rows[k]["tracked"] for k in rows] == ["yes", "yes", "no", "2 of 3", None]

    for name, suffix, seconds in (("a", ".wav", 2.0), ("b", ".flac", 2.4), ("c", ".wav", 2.0)):
        row = rows[name]
        audio = load_audio(folder / f"{name}{suffix}")
        # The model's jaw is what `jaxtalk stream` writes for the recording (outside the folder).
        _ok(["stream", runs["toktalk"], folder / f"{name}{suffix}", "--out", tmp_path / f"{name}.npz"])
        jaw = read_npz(tmp_path / f"{name}.npz").params[:, 50].astype(np.float64)
        n = round(seconds * 25)
        assert jaw.shape == (n,) and row["frames"] == n  # a: the tracked 51 frames cut to the prediction's 50
        db = _hand_loudness(audio, n)
        speech = voice_activity(db)
        assert row["speech_frames"] == speech.sum() and 0 < speech.sum() < n
        assert row["jaw_speech"] == pytest.approx(jaw[speech].mean(), abs=1e-6)
        assert row["jaw_silence"] == pytest.approx(jaw[~speech].mean(), abs=1e-6)
        assert row["loudness_pred_corr"] == pytest.approx(np.corrcoef(jaw, db)[0, 1], abs=1e-5)
        if name == "c":
            assert all(row[k] is None for k in ("corr", "best_lag", "best_corr", "loudness_corr", "loudness_best_lag"))
            continue
        tracked = jaws[name][:n]
        assert row["corr"] == pytest.approx(np.corrcoef(jaw, tracked)[0, 1], abs=1e-5)
        # The loudness follower: the recording's loudness against the tracked jaw, lag by lag by hand
        # (positive: the loudness at t + lag against the jaw at t).
        by_lag = {lag: np.corrcoef(db[max(lag, 0):n + min(lag, 0)], tracked[max(-lag, 0):n - max(lag, 0)])[0, 1]
                  for lag in range(-8, 9)}
        assert row["loudness_corr"] == pytest.approx(by_lag[0], abs=1e-5)
        assert row["loudness_best_lag"] == max(by_lag, key=by_lag.get)
        # Within speech only, at lag 0.
        assert row["speech_corr"] == pytest.approx(np.corrcoef(jaw[speech], tracked[speech])[0, 1], abs=1e-5)
        assert row["loudness_speech_corr"] == pytest.approx(np.corrcoef(db[speech], tracked[speech])[0, 1], abs=1e-5)
        assert row["best_corr"] >= row["corr"] - 1e-12 and -8 <= row["best_lag"] <= 8
    # The mean row: every recording for the loudness columns, the two tracked ones for the tracked jaw's.
    assert rows["mean"]["frames"] == 50 + 60 + 50
    for key in ("loudness_pred_corr", "jaw_silence", "jaw_speech"):
        assert rows["mean"][key] == pytest.approx(np.mean([rows[k][key] for k in "abc"]), abs=1e-12)
    for key in ("corr", "best_lag", "loudness_corr", "loudness_best_lag"):
        assert rows["mean"][key] == pytest.approx(np.mean([rows[k][key] for k in "ab"]), abs=1e-12)
    # The rest jaw: the same stream on 3 s of digital silence.
    run = load_run(runs["toktalk"])
    rest = stream_audio(run, np.zeros(3 * SR, np.float32), SampleOptions(runs["toktalk"], folder), echo=lambda s: None)
    assert rest.shape == (75, 56)
    assert rows["digital silence (3 s)"]["frames"] == 75 and rows["digital silence (3 s)"]["speech_frames"] == 0
    assert rows["digital silence (3 s)"]["jaw_silence"] == pytest.approx(float(rest[:, 50].mean()), abs=1e-6)
    assert rows["digital silence (3 s)"]["jaw_speech"] is None
    # Beside it, the rest of the run's default style clip: its 5th-percentile jaw.
    style_rest = np.percentile(np.asarray(run.default_style())[:, 50], 5)
    assert table["title"].endswith(f"; the style clip rests at {style_rest:.3f} rad")

    # --max-clips takes the first recordings; --sample-steps gives one table per step count.
    _ok(["eval", runs["toktalk"], "--real-voice", folder, "--max-clips", "1", "--sample-steps", "1", "--sample-steps", "2",
         "--json", tmp_path / "s.json"])
    tables = _report(tmp_path / "s.json")["tables"]
    assert [t["title"].split(":")[0] for t in tables] == ["TokTalk on real voices (voices, 1 step)",
                                                          "TokTalk on real voices (voices, 2 steps)"]
    assert [[r["recording"] for r in t["rows"]] for t in tables] == [["a", "mean", "digital silence (3 s)"]] * 2
    assert tables[0]["rows"][0]["corr"] != tables[1]["rows"][0]["corr"]


@pytest.mark.slow
def test_timar_real_voice_streams_whole_turns(runs, tmp_path):
    from jaxtalk.runs import RunRecord

    folder = tmp_path / "voices"
    real_voices(folder)
    _ok(["eval", runs["timar"], "--real-voice", folder, "--json", tmp_path / "r.json"])
    (table,) = _report(tmp_path / "r.json")["tables"]
    rows = {row["recording"]: row for row in table["rows"]}
    f = RunRecord.load(runs["timar"]).config["frames_per_turn"]
    assert table["title"].startswith("TIMAR on real voices (voices)")
    assert rows["b"]["frames"] == 60 // f * f and rows["digital silence (3 s)"]["frames"] == -(-75 // f) * f
    assert all(rows[k][c] is not None for k in ("a", "b") for c in _REAL_VOICE_COLUMNS[4:])
    # The jaw is what `jaxtalk stream` writes: whole turns, the audio kept with them.
    from jaxtalk.audio import load_audio
    from jaxtalk.data.formats import read_npz

    _ok(["stream", runs["timar"], folder / "b.flac", "--out", tmp_path / "b.npz"])
    clip = read_npz(tmp_path / "b.npz")
    n = 60 // f * f
    assert clip.params.shape == (n, 56) and clip.audio.shape == (n * 640,)
    db = _hand_loudness(load_audio(folder / "b.flac"), n)
    assert rows["b"]["loudness_pred_corr"] == pytest.approx(np.corrcoef(clip.params[:, 50], db)[0, 1], abs=1e-5)


@pytest.mark.slow
def test_real_voice_user_errors(runs, tmp_path):
    tok = runs["toktalk"]
    _user_error(["eval", tok, "--real-voice", tmp_path / "nowhere"], "--real-voice folder not found")
    (tmp_path / "empty").mkdir()
    _user_error(["eval", tok, "--real-voice", tmp_path / "empty"], "is empty")
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("no audio here")
    _user_error(["eval", tok, "--real-voice", tmp_path / "notes"], "has no audio file", "readme.txt")
    folder = tmp_path / "voices"
    real_voices(folder)
    _user_error(["eval", runs["ats"], "--real-voice", folder], "through toktalk and timar runs", "is an ats run")
    for option in (["--data", "synthtalk:tiny"], ["--split", "val"], ["--offline"]):
        _user_error(["eval", tok, "--real-voice", folder, *option], f"{option[0]}: not with --real-voice")
    _user_error(["eval", tok, "--real-voice", folder, "--json", folder / "r.json"], "r.json")  # never into the folder
    np.savez(folder / "a.npz", params=np.zeros((55, 56), np.float32))
    _user_error(["eval", tok, "--real-voice", folder], "a.npz' has 55 frames, its recording lasts 50.0 frames")
    bad = np.zeros((50, 6), np.float32)
    bad[7, 3] = np.nan
    np.savez(folder / "a.npz", pose=bad)
    _user_error(["eval", tok, "--real-voice", folder], "a.npz': pose contains 1 NaN")
    np.savez(folder / "a.npz", exp=np.zeros((50, 50), np.float32))
    _user_error(["eval", tok, "--real-voice", folder], "holds neither 'pose' (frames, 6) nor 'params' (frames, 56)")
    np.savez(folder / "a.npz", params=np.zeros((50, 56), np.float32), fps=30)
    _user_error(["eval", tok, "--real-voice", folder], "tracked at 30 fps")
    (folder / "a.npz").unlink()
    import soundfile as sf

    sf.write(folder / "short.wav", syllables(0.3), SR)
    _user_error(["eval", tok, "--real-voice", folder], "short.wav' lasts 0.30 s", "at least 0.44 s")


@pytest.mark.slow
def test_real_voice_on_dualtalk_demo_recordings(runs, tmp_path):
    """DualTalk's demo pairs (``X_speakerK.wav`` + ``X_speakerK.npz``, where ``../shared`` has them)."""
    from helpers import DUALTALK_DEMO

    if not DUALTALK_DEMO.is_dir():
        pytest.skip("shared DualTalk demo data not available")
    folder = tmp_path / "dualtalk"
    folder.mkdir()
    for f in DUALTALK_DEMO.glob("*_speaker*"):
        (folder / f.name).symlink_to(f)
    output = _ok(["eval", runs["toktalk"], "--real-voice", folder, "--json", tmp_path / "r.json"])
    _, printed = _table(output, "TokTalk on real voices (dualtalk)", "recording")
    (table,) = _report(tmp_path / "r.json")["tables"]
    rows = {row["recording"]: row for row in table["rows"]}
    stems = sorted(f.stem for f in DUALTALK_DEMO.glob("*_speaker*.wav"))
    assert list(rows) == list(printed) == [*stems, "mean", "digital silence (3 s)"] and len(stems) == 4
    tracked = {f.stem for f in DUALTALK_DEMO.glob("*_speaker*.npz")}
    for stem in stems:
        row = rows[stem]
        assert row["tracked"] == ("yes" if stem in tracked else "no")
        assert row["frames"] in (587, 749) and 0 < row["speech_frames"] < row["frames"]
        want = _REAL_VOICE_COLUMNS[4:] if stem in tracked else ["loudness_pred_corr", "jaw_silence", "jaw_speech"]
        assert all(np.isfinite(row[c]) for c in want), row
    assert all(np.isfinite(rows["mean"][c]) for c in _REAL_VOICE_COLUMNS[4:])
    assert rows["mean"]["tracked"] == "2 of 4" and np.isfinite(rows["digital silence (3 s)"]["jaw_silence"])
    # The loudness follower on the real speakers is a real baseline (DualTalk's tracked jaw opens with the sound).
    assert all(rows[s]["loudness_corr"] > 0.0 for s in tracked if s.startswith("xkHw"))
