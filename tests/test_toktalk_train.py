"""TokTalk training: windows from SynthTalk, stage 2 leaves every base parameter bitwise unchanged and
trains only the adapter, and the small model learns SynthTalk (beats the mean pose on held-out clips)."""

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


@pytest.mark.slow
def test_small_model_learns_synthtalk():
    from jaxtalk.data import synthtalk

    corpus = synthtalk.generate("tiny", seed=0)
    cfg = tt.TokTalkConfig.small()
    # A third of the train clips keeps the data preparation (token encoding) short.
    train_clips = corpus.split("train")[::3]
    held_out = corpus.split("test")[:4]
    windows = make_windows(corpus, train_clips, cfg, window_frames=50, hop_frames=10)
    test = make_windows(corpus, held_out, cfg, window_frames=50, hop_frames=50)
    res = train_base(cfg, windows, OptimConfig(lr=2e-3, warmup_steps=20, total_steps=150, weight_decay=0.0),
                     key=jax.random.key(0), batch_size=16, progress=False, log_every=50)
    pred = np.asarray(tt.sample(res.state.params, cfg, test["tokens"], test["style"], jax.random.key(1)))
    mask = test["mask"]
    mean_pose = windows["motion"][windows["mask"]].mean(0)
    jaw = slice(50, 53)  # jaw opening is driven by the audio: the part a model must read from tokens
    model_err = np.mean(np.square(pred - test["motion"])[mask][:, jaw])
    base_err = np.mean(np.square(mean_pose - test["motion"])[mask][:, jaw])
    assert model_err < 0.7 * base_err, (model_err, base_err)
