"""FreeTalk learns on SynthTalk: ATS beats the mean pose on held-out clips, STM transfers landmark
motion to a mesh topology and identity it never saw. Small models, short training (slow tests), each
through its recipe on the prepared corpus (the one training path); held-out windows are cut from the
in-memory corpus."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import few_validation_windows

from jaxtalk.face import builtin_face
from jaxtalk.geometry.topology import make_variant
from jaxtalk.models.freetalk import ats, data, stm
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
from jaxtalk.models.freetalk.data import DisplacementStats
from jaxtalk.models.freetalk.fit import FittedATS, sample_displacements
from jaxtalk.models.freetalk.recipe import train_ats, train_stm
from jaxtalk.runs import RunSettings
from jaxtalk.train import LoopSettings, OptimConfig

LIPS = np.r_[48:68]


@pytest.fixture(scope="module")
def corpus(synthtalk_tiny):
    # The session-wide tiny corpus (tests/conftest.py): generated once for every test that needs it.
    return synthtalk_tiny


@pytest.mark.slow
@pytest.mark.optimized  # hundreds of training steps: run time dominates
def test_ats_beats_the_mean_pose_on_held_out_clips(corpus, prepared_tiny):
    window = 16  # the recipe hops a quarter window: 4 frames
    test_w = data.ats_windows(corpus, corpus.split("val") + corpus.split("test"), window=window, hop=window)
    cfg = ATSConfig.small(width=64, num_layers=2, num_heads=4, ff_dim=128, max_frames=window,
                          displacement_scale=1.0, speech_dim=prepared_tiny.manifest["speech_dim"])
    optim = OptimConfig(lr=2e-3, warmup_steps=20, total_steps=150)
    result = train_ats(cfg, prepared_tiny, optim, key=jax.random.key(0),
                       run=RunSettings(window_frames=window, loop=LoopSettings(progress=False)))
    stats = result.extra["stats"]
    fitted = FittedATS(cfg, result.state.eval_params, DisplacementStats(np.asarray(stats["mean"], np.float32),
                       np.asarray(stats["std"], np.float32)), result.history, window=window)
    gt = test_w["displacements"]

    def lip_error(pred):
        return float(np.linalg.norm(pred[:, :, LIPS] - gt[:, :, LIPS], axis=-1).mean())

    baseline = lip_error(np.broadcast_to(fitted.stats.mean, gt.shape))
    sampled = sample_displacements(fitted, test_w["audio"], test_w["emotion"], test_w["intensity"],
                                   jax.random.key(1), sample_steps=10)
    # The denoiser's estimate from pure noise at the last training step is its posterior mean
    # E[x0 | audio, emotion, intensity]; it must use the audio to beat the unconditional mean.
    cond = ats.make_condition(cfg, test_w["audio"], test_w["emotion"], test_w["intensity"])
    noise = jax.random.normal(jax.random.key(2), gt.shape[:2] + (cfg.motion_dim,))
    t_last = jnp.full((gt.shape[0],), cfg.num_timesteps - 1.0)
    posterior_mean = fitted.stats.denormalize(
        np.asarray(ats.ats_denoise(fitted.params, cfg, noise, t_last, cond)).reshape(gt.shape))
    print("lip error / mean pose: posterior mean", lip_error(posterior_mean) / baseline, "sampled",
          lip_error(sampled) / baseline)
    assert lip_error(posterior_mean) < 0.9 * baseline, (lip_error(posterior_mean), baseline)
    assert lip_error(sampled) < baseline, (lip_error(sampled), baseline)


@pytest.mark.slow
@pytest.mark.optimized  # hundreds of training steps: run time dominates
def test_stm_transfers_motion_to_an_unseen_topology_and_identity(corpus, prepared_tiny):
    cfg = STMConfig.small(num_eigenpairs=24)
    base = builtin_face(0, resolution="low")
    train_mesh = stm.prepare_mesh(np.asarray(base.template, np.float64), np.asarray(base.faces), cfg)
    optim = OptimConfig(lr=3e-3, warmup_steps=10, total_steps=120)
    # ONE training mesh (identity 0, base topology), 4-frame windows of the training motion.
    with few_validation_windows():  # the validation loss is not what this test measures
        run = RunSettings(batch_size=4, window_frames=4, loop=LoopSettings(progress=False, log_every=6))
        result = train_stm(cfg, prepared_tiny, optim, key=jax.random.key(0), run=run, meshes=((0, "base"),),
                           resolution="low", val_clips=0)  # the unseen mesh is scored below
    params, history = result.state.eval_params, [h for h in result.history if "loss" in h]
    assert history[-1]["loss"] < history[0]["loss"]

    other = builtin_face(2, resolution="low")
    variant = make_variant(np.asarray(other.template, np.float64), np.asarray(other.faces), "decimated", seed=2)
    mesh = stm.prepare_mesh(variant.vertices, variant.faces, cfg)
    assert mesh.num_vertices != train_mesh.num_vertices
    clip = corpus.split("test")[0]
    lms, gt, _ = data.mesh_motion(other, data.without_head_pose(corpus.motion(clip)), variant)
    pred = np.asarray(stm.apply(params, cfg, mesh, lms))
    err = np.linalg.norm(pred - gt, axis=-1).mean()
    still = np.linalg.norm(gt, axis=-1).mean()  # the neutral mesh (zero displacement)
    print("unseen mesh error / neutral-mesh error:", err / still)
    # Measured here: about 0.65 of the neutral-mesh error after 120 steps on ONE training mesh.
    assert err < 0.75 * still, (err, still)
