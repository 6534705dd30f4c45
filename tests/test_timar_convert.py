"""The public TIMAR code's checkpoints in jaxtalk: conversion, parity with stored reference numbers, bad input.

The fixtures under ``tests/data/timar_reference/`` come from one run of
``experiments/timar_reference_parity.py --save-fixture`` (the public code at width 32, 2 blocks,
4 heads, 3-turn tables, random weights, a random small wav2vec 2.0): its inputs, its state dict and
its outputs at every stage. The tests convert the stored state dict and check jaxtalk against the
stored numbers without torch.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helpers import encoder_folder

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.convert import (
    TORCH_HINT,
    convert_state_dict,
    infer_config,
    read_stats,
    write_converted_run,
)
from jaxtalk.models.timar.data import Normalizer

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "data" / "timar_reference"
FIXTURE_NAMES = ("enc_w32_d2_s0.npz", "encdec_w32_d2_s0.npz")


def _parity_module():
    spec = importlib.util.spec_from_file_location("timar_reference_parity", ROOT / "experiments" / "timar_reference_parity.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def parity():
    return _parity_module()


@pytest.fixture(scope="module", params=FIXTURE_NAMES)
def reference(request, parity):
    return parity.load_reference(FIXTURES / request.param)


def test_fixtures_are_small():
    sizes = [(FIXTURES / n).stat().st_size for n in FIXTURE_NAMES]
    assert all(s < 3_000_000 for s in sizes), sizes


def test_every_stage_matches_the_reference(parity, reference):
    args, state, outs = reference
    rows = parity.differences(parity.jaxtalk_stages(args, state, outs))
    speech = ["turn speech"] if importlib.util.find_spec("safetensors") is not None else []
    assert [r[0] for r in rows] == ["tokens", "encoder", "condition", "head", "mean", "step std", *speech,
                                    "sample turn 1", "sample turn 2"]
    bad = [(name, rel) for name, _, rel, ok in rows if not ok]
    assert not bad, bad


def test_inferred_config_is_the_reference_layout(reference):
    args, state, _ = reference
    config = infer_config(state, args)
    assert config.width == 32 and config.num_heads == 4 and config.max_turns == 3 and config.speech_dim == 48
    assert config.input_projection and config.norm_after_position and config.motion_encoder_final_relu
    assert config.block_norm_epsilon == 1e-6 and config.guidance_drop == "current_turn" and config.learn_sigma
    if args["use_encoder_only"]:
        assert config.architecture == "encoder" and config.num_layers == 2
    else:
        assert config.architecture == "encoder_decoder" and config.num_layers == config.decoder_layers == 2


def test_a_wrong_layout_is_caught(parity):
    # The comparison is sensitive: jaxtalk's own input order (LayerNorm, then the positional table) or
    # bidirectional attention do not reproduce the reference's encoder.
    args, state, outs = parity.load_reference(FIXTURES / FIXTURE_NAMES[0])
    rows = dict((r[0], r) for r in parity.differences(parity.jaxtalk_stages({**args, "use_causal_attn": False}, state, outs)))
    assert not rows["encoder"][3] and rows["tokens"][3]


def test_reference_preset_and_defaults_unchanged():
    ref = TimarConfig.reference()
    assert (ref.width, ref.num_layers, ref.num_heads, ref.head_blocks, ref.head_width) == (1024, 32, 16, 3, 1024)
    assert ref.sample_steps == 5 and ref.sampler == "ddpm" and ref.cfg_scale == 0.0
    paper = TimarConfig.paper()
    assert paper.num_layers == 16 and not paper.input_projection and paper.guidance_drop == "window"
    assert "32 blocks" in TimarConfig.paper.__doc__
    with pytest.raises(ValueError, match="input_projection"):
        TimarConfig(token_width=64, width=128)


# ---------------------------------------------------------------- bad state dicts: one error naming the key


@pytest.fixture()
def enc_state(parity):
    args, state, _ = parity.load_reference(FIXTURES / FIXTURE_NAMES[0])
    return args, dict(state)


def test_missing_key_is_named(enc_state):
    args, state = enc_state
    del state["encoder_blocks.1.attn.qkv.bias"]
    config = infer_config(state, args)
    with pytest.raises(ValueError, match=r"encoder_blocks\.1\.attn\.qkv\.bias"):
        convert_state_dict(state, config)


def test_extra_key_is_named(enc_state):
    args, state = enc_state
    state["encoder_blocks.0.ls1.gamma"] = np.ones(32, np.float32)
    with pytest.raises(ValueError, match=r"encoder_blocks\.0\.ls1\.gamma"):
        convert_state_dict(state, infer_config(state, args))


def test_shape_mismatch_is_named(enc_state):
    args, state = enc_state
    state["diffloss.net.res_blocks.2.mlp.0.weight"] = np.zeros((32, 31), np.float32)
    with pytest.raises(ValueError, match=r"diffloss\.net\.res_blocks\.2\.mlp\.0\.weight.*\(32, 31\)"):
        convert_state_dict(state, infer_config(state, args))


def test_nan_weights_are_refused(enc_state):
    args, state = enc_state
    state["z_proj.bias"] = np.full(32, np.nan, np.float32)
    with pytest.raises(ValueError, match=r"'z_proj\.bias' holds NaN"):
        convert_state_dict(state, infer_config(state, args))


def test_other_models_checkpoint_is_refused():
    state = {"audio_encoder.weight": np.zeros((4, 4), np.float32), "decoder.layers.0.weight": np.zeros((4, 4), np.float32)}
    with pytest.raises(ValueError, match=r"'speech_projection\.weight'"):
        infer_config(state, {"model": "timar_large"})


def test_mlp_head_and_unknown_heads_are_refused(enc_state):
    args, state = enc_state
    with pytest.raises(ValueError, match="mlp_head"):
        infer_config({**state, "mlp_head.0.weight": np.zeros((2, 2), np.float32)}, args)
    with pytest.raises(ValueError, match="attention heads"):
        infer_config(state, {**args, "encoder_num_heads": None, "model": "timar_tiny"})


def test_heads_and_layernorm_epsilon_are_read_from_the_args_or_refused(enc_state):
    args, state = enc_state
    with pytest.raises(ValueError, match="norm_eps"):
        infer_config(state, {k: v for k, v in args.items() if k != "norm_eps"})
    assert infer_config(state, {**args, "norm_eps": 1e-5}).block_norm_epsilon == 1e-5
    # A factory's name must describe the tensors: the fixture is 32 wide, timar_large 1024.
    with pytest.raises(ValueError, match="timar_large.*width 1024"):
        infer_config(state, {**args, "model": "timar_large", "encoder_num_heads": None})
    for name, value in (("mask_history_agent", True), ("num_iter", 4), ("l2r_order", True)):
        with pytest.raises(ValueError, match=f"args.{name}"):
            infer_config(state, {**args, name: value})
    assert infer_config(state, {**args, "cfg": 1.0}).cfg_scale == 0.0
    assert infer_config(state, {**args, "cfg": 2.5}).cfg_scale == 1.5


# ---------------------------------------------------------------- statistics file


def _stats(width_exp: int = 50) -> dict:
    return {"exp": {"mean": [0.1] * width_exp, "std": [2.0] * width_exp}, "jawpose": {"mean": [0.0] * 3, "std": [0.5] * 3},
            "neck": {"mean": [0.0] * 3, "std": [0.0] * 3}}


def test_stats_file(tmp_path):
    path = tmp_path / "stat_flame.json"
    path.write_text(json.dumps(_stats()))
    mean, std = read_stats(path)
    assert mean.shape == std.shape == (56,)
    np.testing.assert_allclose(mean[:50], 0.1)
    assert std[53:].min() > 0  # floored at float32 eps, as the public code does


def test_stats_of_the_wrong_width_are_refused(tmp_path):
    path = tmp_path / "stat_flame.json"
    path.write_text(json.dumps(_stats(49)))
    with pytest.raises(ValueError, match=r"stat_flame\.json.*exp\.mean has 49 values"):
        read_stats(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not a JSON statistics file"):
        read_stats(path)


# ---------------------------------------------------------------- the run folder


def test_converted_run_opens_and_streams_like_the_reference(tmp_path, parity):
    from jaxtalk.models.timar.streaming import init_stream, stream_step
    from jaxtalk.runs import load_run

    args, state, outs = parity.load_reference(FIXTURES / FIXTURE_NAMES[0])
    config = infer_config(state, args)
    params = convert_state_dict(state, config)
    ident = Normalizer(np.zeros(48, np.float32), np.ones(48, np.float32), np.zeros(56, np.float32), np.ones(56, np.float32))
    feat_dir = encoder_folder(tmp_path / "w2v")
    out = write_converted_run(tmp_path / "run", config, params, ident, features=f"wav2vec2:{feat_dir}", args=args,
                              source="TIMAR.pth")
    run = load_run(out)
    assert run.config == config and run.record.preset == "reference" and run.record.extra["num_turns"] == 3
    assert json.loads((out / "features.json").read_text())["turn_speech_dim"] == 48
    state_s = init_stream(run.config, jax.random.key(0), batch=1, context=2)
    speech = outs["sample_speech"][0]
    _, y = stream_step(run.params, run.config, state_s, speech[0][None], outs["sample_user_motion"][0][None],
                       speech[1][None], cfg_scale=1.0, sample_steps=5, initial_noise=outs["sample_x_T"][0][None],
                       step_noise=outs["sample_step_noise"][0][:, None])
    np.testing.assert_allclose(np.asarray(y[0]), outs["sample"][0], rtol=0, atol=1e-4 * max(1, np.abs(outs["sample"][0]).max()))
    # a second conversion into the same folder needs --overwrite, and leaves the first intact
    with pytest.raises(ValueError, match="--overwrite"):
        write_converted_run(out, config, params, ident, features=f"wav2vec2:{feat_dir}")
    assert (out / "run.json").is_file()


def test_explicit_noises_are_checked():
    from jaxtalk.models.timar.sampling import sample_frames

    config = TimarConfig.small(width=32, num_heads=4, head_width=32)
    from jaxtalk.models.timar.model import init_params

    params = init_params(config, jax.random.key(0))
    z = jnp.zeros((1, 25, 32))
    with pytest.raises(ValueError, match="initial_noise must have shape"):
        sample_frames(params, config, z, None, jax.random.key(1), cfg_scale=0.0, sample_steps=2, sampler="ddpm",
                      initial_noise=jnp.zeros((1, 24, 56)))
    with pytest.raises(ValueError, match="only used by the 'ddpm' sampler"):
        sample_frames(params, config, z, None, jax.random.key(1), cfg_scale=0.0, sample_steps=2, sampler="ddim",
                      step_noise=jnp.zeros((2, 1, 25, 56)))
    # same noises, same sample; the key is then irrelevant
    x_t = jax.random.normal(jax.random.key(2), (1, 25, 56))
    steps = jax.random.normal(jax.random.key(3), (2, 1, 25, 56))
    a = sample_frames(params, config, z + 1, None, jax.random.key(1), cfg_scale=0.0, sample_steps=2, sampler="ddpm",
                      initial_noise=x_t, step_noise=steps)
    b = sample_frames(params, config, z + 1, None, jax.random.key(9), cfg_scale=0.0, sample_steps=2, sampler="ddpm",
                      initial_noise=x_t, step_noise=steps)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# ---------------------------------------------------------------- the command line


def _has_torch() -> bool:
    return importlib.util.find_spec("torch") is not None


@pytest.mark.skipif(_has_torch(), reason="checks the message shown when torch is missing")
def test_cli_without_torch_is_one_line_and_writes_nothing(tmp_path):
    ckpt = tmp_path / "TIMAR.pth"
    ckpt.write_bytes(b"PK\x03\x04 not really")
    w2v = encoder_folder(tmp_path / "w2v")
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "jaxtalk.cli", "convert", "timar", str(ckpt), "--out", str(out),
                           "--features", f"wav2vec2:{w2v}"], capture_output=True, text=True, cwd=ROOT,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and TORCH_HINT in lines[0], proc.stderr
    assert not out.exists() and not list(tmp_path.glob(".run.*"))


def test_cli_missing_checkpoint_and_bad_features(tmp_path):
    from typer.testing import CliRunner

    from jaxtalk.cli import app

    runner = CliRunner()
    w2v = encoder_folder(tmp_path / "w2v")
    res = runner.invoke(app, ["convert", "timar", str(tmp_path / "nope.pth"), "--out", str(tmp_path / "run"),
                              "--features", f"wav2vec2:{w2v}"])
    assert res.exit_code == 2 and "nope.pth" in res.output
    ckpt = tmp_path / "TIMAR.pth"
    ckpt.write_bytes(b"x")
    res = runner.invoke(app, ["convert", "timar", str(ckpt), "--out", str(tmp_path / "run"), "--features", "wav2vec2:"])
    assert res.exit_code == 2 and "wav2vec2" in res.output
    assert not (tmp_path / "run").exists()


torch_only = pytest.mark.skipif(not _has_torch(), reason="needs torch (pip install 'jaxtalk[torch]')")


@torch_only
def test_checkpoint_round_trip_and_truncated_file(tmp_path, parity):  # pragma: no cover - runs where torch is installed
    import argparse

    import torch

    from jaxtalk.models.timar.convert import convert_checkpoint

    args, state, _ = parity.load_reference(FIXTURES / FIXTURE_NAMES[0])
    sd = {k: torch.from_numpy(v) for k, v in state.items()}
    ckpt = tmp_path / "TIMAR.pth"
    torch.save({"model": sd, "model_ema": sd, "args": argparse.Namespace(**args), "epoch": 3}, ckpt)
    w2v = encoder_folder(tmp_path / "w2v")
    with pytest.warns(UserWarning, match="identity"):
        result = convert_checkpoint(ckpt, tmp_path / "run", features=f"wav2vec2:{w2v}")
    assert result.config == infer_config(state, args) and result.weights == "ema"
    bad = tmp_path / "bad.pth"
    bad.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    with pytest.raises(ValueError, match="bad.pth.*not a readable PyTorch checkpoint"):
        convert_checkpoint(bad, tmp_path / "run2", features=f"wav2vec2:{w2v}")
    assert not (tmp_path / "run2").exists()
    torch.save({"state_dict": sd}, tmp_path / "other.pth")
    with pytest.raises(ValueError, match="no 'model' state dict"):
        convert_checkpoint(tmp_path / "other.pth", tmp_path / "run3", features=f"wav2vec2:{w2v}")


def test_current_turn_guidance_drop_is_the_same_offline_and_streamed():
    # guidance_drop="current_turn": turn t's unconditional branch drops turn t's user tokens only. The
    # whole-window conditions and the turn-by-turn stream (which keeps the conditional rows' past turns
    # in the unconditional rows' window and key/value cache) must agree, and differ from "window".
    from jaxtalk.models.timar.model import init_params
    from jaxtalk.models.timar.sampling import conditions
    from jaxtalk.models.timar.streaming import init_stream, stream_condition

    config = TimarConfig.reference(width=32, num_layers=2, num_heads=4, speech_dim=8, token_width=24, head_width=32,
                                   max_turns=3, dropout=0.0)
    params = init_params(config, jax.random.key(0))
    rng = np.random.default_rng(0)
    n, f = 3, config.frames_per_turn
    us, as_ = (jnp.asarray(rng.standard_normal((1, n, f, 8)), jnp.float32) for _ in range(2))
    um = jnp.asarray(rng.standard_normal((1, n, f, 56)), jnp.float32)
    z_c, z_u = conditions(params, config, us, um, as_)
    state = init_stream(config, jax.random.key(1), batch=1, context=n - 1)
    rows = []
    for t in range(n):
        state, z = stream_condition(params, config, state, us[:, t], um[:, t], as_[:, t])
        rows.append(np.asarray(z))
    streamed = np.stack(rows, axis=1)  # (2, n, F, w): conditional row, unconditional row
    np.testing.assert_allclose(streamed[0], np.asarray(z_c[0]), atol=2e-5)
    np.testing.assert_allclose(streamed[1], np.asarray(z_u[0]), atol=2e-5)
    import dataclasses

    _, z_window = conditions(params, dataclasses.replace(config, guidance_drop="window"), us, um, as_)
    np.testing.assert_allclose(np.asarray(z_window[0, 0]), np.asarray(z_u[0, 0]), atol=2e-5)  # turn 0: same
    assert np.abs(np.asarray(z_window[0, 2]) - np.asarray(z_u[0, 2])).max() > 1e-3  # later turns: not


def _sha(folder: Path) -> dict[str, str]:
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@torch_only
def test_cli_overwrite_never_replaces_a_folder_holding_its_inputs_or_a_users_files(tmp_path, parity, monkeypatch):
    import argparse

    import torch

    from helpers import cli_error, cli_ok

    args, state, _ = parity.load_reference(FIXTURES / FIXTURE_NAMES[0])
    sd = {k: torch.from_numpy(v) for k, v in state.items()}
    # The README's download step puts the checkpoint and the encoder in ckpts/, beside a user's notes.
    ckpts = tmp_path / "ckpts"
    encoder_folder(ckpts / "w2v")
    torch.save({"model": sd, "model_ema": sd, "args": argparse.Namespace(**args)}, ckpts / "TIMAR.pth")
    (ckpts / "notes.txt").write_text("the user's notes")
    before = _sha(tmp_path)
    base = ["convert", "timar", ckpts / "TIMAR.pth", "--features", f"wav2vec2:{ckpts / 'w2v'}"]
    cli_error([*base, "--out", ckpts, "--overwrite"], "holds", "an input of this command")
    monkeypatch.chdir(ckpts)
    cli_error([*base, "--out", ".", "--overwrite"], "current folder")
    monkeypatch.chdir(tmp_path)
    # A folder of the user's files that holds no input is no previous conversion either.
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    cli_error([*base, "--out", mine, "--overwrite"], "did not write", "notes.txt")
    assert _sha(tmp_path) == {**before, "mine/notes.txt": _sha(mine)["notes.txt"]}
    assert not list(tmp_path.glob(".*replaced-*")) and not list(tmp_path.glob(".*converting-*"))
    # A previous conversion is replaced with --overwrite, and only then.
    cli_ok([*base, "--out", tmp_path / "run"])
    cli_error([*base, "--out", tmp_path / "run"], "--overwrite")
    cli_ok([*base, "--out", tmp_path / "run", "--overwrite"])
    (tmp_path / "run" / "notes.txt").write_text("added by the user")
    cli_error([*base, "--out", tmp_path / "run", "--overwrite"], "did not write", "notes.txt")
    assert (tmp_path / "run" / "notes.txt").read_text() == "added by the user"
