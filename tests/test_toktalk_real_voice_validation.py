"""TokTalk's real-voice validation during training (``jaxtalk train toktalk --real-voice FOLDER``): the
logged real-voice metrics equal a hand computation from what ``jaxtalk stream`` gives for each recording
with the evaluated checkpoint, ``--select real_corr`` keeps the evaluation of the highest ``real_corr``
as ``checkpoint/best``, and a bad folder or selection is one line before training.

One tiny TokTalk run (three steps, validated at each) on SynthTalk tiny with the suite's three-recording
folder (two with tracked motion) is shared by the tests.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from helpers import TINY_TRAIN_ARGS, cli_error, cli_ok, real_voices

STEPS = 3


def _train_args(prepared_tiny, out, *more, steps: int = STEPS) -> list:
    return ["train", "toktalk", "--data", "synthtalk:tiny", "--cache-dir", prepared_tiny.root.parent, "--steps",
            str(steps), "--set", "batch_size=2", *TINY_TRAIN_ARGS["toktalk"], "--set", "eval_every=1",
            "--no-progress", "--out", out, *more]


@pytest.fixture(scope="module")
def trained(prepared_tiny, tmp_path_factory):
    """A tiny TokTalk run validated at every step on the real voices, its best checkpoint by real_corr."""
    root = tmp_path_factory.mktemp("real_voice_train")
    folder = root / "voices"
    jaws = real_voices(folder)
    output = cli_ok(_train_args(prepared_tiny, root / "run", "--real-voice", folder, "--select", "real_corr"))
    return {"dir": root / "run", "voices": folder, "jaws": jaws, "output": output}


def _by_hand(run_dir, folder, jaws: dict, *, best: bool = False) -> dict[str, float]:
    """The real-voice metrics of a checkpoint from `jaxtalk stream`'s computation at 1 sampler step (the
    live path), the correlations by numpy."""
    from jaxtalk.audio import load_audio
    from jaxtalk.commands.inference import SampleOptions, stream_audio
    from jaxtalk.metrics.speech_sync import frame_loudness, lagged_correlation, voice_activity
    from jaxtalk.runs import load_run

    run = load_run(run_dir, best=best)
    corr, loud, lags, silence = [], [], [], []
    for path in sorted(p for p in folder.iterdir() if p.suffix in (".wav", ".flac")):
        audio = load_audio(path)
        motion = stream_audio(run, audio, SampleOptions(run_dir, path, sample_steps=1, best=best), echo=lambda s: None)
        tracked = jaws.get(path.stem)
        n = motion.shape[0] if tracked is None else min(motion.shape[0], tracked.shape[0])
        jaw = motion[:n, 50].astype(np.float64)
        db = frame_loudness(audio, 16000, n)
        silence.append(jaw[~voice_activity(db)].mean())
        if tracked is not None:
            corr.append(np.corrcoef(jaw, tracked[:n])[0, 1])
            loud.append(np.corrcoef(db, tracked[:n])[0, 1])
            lag, r = lagged_correlation(jaw, tracked[:n], 8)
            lags.append(lag[np.nanargmax(r)])
    rest = np.percentile(np.asarray(run.default_style())[:, 50], 5)
    return {"real_corr": np.mean(corr), "real_loudness_corr": np.mean(loud), "real_best_lag": np.mean(lags),
            "real_silence_minus_rest": np.mean(silence) - rest, "step": run.step}


@pytest.mark.slow
def test_logged_real_voice_metrics_equal_a_hand_computation_from_jaxtalk_stream(trained):
    from jaxtalk.train import read_history, read_metrics

    assert "real voices: each evaluation streams 3 recordings of" in trained["output"]
    assert "(2 with tracked motion) at 1 sampler step in the run's default style" in trained["output"]
    evals = {h["step"]: h["eval"] for h in read_history(trained["dir"] / "checkpoint") if h.get("type") == "eval"}
    assert sorted(evals) == list(range(1, STEPS + 1))
    metrics = {r["step"]: r for r in read_metrics(trained["dir"])}
    names = ("real_corr", "real_loudness_corr", "real_best_lag", "real_silence_minus_rest")
    for step, values in evals.items():  # every evaluation, in the history and in metrics.jsonl
        assert all(np.isfinite(values[k]) and metrics[step][f"eval/{k}"] == values[k] for k in names)
        assert "LVE_mm2" in values  # beside the streamed validation of SynthTalk clips
    # The last evaluation's parameters are the latest checkpoint's.
    hand = _by_hand(trained["dir"], trained["voices"], trained["jaws"])
    assert hand["step"] == STEPS
    for k in names:
        assert evals[STEPS][k] == pytest.approx(hand[k], abs=1e-5), k
    # The loudness follower does not depend on the model: the same at every evaluation.
    assert len({round(v["real_loudness_corr"], 12) for v in evals.values()}) == 1


@pytest.mark.slow
def test_select_real_corr_keeps_the_evaluation_of_the_highest_real_corr(trained):
    from jaxtalk.train import read_best, read_history

    evals = {h["step"]: h["eval"] for h in read_history(trained["dir"] / "checkpoint") if h.get("type") == "eval"}
    corr = {step: values["real_corr"] for step, values in evals.items()}
    assert len(set(corr.values())) == STEPS  # the evaluations differ, so the choice means something
    record = read_best(trained["dir"] / "checkpoint")
    assert (record["metric"], record["mode"]) == ("real_corr", "max")
    assert record["step"] == max(corr, key=corr.get) and record["value"] == corr[record["step"]]
    # The best checkpoint streams to the value it was chosen by.
    hand = _by_hand(trained["dir"], trained["voices"], trained["jaws"], best=True)
    assert hand["step"] == record["step"] and hand["real_corr"] == pytest.approx(record["value"], abs=1e-5)


@pytest.mark.slow
def test_real_voice_and_select_user_errors_are_one_line(trained, prepared_tiny, tmp_path):
    out = tmp_path / "run"

    def refused(*more, words):
        cli_error(_train_args(prepared_tiny, out, *more), *words)
        assert not out.exists()  # refused before the run folder is made

    refused("--real-voice", tmp_path / "nowhere", words=["--real-voice folder not found"])
    (tmp_path / "empty").mkdir()
    refused("--real-voice", tmp_path / "empty", words=["is empty"])
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("no audio here")
    refused("--real-voice", tmp_path / "notes", words=["has no audio file", "readme.txt"])
    bad = tmp_path / "bad"
    shutil.copytree(trained["voices"], bad)
    pose = np.zeros((60, 6), np.float32)
    pose[7, 3] = np.nan
    np.savez(bad / "b.npz", pose=pose)
    refused("--real-voice", bad, words=["b.npz': pose contains 1 NaN"])
    refused("--select", "real_corr", words=["--select real_corr", "add --real-voice FOLDER"])
    untracked = tmp_path / "untracked"
    untracked.mkdir()
    shutil.copy(trained["voices"] / "c.wav", untracked / "c.wav")
    refused("--real-voice", untracked, "--select", "real_corr", words=["none of the recordings", "STEM.npz",
                                                                       "select LVE_mm2"])
    refused("--select", "MVE_mm", words=["--select MVE_mm", "choose one of LVE_mm2, real_corr"])
    cli_error(["train", "timar", "--out", out, "--real-voice", trained["voices"]], "--real-voice: TokTalk settings")
    assert not out.exists()
    # A run that selects by real_corr resumes with its recordings only.
    resumed = tmp_path / "resumed"
    shutil.copytree(trained["dir"], resumed)
    cli_error(_train_args(prepared_tiny, resumed, steps=STEPS + 1), "selects its best checkpoint by real_corr",
              "resume it with --real-voice FOLDER")
