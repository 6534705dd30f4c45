"""``jaxtalk train / sample / stream`` end to end on a tiny TokTalk trained for a few steps.

One run serves every test: the session's two-step tiny TokTalk (``trained_toktalk``), copied and resumed
to 4 steps. The CLI's outputs are checked against the library called directly with the same inputs, so a
wiring mistake (wrong style clip, wrong key, dropped frames, normalisation applied twice) fails here.
"""

from __future__ import annotations


import jax
import numpy as np
import pytest
import soundfile as sf

from helpers import cli_ok as _ok, cli_error as _user_error


COMMANDS = ["data", "prepare", "demo", "train", "sample", "stream", "eval", "bench", "render", "export", "view", "convert"]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command):
    output = _ok([command, "--help"])
    assert "Usage" in output and command in output



@pytest.fixture(scope="module")
def run(tmp_path_factory, synthtalk_tiny, prepared_tiny, trained_toktalk):
    """The session's two-step tiny TokTalk (``trained_toktalk``), copied and resumed to 4 steps (the
    resume is a test of its own)."""
    root = tmp_path_factory.mktemp("cli_run")
    out = trained_toktalk.copy(root / "run")
    second = _ok(["train", "toktalk", "--steps", "4", "--no-progress", "--out", str(out)])
    return {"dir": out, "root": root, "first": trained_toktalk.output, "second": second, "corpus": synthtalk_tiny,
            "data": prepared_tiny}


@pytest.mark.slow
def test_train_writes_run_and_resume_continues_the_step_count(run):
    from jaxtalk.runs import RunRecord, load_run
    from jaxtalk.train import Checkpointer, latest_checkpoint_step

    assert "step 0 -> 2" in run["first"]
    assert "resuming toktalk (tiny) from step 2 to 4" in run["second"] and "step 2 -> 4" in run["second"]
    assert latest_checkpoint_step(run["dir"] / "checkpoint") == 4
    with Checkpointer(run["dir"] / "checkpoint", read_only=True) as ckpt:
        assert {2, 4} <= set(ckpt.all_steps())
    record = RunRecord.load(run["dir"])
    assert record.model == "toktalk" and record.preset == "tiny" and record.train["batch_size"] == 2
    assert record.data["spec"] == "synthtalk:tiny" and record.data["key"] == run["data"].key
    assert record.model_config().chunk_frames == 4  # the tiny preset, restored from run.json
    at2, at4 = load_run(run["dir"], step=2), load_run(run["dir"])
    assert (at2.step, at4.step) == (2, 4)
    moved = jax.tree.map(lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b)))), at2.params, at4.params)
    assert max(jax.tree.leaves(moved)) > 0  # the resumed steps trained


@pytest.mark.slow
def test_train_user_errors_are_one_line(run, tmp_path):
    out = str(tmp_path / "fresh")
    _user_error(["train", "toktalk", "--set", "nonsense=1", "--out", out], "nonsense: neither a TokTalkConfig field")
    _user_error(["train", "toktalk", "--set", "sample_steps=many", "--out", out], "expected int")
    _user_error(["train", "toktalk", "--set", "chunk_frames=5", "--out", out], "chunk_frames=5 must be even")
    _user_error(["train", "toktalk", "--set", "channels", "--out", out], "expects key=value")
    _user_error(["train", "toktalk", "--preset", "huge", "--out", out], "no preset 'huge'")
    _user_error(["train", "waveglow", "--out", out], "unknown model 'waveglow'")
    _user_error(["train", "timar", "--out", str(run["dir"])], "holds a toktalk run")
    _user_error(["train", "toktalk", "--set", "sample_steps=5", "--out", str(run["dir"]), "--steps", "5"],
                "resume it with the same settings")
    _user_error(["train", "toktalk", "--set", "lr=fast", "--out", out], "expected float")
    _user_error(["train", "toktalk", "--set", "speed=3", "--out", out], "neither a TokTalkConfig field nor a training setting")
    _user_error(["train", "toktalk", "--data", str(tmp_path / "nowhere"), "--out", out], "is not a prepared dataset")
    _user_error(["train", "toktalk", "--steps", "3", "--out", str(run["dir"])], "already at step 4 > --steps 3")


def test_parse_overrides_types_values_by_field():
    from jaxtalk.runs import build_config, parse_overrides
    from jaxtalk.models.timar import TimarConfig
    from jaxtalk.train import OptimConfig

    got = parse_overrides(TimarConfig, ["width=64", "cfg_scale=2.5", "learn_sigma=yes", "head=mlp"])
    assert got == {"width": 64, "cfg_scale": 2.5, "learn_sigma": True, "head": "mlp"}
    assert parse_overrides(OptimConfig, ["ema_decay=none", "clip_norm=0.5"]) == {"ema_decay": None, "clip_norm": 0.5}
    config = build_config("timar", "small", ["num_layers=2", "num_layers=3"])  # the last one wins
    assert config.num_layers == 3 and config.width == TimarConfig.small().width


def _tokens(run, n: int = 20) -> tuple[np.ndarray, object]:
    corpus = run["corpus"]
    clip = corpus.split("test")[0]
    return np.asarray(corpus.tokens(clip, "A").embeddings, np.float32)[:n], corpus


def _default_style(loaded, corpus) -> np.ndarray:
    # The CLI's documented default: the longest training clip's first 4 x style_frames frames, saved
    # with the run (so sampling needs no dataset).
    train = corpus.split("train")
    longest = max(train, key=lambda i: corpus.clips[i].num_frames)
    want = np.asarray(corpus.motion(longest), np.float32)[: 4 * loaded.config.style_frames]
    np.testing.assert_array_equal(loaded.default_style(), want)
    return want[None]


@pytest.mark.slow
def test_sample_tokens_equals_the_library_call(run, tmp_path):
    from jaxtalk.runs import load_run
    from jaxtalk.data.formats import read_npz
    from jaxtalk.models import toktalk

    tokens, corpus = _tokens(run)
    np.save(tmp_path / "tokens.npy", tokens)
    out = tmp_path / "sampled.npz"
    _ok(["sample", str(run["dir"]), str(tmp_path / "tokens.npy"), "--out", str(out), "--seed", "3"])
    clip = read_npz(out)
    loaded = load_run(run["dir"])
    want = toktalk.sample(loaded.params, loaded.config, tokens[None], _default_style(loaded, corpus), jax.random.key(3))
    assert clip.fps == 25 and clip.params.shape == (2 * tokens.shape[0], 56)  # 12.5 Hz tokens -> 25 fps
    np.testing.assert_allclose(clip.params, np.asarray(want)[0], rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_stream_prints_each_chunk_and_equals_the_streaming_engine(run, tmp_path):
    from jaxtalk.runs import load_run
    from jaxtalk.data.formats import read_npz
    from jaxtalk.models import toktalk

    tokens, corpus = _tokens(run, 19)  # not a whole number of chunks: the last one is padded and cropped
    np.save(tmp_path / "tokens.npy", tokens)
    out = tmp_path / "streamed.npz"
    output = _ok(["stream", str(run["dir"]), str(tmp_path / "tokens.npy"), "--out", str(out)])
    loaded = load_run(run["dir"])
    chunks = -(-tokens.shape[0] // toktalk.tokens_per_chunk(loaded.config))
    lines = [line for line in output.splitlines() if line.startswith("chunk")]
    assert len(lines) == chunks and lines[-1].startswith(f"chunk {chunks:3d}/{chunks}")
    assert all(" ms for " in line for line in lines) and "median" in output
    style_vec = toktalk.encode_style(loaded.params, loaded.config, _default_style(loaded, corpus))
    want = toktalk.stream(loaded.params, loaded.config, tokens[None], style_vec, jax.random.key(0))
    got = read_npz(out).params
    assert got.shape == (2 * tokens.shape[0], 56)
    np.testing.assert_allclose(got, np.asarray(want)[0], rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_sample_stereo_audio_at_another_rate(run, tmp_path):
    from jaxtalk.audio import resample_audio
    from jaxtalk.data.formats import read_npz

    corpus = run["corpus"]
    audio = np.asarray(corpus.audio(corpus.split("test")[0]), np.float32)[: 16000 * 3 // 2]  # 1.5 s
    stereo = np.stack([resample_audio(audio, 16000, 22050)] * 2, axis=1)
    sf.write(tmp_path / "speech.wav", stereo, 22050)
    _ok(["sample", str(run["dir"]), str(tmp_path / "speech.wav")])
    clip = read_npz(tmp_path / "speech_params.npz")  # the default output name
    assert clip.params.shape == (round(1.5 * 25), 56) and np.isfinite(clip.params).all()
    assert clip.audio is not None and abs(clip.audio.shape[0] - audio.shape[0]) <= 2  # 16 kHz mono, stored


@pytest.mark.slow
def test_sample_user_errors(run, tmp_path):
    run_dir = str(run["dir"])
    _user_error(["sample", run_dir, str(tmp_path / "missing.wav")], "input file not found")
    (tmp_path / "notes.txt").write_text("hello")
    _user_error(["sample", run_dir, str(tmp_path / "notes.txt")], "expected an audio file")
    np.save(tmp_path / "wide.npy", np.zeros((10, 7), np.float32))
    _user_error(["sample", run_dir, str(tmp_path / "wide.npy")], "must have shape (tokens, 64)")
    bad = np.zeros((10, 64), np.float32)
    bad[3, 3] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    _user_error(["stream", run_dir, str(tmp_path / "nan.npy")], "NaN")
    _user_error(["sample", str(tmp_path), str(tmp_path / "wide.npy")], "is not a training run")


def test_a_toktalk_run_recorded_before_noise_frames_existed_keeps_white_noise(tmp_path):
    import dataclasses

    from jaxtalk.runs import RunRecord
    from jaxtalk.models.toktalk import TokTalkConfig

    config = dataclasses.asdict(TokTalkConfig.tiny())
    old = {k: v for k, v in config.items() if k != "noise_frames"}
    record = RunRecord(model="toktalk", preset="tiny", items=[], config=old, train={}, optim={}, data={}, seed=0,
                       extra={})
    record.save(tmp_path / "old")
    assert RunRecord.load(tmp_path / "old").model_config().noise_frames == 0.0
    RunRecord(**{**dataclasses.asdict(record), "config": config}).save(tmp_path / "new")
    assert RunRecord.load(tmp_path / "new").model_config().noise_frames == 2.0


def test_a_timar_run_of_format_one_reads_its_guidance_omega_as_todays_weight(tmp_path):
    import dataclasses
    import json

    from jaxtalk.models.timar import TimarConfig
    from jaxtalk.runs import RUN_FORMAT, RunRecord

    # Format 1 stored the paper's omega (u + omega (c - u)); today's cfg_scale is w = omega - 1.
    config = {**dataclasses.asdict(TimarConfig.small()), "cfg_scale": 2.5}
    raw = dict(model="timar", preset="small", items=["cfg_scale=2.5", "width=64"], config=config, train={},
               optim={}, data={}, seed=0, extra={})
    (tmp_path / "run.json").write_text(json.dumps(raw))
    record = RunRecord.load(tmp_path)
    assert record.format == RUN_FORMAT == 2
    assert record.model_config().cfg_scale == 1.5 and record.items == ["cfg_scale=1.5", "width=64"]
    # A record of today's format is read as written, and saving keeps the format.
    record.save(tmp_path)
    assert RunRecord.load(tmp_path).model_config().cfg_scale == 1.5
    assert json.loads((tmp_path / "run.json").read_text())["format"] == 2


@pytest.mark.slow
def test_a_run_written_before_the_one_vocabulary_renames_samples_and_resumes(run, tmp_path):
    import json
    import shutil

    from jaxtalk.runs import RENAMED_FIELDS, RunRecord

    # The run as an older jaxtalk wrote it: TokTalk's fields under their old names, in the config and
    # in the --set items.
    old_dir = tmp_path / "old"
    shutil.copytree(run["dir"], old_dir)
    raw = json.loads((old_dir / "run.json").read_text())
    back = {new: old for old, new in RENAMED_FIELDS["toktalk"].items()}
    raw["config"] = {back.get(k, k): v for k, v in raw["config"].items()}
    raw["items"] = [*raw["items"], "num_steps=3"]
    assert {"token_dim", "channels", "num_steps", "cond_dropout"} <= set(raw["config"])
    (old_dir / "run.json").write_text(json.dumps(raw))

    record = RunRecord.load(old_dir)
    config = record.model_config()
    assert (config.speech_dim, config.width) == (raw["config"]["token_dim"], raw["config"]["channels"])
    assert record.items[-1] == "sample_steps=3"
    wav = tmp_path / "a.wav"
    sf.write(wav, (0.2 * np.sin(np.arange(32_000) / 5)).astype(np.float32), 16_000)
    _ok(["sample", str(old_dir), str(wav), "--out", str(tmp_path / "a.npz"), "--sample-steps", "2"])
    assert np.load(tmp_path / "a.npz")["params"].shape[1] == 56
