"""TIMAR learns from audio on SynthTalk: on held-out speakers its posterior mean beats the mean pose on
the jaw (the audio-driven group) during speech by a clear margin.

Metric choice: the jaw opening on the agent's speaking frames is determined by the audio (the
generator's oracle explains it fully, a ridge probe on log-mel recovers most of it), while the mean
pose cannot follow it. MSE over all 50 expression components is dominated by each speaker's resting
expression, which no audio reveals (a sample of a correct model then scores about twice that
variance, worse than the mean), and FD is beaten by any motion with the right covariance, so neither
shows learning. Small model, one-turn windows, short training (a slow test, ~1 min) through TIMAR's
recipe on the prepared corpus (the one training path; evaluation streams the in-memory corpus's
held-out conversations, whose per-turn speech features are the prepared ones, with the recipe's
normaliser).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxtalk.layout import GROUPS
from jaxtalk.models.timar import TimarConfig, recipe, sample
from jaxtalk.models.timar.data import Normalizer, conversations
from jaxtalk.models.timar.sampling import posterior_mean
from jaxtalk.runs import RunSettings
from jaxtalk.train import LoopSettings, OptimConfig

JAW = GROUPS["jaw"]
STEPS = 450


@pytest.mark.slow
@pytest.mark.optimized  # hundreds of training steps: run time dominates
def test_posterior_mean_beats_the_mean_pose_on_the_jaw_of_held_out_speakers(synthtalk_tiny, prepared_tiny):
    corpus = synthtalk_tiny
    cfg = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=64, max_turns=1, mask_ratio_min=1.0)
    # AdamW 3e-3, 20 warm-up steps, cosine to a tenth (the small-model settings on CPU).
    optim = OptimConfig(lr=3e-3, warmup_steps=20, total_steps=STEPS, final_lr_ratio=0.1)
    result = recipe.train(cfg, prepared_tiny, optim, key=jax.random.key(0),
                          run=RunSettings(batch_size=16, eval_every=STEPS, loop=LoopSettings(progress=False)))
    params, norm = result.state.eval_params, Normalizer.from_dict(result.extra["normalizer"])

    test = conversations(corpus, "test")
    err = {"posterior mean": [], "sample": [], "mean pose": []}
    for i, c in enumerate(test):
        # One-turn windows: every turn of the conversation is one batch row.
        per_turn = lambda x: x.reshape(-1, cfg.frames_per_turn, x.shape[-1])  # noqa: E731
        args = (per_turn(norm.speech(c.user_speech)), per_turn(norm.motion(c.user_motion)),
                per_turn(norm.speech(c.agent_speech)))
        preds = {
            "posterior mean": posterior_mean(params, cfg, *args, jax.random.key(i)),
            "sample": sample(params, cfg, *args, jax.random.key(i), cfg_scale=0.0),
        }
        speaking = corpus.voice_activity(c.agent_clip)[: c.num_frames]
        for name, x in preds.items():
            pred = norm.unmotion(np.asarray(x).reshape(c.num_frames, 56))
            err[name].append(((pred - c.agent_motion)[speaking][:, JAW] ** 2).mean())
        err["mean pose"].append(((norm.motion_mean - c.agent_motion)[speaking][:, JAW] ** 2).mean())
    score = {k: float(np.mean(v)) for k, v in err.items()}
    print("jaw MSE on speaking frames:", score, "posterior mean / mean pose:", score["posterior mean"] / score["mean pose"])
    # The posterior mean must use the audio to beat the training mean by a clear margin. (Samples
    # need a longer run to do so: with width 48 and 600 steps they reach ~0.35x, here ~0.9x, so
    # they are only required not to be much worse.)
    # Measured 0.59x on the development machine; the bar leaves room for other CPUs' float rounding,
    # which moves this short run by ~0.1x (a 1e-5 change in the normaliser gave 0.69x).
    assert score["posterior mean"] < 0.75 * score["mean pose"], score
    assert score["sample"] < 1.2 * score["mean pose"], score
