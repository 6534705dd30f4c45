"""TIMAR loss: mask-ratio distribution, exact mask counts, loss only at masked frames, grouped MSE."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import perturbed, timar_streams
from scipy import stats

from jaxtalk.models.timar import TimarConfig, init_params, loss
from jaxtalk.models.turns.streams import to_turns
from jaxtalk.models.timar.loss import grouped_mse, masked_loss, random_agent_mask, sample_mask_ratio


CFG = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=32, speech_dim=8, max_turns=4, frames_per_turn=5)
B, N, F = 2, 2, 5


def _batch(seed=0, n=N):
    return timar_streams(B, n * F, seed)





@pytest.fixture(scope="module")
def params():
    p = init_params(CFG, jax.random.key(0))
    return perturbed(p, jax.random.key(9))


def test_mask_ratio_follows_the_truncated_normal_on_0p7_1():
    paper = TimarConfig.small(**{**CFG.__dict__, "mask_ratio_min": 0.7})  # the paper's / public code's draw
    keys = jax.random.split(jax.random.key(0), 4000)
    r = np.asarray(jax.vmap(lambda k: sample_mask_ratio(paper, k))(keys))
    assert r.min() >= 0.7 and r.max() <= 1.0
    ref = stats.truncnorm((0.7 - 1.0) / 0.25, 0.0, loc=1.0, scale=0.25)
    assert abs(r.mean() - ref.mean()) < 4 * ref.std() / np.sqrt(len(r))
    assert stats.kstest(r, ref.cdf).pvalue > 1e-3


def test_small_preset_masks_every_agent_frame_as_at_inference():
    assert CFG.mask_ratio_min == 1.0 and TimarConfig.paper().mask_ratio_min == 0.7
    keys = jax.random.split(jax.random.key(0), 16)
    r = np.asarray(jax.vmap(lambda k: sample_mask_ratio(CFG, k))(keys))
    np.testing.assert_array_equal(r, 1.0)
    assert bool(np.asarray(random_agent_mask(jax.random.key(3), float(r[0]), 2, 50)).all())


def test_random_agent_mask_masks_exactly_ceil_ratio_per_example_and_uniformly():
    m = np.asarray(random_agent_mask(jax.random.key(1), 0.7, 4, 200))
    assert m.sum(axis=1).tolist() == [140] * 4
    m = np.asarray(random_agent_mask(jax.random.key(2), jnp.float32(0.71), 3, 50))
    assert m.sum(axis=1).tolist() == [36] * 3  # ceil(35.5)
    assert np.asarray(random_agent_mask(jax.random.key(3), 1.0, 2, 25)).all()
    # Every position is masked about equally often.
    many = np.asarray(jax.vmap(lambda k: random_agent_mask(k, 0.5, 1, 10)[0])(jax.random.split(jax.random.key(4), 2000)))
    assert np.allclose(many.mean(0), 0.5, atol=0.06)


def test_grouped_mse_weights_each_group_equally():
    target = jnp.zeros((56,))
    pred = jnp.zeros((56,)).at[0].set(1.0).at[50].set(1.0).at[55].set(2.0)
    total, groups = grouped_mse(pred, target)
    np.testing.assert_allclose(float(groups["exp"]), 1 / 50)
    np.testing.assert_allclose(float(groups["jaw"]), 1 / 3)
    np.testing.assert_allclose(float(groups["neck"]), 4 / 3)
    np.testing.assert_allclose(float(total), 1 / 50 + 1 / 3 + 4 / 3, rtol=1e-6)


def test_loss_only_counts_masked_frames(params):
    b = _batch()
    turns = tuple(to_turns(jnp.asarray(b[k]), F) for k in ("user_speech", "user_motion", "agent_speech", "agent_motion"))
    mask = np.zeros((B, N, F), bool)
    mask[0, 0, :3] = True
    mask[1, 1, 1:4] = True
    mask = jnp.asarray(mask)
    drop = jnp.zeros((B,), bool)
    key = jax.random.key(5)
    fn = jax.jit(lambda tg: masked_loss(params, CFG, turns, tg, mask, drop, key))
    target = turns[3]
    base, metrics = fn(target)
    assert float(metrics["masked_frames"]) == 3 + 3
    # Changing the TARGET of an unmasked frame leaves the loss bit-identical...
    changed = target.at[0, 1, 4].add(10.0).at[1, 0, 0].add(-3.0)
    assert float(fn(changed)[0]) == float(base)
    # ...and of a masked frame changes it.
    assert abs(float(fn(target.at[1, 1, 2].add(1.0))[0]) - float(base)) > 1e-4
    # The gradient w.r.t. the targets vanishes exactly on unmasked frames.
    g = np.asarray(jax.grad(lambda tg: fn(tg)[0])(target))
    assert np.all(g[~np.asarray(mask)] == 0) and np.abs(g[np.asarray(mask)]).sum() > 0


@pytest.mark.slow
def test_timar_loss_is_finite_differentiable_and_reports_groups(params):
    value, m = jax.jit(lambda p, b, k: loss(p, CFG, b, k))(params, _batch(), jax.random.key(0))
    assert np.isfinite(float(value))
    np.testing.assert_allclose(float(value), float(m["loss_exp"] + m["loss_jaw"] + m["loss_neck"]), rtol=1e-5)
    assert 0.7 <= float(m["mask_ratio"]) <= 1.0
    assert float(m["masked_frames"]) == B * np.ceil(np.round(float(m["mask_ratio"]) * N * F, 4))
    g = jax.jit(jax.grad(lambda p, b: loss(p, CFG, b, jax.random.key(0))[0]))(params, _batch())
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(g))
    sig = TimarConfig.small(**{**CFG.__dict__, "learn_sigma": True})
    ps = init_params(sig, jax.random.key(1))
    loss_s, ms = jax.jit(lambda p, b: loss(p, sig, b, jax.random.key(0)))(ps, _batch())
    assert np.isfinite(float(loss_s)) and float(ms["loss_vlb"]) > 0


def test_loss_rejects_bad_batches(params):
    b = _batch()
    with pytest.raises(ValueError, match="missing"):
        loss(params, CFG, {k: v for k, v in b.items() if k != "user_motion"}, jax.random.key(0))
    bad = dict(b, agent_motion=b["agent_motion"][:, :-1])
    with pytest.raises(ValueError, match="aligned"):
        loss(params, CFG, bad, jax.random.key(0))
    short = {k: v[:, :-3] for k, v in b.items()}
    with pytest.raises(ValueError, match="multiple of frames_per_turn"):
        loss(params, CFG, short, jax.random.key(0))
    nan = dict(b, user_speech=np.where(np.arange(8) == 3, np.nan, b["user_speech"]).astype(np.float32))
    with pytest.raises(ValueError, match="NaN"):
        loss(params, CFG, nan, jax.random.key(0))
    long = _batch(n=5)
    with pytest.raises(ValueError, match="max_turns"):
        loss(params, CFG, long, jax.random.key(0))


@pytest.mark.slow
def test_diffusion_batch_mul_averages_draws_without_bias_and_cuts_the_loss_noise(params):
    # m (t, noise) draws per frame: the same expected loss (an average of single draws) with about
    # 1/m of the key-to-key variance. All randomness here is the draws (every frame masked, no CFG
    # dropout, deterministic encoder), so 96 keys tell the two apart clearly.
    b = _batch()
    keys = jax.random.split(jax.random.key(1), 96)

    def losses(m):
        cfg = TimarConfig.small(**{**CFG.__dict__, "diffusion_batch_mul": m, "cfg_dropout": 0.0})
        return np.asarray(jax.jit(jax.vmap(lambda k: loss(params, cfg, b, k)[0]))(keys))

    one, four = losses(1), losses(4)
    assert np.var(four) < 0.5 * np.var(one), (np.var(one), np.var(four))
    se = np.sqrt(np.var(one) / len(one) + np.var(four) / len(four))
    assert abs(one.mean() - four.mean()) < 4 * se, (one.mean(), four.mean(), se)
    with pytest.raises(ValueError, match="diffusion_batch_mul"):
        TimarConfig.small(diffusion_batch_mul=0)
