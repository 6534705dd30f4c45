"""The DualTalk baseline: window shapes, that it reads the future (it is offline by design), no
agent-motion input, the progressive-context predictions, the loss (by hand and against finite
differences), input errors, presets, and a short run of its recipe through ``jaxtalk train dualtalk``
on SynthTalk tiny (the loss falls) that ``jaxtalk eval`` scores and ``jaxtalk sample`` refuses.
"""

from __future__ import annotations

import dataclasses
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from jaxtalk.models.dualtalk import (
    DualTalkConfig,
    apply,
    loss,
    init_params,
    predict_turns,
    predict_window,
)
from jaxtalk.models.dualtalk.loss import regression_loss

# One small graph for every test (compile time dominates): it also trains on prepared SynthTalk (80-d
# log-mel, 25-frame turns) in 2-turn windows, and the CLI builds the same config from CLI_SET, so the
# module compiles each program once.
CFG = DualTalkConfig.small(width=16, num_layers=1, num_heads=2, lstm_layers=1, max_turns=2)
CLI_SET = ["--set", "width=16", "--set", "num_layers=1", "--set", "num_heads=2", "--set", "lstm_layers=1",
           "--set", "max_turns=2", "--set", "batch_size=2"]
B, N, F = 2, 2, 25



@pytest.fixture(scope="module")
def params():
    return init_params(CFG, jax.random.key(0))


def _streams(seed=0, n=N):
    rng = np.random.default_rng(seed)
    t = n * F
    return {
        "user_speech": rng.normal(size=(B, t, CFG.speech_dim)).astype(np.float32),
        "user_motion": rng.normal(size=(B, t, 56)).astype(np.float32),
        "agent_speech": rng.normal(size=(B, t, CFG.speech_dim)).astype(np.float32),
    }


def _inputs(s):
    return s["user_speech"], s["user_motion"], s["agent_speech"]


def test_window_gives_one_56d_frame_per_input_frame_deterministically(params):
    s = _streams()
    out = np.asarray(predict_window(params, CFG, *_inputs(s)))
    assert out.shape == (B, N * F, 56) and np.isfinite(out).all()
    # A regression model: no key, the same output twice.
    np.testing.assert_array_equal(out, np.asarray(predict_window(params, CFG, *_inputs(s))))


@pytest.mark.parametrize("stream", ["user_speech", "user_motion", "agent_speech"])
def test_changing_the_last_turn_changes_the_first_turns_output_the_baseline_reads_the_future(params, stream):
    s = _streams()
    changed = {k: v.copy() for k, v in s.items()}
    changed[stream][:, -F:] += 1.0
    before = np.asarray(predict_window(params, CFG, *_inputs(s)))[:, :F]
    after = np.asarray(predict_window(params, CFG, *_inputs(changed)))[:, :F]
    assert np.abs(after - before).max() > 1e-4


def test_there_is_no_agent_motion_input():
    for fn in (apply, predict_window, predict_turns):
        names = list(inspect.signature(fn).parameters)
        assert "agent_motion" not in names
        assert names[:5] == ["params", "config", "user_speech", "user_motion", "agent_speech"]
    with pytest.raises(TypeError, match="agent_motion"):
        apply({}, CFG, *_inputs(_streams()), agent_motion=np.zeros((B, N * F, 56), np.float32))


def test_predict_turns_keeps_turn_t_of_the_window_ending_at_t(params):
    # 3 turns, longer than the 2-turn windows: turn 0 alone, then windows [0, 1] and [1, 2].
    s = _streams(n=3)
    out = predict_turns(params, CFG, *_inputs(s), context=1)
    assert out.shape == (B, 3 * F, 56) and out.dtype == np.float32
    for t in range(3):
        lo = max(0, t - 1) * F
        window = [x[:, lo:(t + 1) * F] for x in _inputs(s)]
        want = np.asarray(predict_window(params, CFG, *window))[:, -F:]
        np.testing.assert_allclose(out[:, t * F:(t + 1) * F], want, rtol=1e-5, atol=1e-5)


def test_regression_loss_is_group_mse_plus_velocity_mse():
    rng = np.random.default_rng(0)
    target = rng.normal(size=(2, 6, 56)).astype(np.float32)
    # A constant offset: no velocity error; each group's MSE is the offset squared.
    loss, m = regression_loss(jnp.asarray(target + 0.5), jnp.asarray(target), 1.0)
    assert float(loss) == pytest.approx(3 * 0.25, rel=1e-5) and float(m["loss_velocity"]) == pytest.approx(0.0, abs=1e-9)
    # Noise on one frame: velocity error on the two differences next to it, weighted.
    pred = target.copy()
    pred[:, 2, :] += 1.0
    loss, m = regression_loss(jnp.asarray(pred), jnp.asarray(target), 2.0)
    groups = (1 / 6) * 3  # every group's MSE: one frame in six is off by 1
    velocity = 2 / 5  # two of the five differences are off by 1 in every channel
    assert float(m["loss_velocity"]) == pytest.approx(velocity, rel=1e-5)
    assert float(loss) == pytest.approx(groups + 2.0 * velocity, rel=1e-5)


@pytest.mark.slow
def test_loss_gradient_matches_central_finite_differences_in_float64(params, float64):
    from jax.flatten_util import ravel_pytree

    # The parameters as one float64 vector: the direction and the shifts are host arithmetic, and one
    # compiled program gives the gradient and the values for the finite differences.
    flat, unravel = ravel_pytree(jax.tree.map(lambda x: np.asarray(x, np.float64), params))
    rng = np.random.default_rng(1)
    batch = {k: np.asarray(v, np.float64) for k, v in _streams(n=1).items()}
    batch["agent_motion"] = rng.normal(size=(B, F, 56))
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda x: loss(unravel(x), CFG, batch, jax.random.key(0))[0]))
    grad = np.asarray(value_and_grad(flat)[1])
    # Every parameter moves, by a random amount, the way its gradient says raises the loss: a parameter
    # whose gradient were missing or of the wrong sign would still move and break the match. The shared
    # attention forms its logits in float32 even under x64, which leaves ~1e-5 relative noise in any
    # directional derivative: a direction this close to the gradient keeps the signal far above it.
    d = np.where(grad >= 0, 1.0, -1.0) * np.abs(rng.normal(size=grad.shape))
    d /= np.linalg.norm(d)
    eps = 1e-3
    numeric = (float(value_and_grad(flat + eps * d)[0]) - float(value_and_grad(flat - eps * d)[0])) / (2 * eps)
    analytic = float(grad @ d)
    assert analytic > 1.0 and numeric == pytest.approx(analytic, rel=1e-3)


def test_bad_inputs_and_settings_raise_clear_value_errors(params):
    s = _streams()
    us, um, as_ = _inputs(s)
    cases = [
        ((us[..., :4], um, as_), "user_speech must have 80 channels"),
        ((us, um[..., :50], as_), "user_motion must have 56 channels"),
        ((us[:, :-1], um[:, :-1], as_[:, :-1]), "not a positive multiple of frames_per_turn=25"),
        ((us, um, as_[:, :-F]), "all streams must be aligned"),
        ((np.where(np.arange(N * F)[None, :, None] == 3, np.nan, us), um, as_), "user_speech contains NaN"),
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            predict_window(params, CFG, *args)
        with pytest.raises(ValueError, match=message):
            apply(params, CFG, *args)
    long = _inputs(_streams(n=3))
    with pytest.raises(ValueError, match="3 turns exceed .* max_turns=2"):
        predict_window(params, CFG, *long)
    for context in (-1, 2):
        with pytest.raises(ValueError, match=r"context must be an integer in \[0, max_turns - 1 = 1\]"):
            predict_turns(params, CFG, *long, context=context)
    with pytest.raises(ValueError, match="batch is missing streams"):
        loss(params, CFG, s, jax.random.key(0))
    with pytest.raises(ValueError, match="agent_motion must have 56 channels"):
        loss(params, CFG, {**s, "agent_motion": um[..., :3]}, jax.random.key(0))
    for field, value, message in [("width", 18, "multiple of 4"), ("num_heads", 3, "not divisible by num_heads"),
                                  ("param_dim", 50, "must be 56"), ("max_turns", 0, "positive integer"),
                                  ("feature_dropout", 1.0, r"in \[0, 1\)"), ("velocity_weight", -1.0, ">= 0")]:
        with pytest.raises(ValueError, match=message):
            DualTalkConfig.small(**{field: value})


def test_presets_small_matches_timar_small_budget_and_paper_has_dualtalk_sizes():
    from jaxtalk.models.timar import TimarConfig

    small, paper, timar = DualTalkConfig.small(), DualTalkConfig.paper(), TimarConfig.small()
    assert (small.width, small.num_layers, small.num_heads, small.speech_dim) == (
        timar.width, timar.num_layers, timar.num_heads, timar.speech_dim)
    assert (paper.feature_width, paper.width, paper.num_layers, paper.num_heads, paper.mlp_ratio * paper.width) == (
        256, 512, 3, 4, 2048)
    assert (paper.decoder_layers, paper.lstm_layers, paper.dropout, paper.feature_dropout, paper.speech_dim) == (
        1, 2, 0.1, 0.5, 1024)
    assert paper.max_turns * paper.frames_per_turn == 200  # DualTalk's 8-s training clips
    assert hash(small) == hash(DualTalkConfig.small())  # jit-static


@pytest.mark.slow
def test_jaxtalk_train_dualtalk_lowers_the_loss_on_timar_windows_then_eval_scores_it_and_sample_refuses(
        prepared_tiny, tmp_path):
    # One run through the CLI, which trains with the recipe (jaxtalk.models.dualtalk.recipe.train): a
    # second, direct recipe run would compile the same training step again.
    from jaxtalk.cli import app
    from jaxtalk.runs import RunRecord, checkpoint_dir
    from jaxtalk.models.timar import TimarConfig
    from jaxtalk.models.timar.recipe import fit_data_normalizer, make_windows
    from jaxtalk.train import read_history

    data = prepared_tiny
    windows = len(make_windows(TimarConfig.small(max_turns=2), data).table(data, "train"))
    runner = CliRunner()
    out = tmp_path / "dualtalk"
    result = runner.invoke(app, ["train", "dualtalk", "--data", "synthtalk:tiny", "--cache-dir", str(data.root.parent),
                                 "--steps", "20", *CLI_SET, "--set", "lr=3e-3", "--set", "warmup_steps=0",
                                 "--set", "eval_every=10",
                                 "--no-progress", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"dualtalk: step 0 -> 20 on {windows} windows" in result.output  # TIMAR's windows
    record = RunRecord.load(out)
    assert record.model == "dualtalk" and record.config == dataclasses.asdict(CFG)  # speech_dim from the data
    assert record.extra["normalizer"] == fit_data_normalizer(data).to_dict() and record.extra["num_turns"] == 2
    history = read_history(checkpoint_dir(out))
    train = [row["loss"] for row in history if row["type"] == "train"]
    val = [row["eval"]["val_loss"] for row in history if row["type"] == "eval"]
    assert train[-1] < 0.8 * train[0], train  # window means: the first steps against the last
    # Scored on the validation split too (other speakers than the one training conversation of tiny).
    assert len(val) == 2 and np.isfinite(val).all()

    result = runner.invoke(app, ["eval", str(out), "--max-clips", "1"])
    assert result.exit_code == 0, result.output
    for group in ("exp", "jaw", "pose"):
        assert f"DualTalk baseline on test (synthtalk-tiny-seed0), {group}" in result.output
    assert "dualtalk (turn windows)" in result.output and "mean pose" in result.output
    result = runner.invoke(app, ["sample", str(out), str(tmp_path / "speech.wav")])
    assert result.exit_code == 2 and "is a DualTalk baseline run" in result.output and "Traceback" not in result.output
