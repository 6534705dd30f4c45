"""FreeTalk's in-training validations score the models as users measure them. ATS: the DDIM-sampled
windows' landmark LVE, LE and jitter equal a hand computation on the clips' first windows, repeat exactly
at every evaluation, reach the run's metrics, and choose the best checkpoint (lowest sampled LVE). STM:
the vertices decoded on a mesh it never trained on score as computed by hand, and choose the best
checkpoint (lowest held-out LVE)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxtalk.metrics import landmark_metrics
from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.models.freetalk.recipe import ATSWindows, fit_displacement_stats
from jaxtalk.models.freetalk.validation import SELECTION_METRIC, held_out_mesh_validation, sampled_validation


@pytest.fixture(scope="module")
def config(prepared_tiny):
    return ATSConfig.small(width=16, num_layers=1, num_heads=2, ff_dim=32, max_frames=20, sample_steps=2,
                           speech_dim=prepared_tiny.manifest["speech_dim"])


def _perturbed(params, key):
    # Zero-initialised output layers make a fresh ATS predict exactly 0; perturb so the samples vary.
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(tree, [x + 0.05 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])


def test_sampled_validation_equals_a_hand_computation_and_repeats_exactly(config, prepared_tiny):
    data = prepared_tiny
    windows = ATSWindows(10, fit_displacement_stats(data), config.emotions)
    params = _perturbed(ats.init_params(config, jax.random.key(0)), jax.random.key(1))
    key = jax.random.key(3)
    eval_fn = sampled_validation(config, data, windows, "val", key=key, clips=2)
    first = eval_fn(params, None, 0)
    assert set(first) == {"LVE_mm2", "LE_mm", "jitter_mm"} and SELECTION_METRIC == "LVE_mm2"
    assert eval_fn(params, None, 10) == first  # the same windows and noise at every evaluation

    # By hand: the first 10 frames of the first and the last val clip (2 clips spread over the split).
    usable = [i for i in data.split("val") if data.clips[i]["frames"] >= 10]
    picked = [usable[0], usable[-1]]
    recs = [data.record(i, ("landmarks", "speech")) for i in picked]
    audio = np.stack([r["speech"][:10] for r in recs]).astype(np.float32)
    emotion = [data.clips[i]["emotion"] or "neutral" for i in picked]
    intensity = np.asarray([data.clips[i]["intensity"] or 1.0 for i in picked], np.float32)
    out = ats.sample(params, config, ats.make_condition(config, audio, emotion, intensity), key)
    pred = windows.stats.denormalize(np.asarray(out))
    scores = [landmark_metrics(p, np.asarray(r["landmarks"][:10], np.float32)) for p, r in zip(pred, recs)]
    for name in first:
        assert first[name] == pytest.approx(np.mean([s[name] for s in scores]), rel=1e-4)
    # The EMA parameters are the ones scored when the run keeps them.
    zero = jax.tree.map(np.zeros_like, params)
    assert eval_fn(zero, params, 0) == first


def test_zero_clips_or_a_split_without_windows_gets_no_sampled_validation(config, prepared_tiny):
    windows = ATSWindows(10, fit_displacement_stats(prepared_tiny), config.emotions)
    key = jax.random.key(0)
    assert sampled_validation(config, prepared_tiny, windows, "val", key=key, clips=0) is None
    too_long = ATSWindows(10**6, windows.stats, config.emotions)
    assert sampled_validation(config, prepared_tiny, too_long, "val", key=key) is None


def test_recipe_records_sampled_metrics_and_keeps_the_best_checkpoint_by_sampled_lve(config, prepared_tiny, tmp_path):
    from jaxtalk.models.freetalk.recipe import train_ats
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig
    from jaxtalk.train.checkpoint import read_best

    run = RunSettings(steps=3, batch_size=2, window_frames=10, run_dir=tmp_path / "run", eval_every=1,
                      loop=LoopSettings(progress=False))
    result = train_ats(config, prepared_tiny, OptimConfig(lr=1e-3, warmup_steps=0, total_steps=3),
                       key=jax.random.key(0), run=run, val_clips=2)
    evals = [h for h in result.history if "eval" in h]
    assert len(evals) == 3 and all({"val_loss", "LVE_mm2", "LE_mm", "jitter_mm"} <= set(h["eval"]) for h in evals)
    record = read_best(tmp_path / "run" / "checkpoint")
    assert record["metric"] == SELECTION_METRIC
    assert record["value"] == pytest.approx(min(h["eval"][SELECTION_METRIC] for h in evals))


@pytest.fixture(scope="module")
def stm_config():
    from jaxtalk.models.freetalk.config import STMConfig

    return STMConfig.small(encoder_blocks=1, decoder_blocks=1, num_eigenpairs=16)


def test_held_out_mesh_validation_equals_a_hand_computation(stm_config, prepared_tiny):
    from jaxtalk.metrics import jitter, lve, mve
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.data import face_mesh, without_head_pose

    data = prepared_tiny
    fm = face_mesh(3, "retriangulated")
    prepared = stm.prepare_mesh(fm.vertices, fm.faces, stm_config)
    params = _perturbed(stm.init_params(stm_config, jax.random.key(0), prepared), jax.random.key(1))
    eval_fn = held_out_mesh_validation(stm_config, data, ((3, "retriangulated"),), "val", window=6, clips=1)
    scores = eval_fn(params, None, 0)
    assert set(scores) == {"LVE_mm2", "MVE_mm", "jitter_mm"}

    first = [i for i in data.split("val") if data.clips[i]["frames"] >= 6][0]
    landmarks, vertices = fm.motion(without_head_pose(np.asarray(data.record(first, ("motion",))["motion"], np.float32)[:6]))
    pred = np.asarray(stm.stm_decode(params, stm_config, stm.stm_mesh_features(params, stm_config, prepared), landmarks,
                                     prepared))
    assert scores["LVE_mm2"] == pytest.approx(float(lve(pred, vertices, fm.region("lips"))) * 1e6, rel=1e-4)
    assert scores["MVE_mm"] == pytest.approx(float(mve(pred, vertices)) * 1e3, rel=1e-4)
    assert scores["jitter_mm"] == pytest.approx(float(jitter(pred)) * 1e3, rel=1e-4)
    assert held_out_mesh_validation(stm_config, data, (), "val") is None
    assert held_out_mesh_validation(stm_config, data, ((3, "base"),), "val", clips=0) is None


@pytest.mark.slow
def test_stm_recipe_keeps_the_best_checkpoint_by_the_held_out_mesh_lve(stm_config, prepared_tiny, tmp_path):
    from jaxtalk.models.freetalk.recipe import train_stm
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig
    from jaxtalk.train.checkpoint import read_best

    run = RunSettings(steps=2, batch_size=2, window_frames=4, run_dir=tmp_path / "run", eval_every=1,
                      loop=LoopSettings(progress=False))
    result = train_stm(stm_config, prepared_tiny, OptimConfig(lr=1e-3, warmup_steps=0, total_steps=2),
                       key=jax.random.key(0), run=run, meshes=((1, "decimated"),), held_out=((3, "retriangulated"),),
                       val_clips=1)
    evals = [h for h in result.history if "eval" in h]
    assert len(evals) == 2 and all({"val_loss", "LVE_mm2", "MVE_mm", "jitter_mm"} <= set(h["eval"]) for h in evals)
    record = read_best(tmp_path / "run" / "checkpoint")
    assert record["metric"] == SELECTION_METRIC
    assert record["value"] == pytest.approx(min(h["eval"][SELECTION_METRIC] for h in evals))
