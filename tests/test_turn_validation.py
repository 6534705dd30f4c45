"""TIMAR's and the DualTalk baseline's in-training validation predicts conversation sides as ``jaxtalk eval``
does: with transparent predictors the scores equal a hand computation (the mean pose's MSE per group, the
truth's zero MSE), the model receives the side's normalised streams with the run's context, and the
recipes record the metrics and keep the best checkpoint by FD."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxtalk.models.turns.windows import agent_sides, make_windows
from jaxtalk.models.timar import TimarConfig
from jaxtalk.train.recipes import spread
from jaxtalk.models.turns.training import SELECTION_METRIC, conversation_validation

SMALL = {"width": 32, "num_layers": 1, "num_heads": 2, "head_width": 32, "head_blocks": 1, "max_turns": 2,
         "sample_steps": 2}


@pytest.fixture(scope="module")
def windows(prepared_tiny):
    config = TimarConfig.small(**SMALL, speech_dim=prepared_tiny.manifest["turn_speech_dim"])
    return make_windows(config, prepared_tiny)


def test_mean_pose_and_truth_predictors_score_as_computed_by_hand(windows, prepared_tiny):
    data, norm, f = prepared_tiny, windows.normalizer, windows.config.frames_per_turn
    sides = [agent_sides(data, "val")[int(k)] for k in spread(len(agent_sides(data, "val")), 2)]
    truths = {}
    for i, j in sides:
        agent, user = data.record(i, ("motion",)), data.record(j, ("motion",))
        total = min(agent["motion"].shape[0], user["motion"].shape[0])
        truths[i] = np.asarray(agent["motion"], np.float32)[:total]
    seen = []

    def mean_pose(params, streams, key, context):
        seen.append((streams[0].shape, streams[1].shape, context))
        return np.zeros((1, streams[0].shape[1], 56), np.float32)  # the normaliser's mean, in its units

    scores = conversation_validation(data, windows, "val", predict=mean_pose, key=jax.random.key(0), clips=2)(None, None, 0)
    context = windows.num_turns - 1
    assert [s[2] for s in seen] == [context, context] and all(s[0][1] % f == 0 and s[0][1] == s[1][1] for s in seen)
    for group, sl, scale in (("exp", slice(0, 50), 10.0), ("jaw", slice(50, 53), 1e3), ("pose", slice(53, 56), 1e2)):
        by_hand = np.mean([((gt - norm.motion_mean) ** 2)[:, sl].mean() for gt in truths.values()])
        assert scores[f"MSE_{group}"] == pytest.approx(scale * by_hand, rel=1e-4)
    assert scores[SELECTION_METRIC] == pytest.approx(np.mean([scores[f"FD_{g}"] for g in ("exp", "jaw", "pose")]))

    order = iter(truths.values())

    def truth(params, streams, key, context):  # the agent's true motion over its whole turns
        gt = next(order)
        return norm.motion(gt[: streams[0].shape[1]])[None]

    exact = conversation_validation(data, windows, "val", predict=truth, key=jax.random.key(0), clips=2)(None, None, 0)
    assert exact["MSE_exp"] < 0.05 * scores["MSE_exp"]  # only the frames after the last whole turn differ
    assert exact[SELECTION_METRIC] < scores[SELECTION_METRIC]


def test_zero_clips_gets_no_conversation_validation(windows, prepared_tiny):
    def unused(params, streams, key, context):
        raise AssertionError("nothing is predicted")

    assert conversation_validation(prepared_tiny, windows, "val", predict=unused, key=jax.random.key(0), clips=0) is None


@pytest.mark.slow
@pytest.mark.parametrize("model", ["timar", "dualtalk"])
def test_recipe_records_conversation_metrics_and_keeps_the_best_checkpoint_by_fd(model, prepared_tiny, tmp_path):
    from jaxtalk.runs import REGISTRY, RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig
    from jaxtalk.train.checkpoint import read_best

    spec = REGISTRY[model]
    fields = SMALL if model == "timar" else {"width": 16, "num_layers": 1, "num_heads": 2, "lstm_layers": 1, "max_turns": 2}
    widths = {field: prepared_tiny.manifest[key] for field, key in spec.data_fields}
    config = spec.config_class.small(**fields, **widths)
    run = RunSettings(steps=2, batch_size=2, run_dir=tmp_path / "run", eval_every=1, loop=LoopSettings(progress=False))
    result = spec.train(config, prepared_tiny, OptimConfig(lr=1e-3, warmup_steps=0, total_steps=2),
                        key=jax.random.key(0), run=run, val_clips=1)
    evals = [h for h in result.history if "eval" in h]
    assert len(evals) == 2 and all({"val_loss", "FD", "FD_jaw", "MSE_pose", "rPCC_exp"} <= set(h["eval"]) for h in evals)
    record = read_best(tmp_path / "run" / "checkpoint")
    assert record["metric"] == SELECTION_METRIC
    assert record["value"] == pytest.approx(min(h["eval"][SELECTION_METRIC] for h in evals))


def test_public_scoring_cuts_to_the_whole_seconds_predicted_and_jaxtalk_scoring_repeats_the_tail():
    from jaxtalk.data.batching import fit_length
    from jaxtalk.metrics import conversation_metrics
    from jaxtalk.metrics.evaluation import EvalSettings
    from jaxtalk.models.turns.training import _scored_tables
    from jaxtalk.models.turns.windows import Normalizer

    rng = np.random.default_rng(0)
    pred = rng.normal(size=(50, 56)).astype(np.float32)  # two whole 25-frame turns
    truth = rng.normal(size=(62, 56)).astype(np.float32)  # the side runs 12 frames past them
    partner = rng.normal(size=(62, 56)).astype(np.float32)
    norm = Normalizer(np.zeros(8, np.float32), np.ones(8, np.float32), np.zeros(56, np.float32), np.ones(56, np.float32))
    notes = []

    def fd_exp(scoring):
        (table, *_) = _scored_tables(scoring, "model", [pred], [truth], [partner], [None], norm, notes.append,
                                     "t", named=True)
        assert scoring in table.title
        return table.rows[0]["FD"], table.rows[0]["frames"]

    public, public_frames = fd_exp("public")
    ours, our_frames = fd_exp("jaxtalk")
    cut = conversation_metrics([pred], [truth[:50]], [partner[:50]], scaled=True, sid_convention="fit_gt")
    padded = conversation_metrics([fit_length(pred, 62)], [truth], [partner], scaled=True, sid_convention="fit_gt")
    assert (public, public_frames) == (pytest.approx(cut["FD_exp"]), 50)
    assert (ours, our_frames) == (pytest.approx(padded["FD_exp"]), 62)
    assert abs(public - ours) > 1e-3
    with pytest.raises(ValueError, match="scoring must name"):
        EvalSettings(scoring=("calc_metric",))
