"""TokTalk's two training stages, both recipes on prepared SynthTalk: stage 2's windows carry the source
stream aligned with the base tokens and the motion, stage 2 leaves every base parameter bitwise
unchanged and trains only the adapter (and writes a run that loads), and the causal ``small`` model
trained with stage 1's recipe learns SynthTalk: streamed on held-out clips it beats the mean pose on LVE
at 1 and at 10 Euler steps."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.recipe import AdapterWindows, adapter_trainable, base_trainable, train_adapter
from jaxtalk.runs import RunSettings
from jaxtalk.train import LoopSettings, OptimConfig

CFG = tt.TokTalkConfig.tiny(num_mid_blocks=0)


@pytest.fixture(scope="module")
def stream_b(synthtalk_tiny):
    """SynthTalk's second token stream ("B", 25 Hz x 48) per prepared clip name: stage 2's source."""
    from jaxtalk.data.sources.synthtalk import clip_name

    return {clip_name(i): np.asarray(synthtalk_tiny.tokens(i, "B").embeddings, np.float32)
            for i in range(len(synthtalk_tiny.clips))}


def test_adapter_windows_align_the_source_stream_with_the_tokens_and_motion(prepared_tiny, stream_b):
    data = prepared_tiny
    cfg = tt.TokTalkConfig.tiny(style_frames=20)
    left_out = data.clips[data.split("train")[0]]["name"]
    recipe = AdapterWindows(cfg, 40, hop_frames=20, src_tokens={k: v for k, v in stream_b.items() if k != left_out},
                            src_rate=25.0)
    table = recipe.table(data, "train")
    assert len(table) and left_out not in {data.clips[int(i)]["name"] for i in table[:, 0]}
    for row in table[:: max(len(table) // 6, 1)]:
        w = recipe.example(data, row)
        i, st = int(row[0]), int(row[1])
        rec = data.record(i, ("motion", "tokens"))
        assert w["motion"].shape == (40, 56) and w["tokens"].shape == (20, 64) and w["src_tokens"].shape == (40, 48)
        length = int(w["mask"].sum())
        np.testing.assert_array_equal(w["motion"][:length], rec["motion"][st:st + length])
        np.testing.assert_array_equal(w["tokens"][0], rec["tokens"][st // 2])
        # 25 Hz source tokens at 25 fps: token k of the window is the stream's token at frame start + k.
        src = stream_b[data.clips[i]["name"]]
        n = min(40, len(src) - st)
        np.testing.assert_array_equal(w["src_tokens"][:n], src[st:st + n])
    with pytest.raises(ValueError, match="whole tokens"):
        AdapterWindows(cfg, 41, src_tokens=stream_b, src_rate=25.0)


@pytest.mark.slow
def test_stage2_trains_only_the_adapter_and_writes_a_run(prepared_tiny, stream_b, tmp_path):
    from jaxtalk.runs import load_run

    base = tt.init_params(CFG, jax.random.key(0))
    before = jax.tree.map(np.asarray, base)
    res = train_adapter(CFG, prepared_tiny, OptimConfig(lr=1e-2, warmup_steps=0, total_steps=3), base_params=base,
                        src_tokens=stream_b, src_rate=25.0, key=jax.random.key(1),
                        run=RunSettings(steps=3, batch_size=4, window_frames=32, run_dir=tmp_path / "run",
                                        loop=LoopSettings(progress=False)))
    after = res.state.params
    for name in ("decoder", "style", "norm"):
        same = jax.tree.map(lambda a, b: a.dtype == b.dtype and np.array_equal(a, np.asarray(b)), before[name],
                            after[name])
        assert all(jax.tree.leaves(same)), name
    fresh = tt.init_adapter(CFG, jax.random.split(jax.random.key(1), 3)[0], 48)
    moved = [float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(fresh), jax.tree.leaves(after["adapter"]))]
    assert max(moved) > 1e-3
    assert res.extra["adapter"] == {"src_rate": 25.0, "src_dim": 48}
    run = load_run(tmp_path / "run")
    assert run.record.extra["adapter"] == res.extra["adapter"]
    for a, b in zip(jax.tree.leaves(run.params["adapter"]), jax.tree.leaves(after["adapter"]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert adapter_trainable("adapter/conv/kernel", None) and not adapter_trainable("decoder/adapter", None)
    assert base_trainable("decoder/x", None) and not base_trainable("norm/mean", None)
    with pytest.raises(ValueError, match="src_tokens"):
        train_adapter(CFG, prepared_tiny, OptimConfig(total_steps=1, warmup_steps=0), base_params=base,
                      src_tokens={"no such clip": np.zeros((4, 48), np.float32)}, src_rate=25.0,
                      key=jax.random.key(1))


# Steps of the learning test. Measured on SynthTalk tiny v2 (the 6 held-out monologues, 2 CPU cores),
# LVE / mean-pose LVE at 1 and 10 sampler steps, over training seeds 0-3:
#   200 steps (1 min): 0.38 / 0.43 / 0.43 / 0.44 and 0.84 / 0.88 / 0.87 / 0.89;
#   300 steps: 0.47 / 0.53 / 0.55 / 0.57 and 0.89 / 0.95 / 0.95 / 0.99;
#   600 steps (seeds 0-1): 0.67 / 0.83 and 0.98 / 1.11.
# (Those figures are of the earlier small recipe sampling at temperature 1. At 0.5 seed 0's 200-step
# ratios were 0.38 and 0.52; with today's small recipe, the target clip's crop as the style and neither
# the anchor nor the style latent read by the decoder, 0.33 and 0.42.)
# Longer training overfits the tiny corpus's training speakers, so the test's model (conftest's
# learned_toktalk_small, shared with the exported page's test) trains 200 steps and its
# bars, 0.6 at 1 step and 0.75 at 10 (which a temperature-1 sampler misses), hold for the seed it
# trains. A 10-step sample scores worse than a 1-step one: its samples spread over what so brief a
# training has not learned (see experiments/toktalk_sample_quality.py). The held-out conversation sides are left out: their head
# motion repeats the partner's (delayed mimicry), which one voice cannot predict.


@pytest.mark.slow
@pytest.mark.optimized  # hundreds of training steps: run time dominates
def test_streamed_small_model_beats_the_mean_pose_on_held_out_monologues(prepared_tiny, learned_toktalk_small):
    from jaxtalk.face import builtin_face
    from jaxtalk.metrics import lve
    from jaxtalk.models.toktalk.sampling import default_grid

    data = prepared_tiny
    cfg, params = learned_toktalk_small
    face = builtin_face(0)
    lips = np.asarray(face.regions["lips"])
    mean_pose = np.asarray(params["norm"]["mean"], np.float32)
    # Monologues only: TokTalk maps one voice to its face (see the comment above the test).
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
    assert ratios[10] < 0.75, ratios
