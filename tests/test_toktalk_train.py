"""TokTalk training: windows from SynthTalk, stage 2 leaves every base parameter bitwise unchanged and
trains only the adapter, the flow loss falls on a learnable task, and the causal ``small`` model trained
with TokTalk's recipe learns SynthTalk: streamed on held-out clips it beats the mean pose on LVE at 1
and at 10 Euler steps."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.train import adapter_trainable, make_windows, train_adapter, train_base
from jaxtalk.train import OptimConfig

CFG = tt.TokTalkConfig.tiny()


def _fake_windows(n=8, t=16, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "motion": rng.normal(size=(n, t, 56)).astype(np.float32),
        "tokens": rng.normal(size=(n, t // 2, 64)).astype(np.float32),
        "src_tokens": rng.normal(size=(n, t, 48)).astype(np.float32),
        "style": rng.normal(size=(n, CFG.style_frames, 56)).astype(np.float32),
        "mask": np.ones((n, t), bool),
    }


def test_stage2_trains_only_the_adapter(fast_compile):
    windows = _fake_windows()
    base = tt.init_params(CFG, jax.random.key(0))
    before = jax.tree.map(np.asarray, base)
    res = train_adapter(CFG, base, windows, OptimConfig(lr=1e-2, warmup_steps=0, total_steps=3),
                        key=jax.random.key(1), src_rate=25.0, batch_size=4, progress=False)
    after = res.state.params
    for name in ("decoder", "style"):
        same = jax.tree.map(lambda a, b: a.dtype == b.dtype and np.array_equal(a, np.asarray(b)), before[name],
                            after[name])
        assert all(jax.tree.leaves(same)), name
    fresh = tt.init_adapter(CFG, jax.random.split(jax.random.key(1))[0], 48)
    moved = [float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(fresh), jax.tree.leaves(after["adapter"]))]
    assert max(moved) > 1e-3
    assert adapter_trainable("adapter/conv/kernel", None) and not adapter_trainable("decoder/adapter", None)
    with pytest.raises(ValueError, match="src_tokens"):
        train_adapter(CFG, base, {k: v for k, v in windows.items() if k != "src_tokens"},
                      OptimConfig(total_steps=1, warmup_steps=0), key=jax.random.key(1), src_rate=25.0)


def test_make_windows_cuts_aligned_motion_tokens_and_foreign_style():
    from jaxtalk.data import synthtalk
    from jaxtalk.data.synthtalk import SizeSpec

    corpus = synthtalk.generate(SizeSpec((2, 1, 1, 1), 2, 3.0, (0, 0, 0, 0), 10.0, 16, 1e9), seed=0)
    cfg = tt.TokTalkConfig.tiny(style_frames=20)
    clips = corpus.split("train")
    w = make_windows(corpus, clips, cfg, window_frames=40, hop_frames=20, src_stream="B", seed=0)
    n = len(w["clip"])
    assert w["motion"].shape == (n, 40, 56) and w["tokens"].shape == (n, 20, 64)
    assert w["src_tokens"].shape == (n, 40, 48) and w["style"].shape == (n, 20, 56)
    for k in range(n):
        c, st = int(w["clip"][k]), int(w["start"][k])
        motion = np.asarray(corpus.motion(c))
        length = int(w["mask"][k].sum())
        np.testing.assert_array_equal(w["motion"][k, :length], motion[st : st + length])
        tok = np.asarray(corpus.tokens(c, "A").embeddings)
        np.testing.assert_array_equal(w["tokens"][k, 0], tok[st // 2])
        # The style clip is a crop of another clip of the same speaker, never of the window's own clip.
        same_speaker = [j for j in clips if corpus.clips[j].speaker == corpus.clips[c].speaker and j != c]
        sources = [np.asarray(corpus.motion(j)) for j in same_speaker] or [motion]
        assert any(np.any(np.all(src == w["style"][k, 0], axis=1)) for src in sources)
    # Every clip's last frames are covered by a window aligned to its end.
    for c in clips:
        ends = w["start"][w["clip"] == c] + w["mask"][w["clip"] == c].sum(1)
        assert ends.max() == corpus.clips[c].num_frames
    with pytest.raises(ValueError, match="whole tokens"):
        make_windows(corpus, clips, cfg, window_frames=41)


@pytest.mark.slow  # 120 training steps
def test_training_reduces_the_flow_loss_on_a_learnable_task(fast_compile):
    # Motion that is a fixed linear function of the tokens: learnable from the condition alone.
    rng = np.random.default_rng(0)
    n, t = 64, 16
    tokens = rng.normal(size=(n, t // 2, 64)).astype(np.float32)
    proj = (0.1 * rng.normal(size=(64, 56))).astype(np.float32)
    windows = {
        "motion": np.repeat(tokens @ proj, 2, axis=1),
        "tokens": tokens,
        "style": np.zeros((n, CFG.style_frames, 56), np.float32),
        "mask": np.ones((n, t), bool),
    }
    res = train_base(CFG, windows, OptimConfig(lr=3e-3, warmup_steps=10, total_steps=120, weight_decay=0.0),
                     key=jax.random.key(0), batch_size=16, progress=False, log_every=20)
    losses = np.array([h["loss"] for h in res.history if "loss" in h])
    assert np.all(np.isfinite(losses))
    assert losses[-20:].mean() < 0.85 * losses[:5].mean(), (losses[:5], losses[-20:])


# Steps of the learning test. Measured on SynthTalk tiny v2 (the 6 held-out monologues, 2 CPU cores),
# LVE / mean-pose LVE at 1 and 10 sampler steps, over training seeds 0-3:
#   200 steps (1 min): 0.38 / 0.43 / 0.43 / 0.44 and 0.84 / 0.88 / 0.87 / 0.89;
#   300 steps: 0.47 / 0.53 / 0.55 / 0.57 and 0.89 / 0.95 / 0.95 / 0.99;
#   600 steps (seeds 0-1): 0.67 / 0.83 and 0.98 / 1.11.
# Longer training overfits the tiny corpus's training speakers, so the test trains 200 steps and its
# bars, 0.6 and 0.95, clear every seed measured by at least 0.06. A 10-step sample scores worse than a
# 1-step one: its samples spread over what so brief a training has not learned (see
# experiments/toktalk_sample_quality.py). The held-out conversation sides are left out: their head
# motion repeats the partner's (delayed mimicry), which one voice cannot predict.
LEARN_STEPS = 200


@pytest.mark.slow
def test_streamed_small_model_beats_the_mean_pose_on_held_out_monologues(prepared_tiny):
    from jaxtalk.face import builtin_face
    from jaxtalk.metrics import lve
    from jaxtalk.models.toktalk import recipe
    from jaxtalk.models.toktalk.sample import default_grid

    data = prepared_tiny
    cfg = tt.TokTalkConfig.small()
    result = recipe.train(cfg, data, OptimConfig(lr=recipe.DEFAULTS.lr, warmup_steps=50, total_steps=LEARN_STEPS,
                                                 ema_decay=recipe.DEFAULTS.ema_decay),
                          key=jax.random.key(0), batch_size=16, progress=False)
    params = result.state.eval_params
    face = builtin_face(0)
    lips = np.asarray(face.regions["lips"])
    mean_pose = np.asarray(params["norm"]["mean"], np.float32)
    # Monologues only: TokTalk maps one voice to its face (see LEARN_STEPS' comment).
    test = [i for i in data.split("test") if data.clips[i]["tokens"] and not data.clips[i]["partner"]]
    by_speaker = {}
    for i in test:
        by_speaker.setdefault(data.clips[i]["speaker"], []).append(i)
    errors = {"mean pose": [], 1: [], 10: []}
    for n, i in enumerate(test):
        rec = data.record(i, ("motion", "tokens"))
        other = next((j for j in by_speaker[data.clips[i]["speaker"]] if j != i), i)
        style = tt.encode_style(params, cfg, data.record(other, ("motion",))["motion"][None, : 4 * cfg.style_frames])
        gt = np.asarray(rec["motion"], np.float32)
        v_gt = np.asarray(face.vertices_seq(gt))
        errors["mean pose"].append(float(lve(np.asarray(face.vertices_seq(np.broadcast_to(mean_pose, gt.shape))), v_gt, lips)))
        for steps in (1, 10):
            out = np.asarray(tt.stream(params, cfg, rec["tokens"][None], style, jax.random.key(n),
                                       ts=default_grid(cfg, steps)))[0][: gt.shape[0]]
            errors[steps].append(float(lve(np.asarray(face.vertices_seq(out)), v_gt[: out.shape[0]], lips)))
    base = np.mean(errors["mean pose"])
    ratios = {steps: np.mean(errors[steps]) / base for steps in (1, 10)}
    print("LVE / mean-pose LVE:", ratios)
    assert ratios[1] < 0.6, ratios
    assert ratios[10] < 0.95, ratios
