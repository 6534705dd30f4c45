"""TokTalk's in-training validation samples the model as users do: the streamed clips' LVE, MVE and
jitter on the built-in face equal a hand computation, repeat exactly at every evaluation, reach the run's
metrics, and choose the best checkpoint (lowest streamed LVE)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from jaxtalk.face import builtin_face
from jaxtalk.metrics import jitter, lve, mve
from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.sampling import default_grid
from jaxtalk.models.toktalk.validation import SELECTION_METRIC, streamed_validation



@pytest.fixture(scope="module")
def config(prepared_tiny):
    m = prepared_tiny.manifest
    return tt.TokTalkConfig.tiny(num_mid_blocks=0, speech_dim=m["token_dim"], token_rate=float(m["token_rate"]))


@pytest.mark.slow
def test_streamed_validation_equals_a_hand_computation_and_repeats_exactly(config, prepared_tiny):
    data = prepared_tiny
    params = tt.init_params(config, jax.random.key(0))
    params["norm"] = {k: np.asarray(v) for k, v in data.motion_stats().items()}
    key = jax.random.key(3)
    eval_fn = streamed_validation(config, data, "val", key=key, clips=1, step_counts=(1, 2))
    first = eval_fn(params, None, 0)
    assert set(first) == {SELECTION_METRIC} | {f"{m}_{n}step" for m in ("LVE_mm2", "MVE_mm", "jitter_mm") for n in (1, 2)}
    assert eval_fn(params, None, 10) == first  # the same clips, keys and grids at every evaluation

    # By hand: the first val clip with tokens, styled by another clip of its speaker.
    clips = [i for i in data.split("val") if data.clips[i]["tokens"]]
    i = clips[0]
    rec = data.record(i, ("motion", "tokens"))
    others = [j for j in data.split("val") if j != i and data.clips[j]["speaker"] == data.clips[i]["speaker"]]
    style = data.record(others[0], ("motion",))["motion"] if others else rec["motion"]
    style_vec = tt.encode_style(params, config, np.asarray(style, np.float32)[None, : 4 * config.style_frames])
    t = min(2 * rec["tokens"].shape[0], rec["motion"].shape[0])
    face = builtin_face(0)
    gt = np.asarray(face.vertices_seq(np.asarray(rec["motion"], np.float32)[:t]))
    lves = []
    for n in (1, 2):
        out = tt.stream(params, config, np.asarray(rec["tokens"], np.float32)[None], style_vec,
                        jax.random.fold_in(key, 0), ts=default_grid(config, n))
        v = np.asarray(face.vertices_seq(np.asarray(out)[0][:t]))
        lves.append(float(lve(v, gt, face.regions["lips"])) * 1e6)
        assert first[f"LVE_mm2_{n}step"] == pytest.approx(lves[-1], rel=1e-5)
        assert first[f"MVE_mm_{n}step"] == pytest.approx(float(mve(v, gt)) * 1e3, rel=1e-5)
        assert first[f"jitter_mm_{n}step"] == pytest.approx(float(jitter(v)) * 1e3, rel=1e-5)
    assert first[SELECTION_METRIC] == pytest.approx(np.mean(lves), rel=1e-6)
    # The EMA parameters are the ones scored when the run keeps them.
    zero = jax.tree.map(np.zeros_like, params)
    zero["norm"] = params["norm"]
    assert eval_fn(zero, params, 0) == first


def test_offline_model_or_zero_clips_gets_no_streamed_validation_and_an_unknown_split_is_an_error(config, prepared_tiny):
    key = jax.random.key(0)
    assert streamed_validation(tt.TokTalkConfig.tiny(causal=False), prepared_tiny, "val", key=key) is None
    assert streamed_validation(config, prepared_tiny, "val", key=key, clips=0) is None
    with pytest.raises(ValueError, match="unknown split 'no-such-split'"):
        streamed_validation(config, prepared_tiny, "no-such-split", key=key)


@pytest.mark.slow
def test_recipe_records_streamed_metrics_and_keeps_the_best_checkpoint_by_streamed_lve(config, prepared_tiny, tmp_path):
    from jaxtalk.models.toktalk import recipe
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig
    from jaxtalk.train.checkpoint import read_best

    run = RunSettings(steps=3, batch_size=2, run_dir=tmp_path / "run", eval_every=1, loop=LoopSettings(progress=False))
    result = recipe.train(config, prepared_tiny, OptimConfig(lr=1e-3, warmup_steps=0, total_steps=3),
                          key=jax.random.key(0), run=run, val_clips=1)
    evals = [h for h in result.history if "eval" in h]
    assert len(evals) == 3 and all({"val_loss", SELECTION_METRIC, "LVE_mm2_1step"} <= set(h["eval"]) for h in evals)
    best_value = min(h["eval"][SELECTION_METRIC] for h in evals)
    record = read_best(tmp_path / "run" / "checkpoint")
    assert record["metric"] == SELECTION_METRIC and record["value"] == pytest.approx(best_value)


@pytest.mark.slow
def test_a_resumed_run_whose_best_was_chosen_by_the_loss_keeps_selecting_by_it(config, prepared_tiny, tmp_path):
    from jaxtalk.models.toktalk import recipe
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig
    from jaxtalk.train.checkpoint import read_best

    optim = OptimConfig(lr=1e-3, warmup_steps=0, total_steps=3)
    run = RunSettings(batch_size=2, run_dir=tmp_path / "run", eval_every=1, loop=LoopSettings(progress=False))
    key = jax.random.key(0)
    recipe.train(config, prepared_tiny, optim, key=key, run=dataclasses.replace(run, steps=2),
                 val_clips=0)  # as runs before streamed validation
    with pytest.warns(UserWarning, match="best checkpoint was chosen by 'val_loss'"):
        result = recipe.train(config, prepared_tiny, optim, key=key, run=dataclasses.replace(run, steps=3), val_clips=1)
    assert SELECTION_METRIC in result.history[-1]["eval"]
    assert read_best(tmp_path / "run" / "checkpoint")["metric"] == "val_loss"
