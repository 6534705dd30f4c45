"""TIMAR encoder + head: causality across turns, CFG fake token, per-frame head vmapped == loop."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import perturbed, timar_streams

from jaxtalk.models.timar import TimarConfig, encode_window, init_params, sample
from jaxtalk.models.timar.head import (
    apply_head,
    apply_head_hoisted,
    apply_head_modulated,
    head_condition,
    head_modulations,
    init_head,
    time_embedding,
)
from jaxtalk.models.turns.streams import to_turns


CFG = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=32, speech_dim=8, max_turns=4, frames_per_turn=5)
B, N, F = 2, 3, 5


def _perturbed(params, seed=3):
    return perturbed(params, jax.random.key(seed))





@pytest.fixture(scope="module")
def params():
    return _perturbed(init_params(CFG, jax.random.key(0)))


def _streams(seed=0, n=N):
    return timar_streams(B, n * F, seed)


_encode = jax.jit(encode_window, static_argnums=1)


def _z(config, params, s, user_drop=None):
    turns = {k: to_turns(jnp.asarray(v), F) for k, v in s.items()}
    return np.asarray(_encode(params, config, turns["user_speech"], turns["user_motion"], turns["agent_speech"],
                              None, None, user_drop))


@pytest.mark.slow
def test_changing_turn_t_plus_1_leaves_turns_up_to_t_exactly_unchanged(params):
    s = _streams()
    z0 = _z(CFG, params, s)
    x0 = np.asarray(sample(params, CFG, s["user_speech"], s["user_motion"], s["agent_speech"], jax.random.key(1)))
    for stream in ("user_speech", "user_motion", "agent_speech"):
        s2 = {k: v.copy() for k, v in s.items()}
        s2[stream][:, 2 * F :] += 5.0  # change only turn 2 (0-based)
        z1 = _z(CFG, params, s2)
        x1 = np.asarray(sample(params, CFG, s2["user_speech"], s2["user_motion"], s2["agent_speech"], jax.random.key(1)))
        np.testing.assert_array_equal(z0[:, :2], z1[:, :2])
        np.testing.assert_array_equal(x0[:, : 2 * F], x1[:, : 2 * F])
        assert np.abs(z0[:, 2] - z1[:, 2]).max() > 1e-3  # the changed turn itself does see it
    # The same change leaks into earlier turns under bidirectional attention (the Table 2 ablation).
    bi = TimarConfig.small(**{**CFG.__dict__, "attention": "bidirectional"})
    assert np.abs(_z(bi, params, s)[:, 0] - _z(bi, params, s2)[:, 0]).max() > 1e-4


def test_agent_motion_only_enters_where_unmasked(params):
    s = _streams()
    turns = {k: to_turns(jnp.asarray(v), F) for k, v in s.items()}
    mask = np.ones((B, N, F), bool)
    mask[:, 1, 2] = False  # one visible agent frame
    args = (turns["user_speech"], turns["user_motion"], turns["agent_speech"])
    z0 = np.asarray(_encode(params, CFG, *args, turns["agent_motion"], jnp.asarray(mask)))
    am = np.asarray(turns["agent_motion"]).copy()
    am[:, 1, 3] += 3.0  # a masked frame: invisible
    z1 = np.asarray(_encode(params, CFG, *args, jnp.asarray(am), jnp.asarray(mask)))
    np.testing.assert_array_equal(z0, z1)
    am[:, 1, 2] += 3.0  # the visible frame: seen by its turn and later ones, not earlier ones
    z2 = np.asarray(_encode(params, CFG, *args, jnp.asarray(am), jnp.asarray(mask)))
    np.testing.assert_array_equal(z0[:, 0], z2[:, 0])
    assert np.abs(z0[:, 1:] - z2[:, 1:]).max() > 1e-3
    # All-masked input equals passing no agent motion at all (what the samplers do).
    z_none = np.asarray(_encode(params, CFG, *args, None, None))
    z_all = np.asarray(_encode(params, CFG, *args, turns["agent_motion"], jnp.ones((B, N, F), bool)))
    np.testing.assert_allclose(z_none, z_all, atol=1e-6)


def test_fake_token_removes_every_user_input(params):
    s = _streams()
    s2 = {k: v.copy() for k, v in s.items()}
    s2["user_speech"] += 2.0
    s2["user_motion"] -= 1.0
    drop = jnp.asarray([True, False])
    z0, z1 = _z(CFG, params, s, user_drop=drop), _z(CFG, params, s2, user_drop=drop)
    np.testing.assert_array_equal(z0[0], z1[0])  # dropped example: user inputs invisible
    assert np.abs(z0[1] - z1[1]).max() > 1e-3  # kept example: they matter


def test_head_vmapped_over_frames_equals_python_loop(params):
    rng = np.random.default_rng(1)
    z = jnp.asarray(rng.normal(size=(2, 5, CFG.width)), jnp.float32)
    x = jnp.asarray(rng.normal(size=(2, 5, 56)), jnp.float32)
    t = jnp.asarray(rng.integers(0, 1000, size=(2, 5)), jnp.float32)
    out = np.asarray(jax.jit(lambda p, z, x, t: apply_head(p, CFG, z, x, t))(params["head"], z, x, t))
    one_frame = jax.jit(lambda p, z, x, t: apply_head(p, CFG, z, x, t))  # no leading axes: one frame
    loop = np.stack([
        np.stack([np.asarray(one_frame(params["head"], z[i, j], x[i, j], t[i, j])) for j in range(5)])
        for i in range(2)
    ])
    np.testing.assert_allclose(out, loop, rtol=1e-5, atol=1e-6)
    assert out.shape == (2, 5, 56) and np.abs(out).max() > 0


def test_hoisted_head_equals_the_per_frame_head(params):
    # The sampler's path (Dense(z) once, one timestep embedding per row) == the training path.
    rng = np.random.default_rng(2)
    z = jnp.asarray(rng.normal(size=(3, 2, 5, CFG.width)), jnp.float32)
    x = jnp.asarray(rng.normal(size=(3, 2, 5, 56)), jnp.float32)
    t = jnp.asarray([0.0, 417.0, 999.0])
    plain = jax.jit(lambda p: apply_head(p, CFG, z, x, jnp.broadcast_to(t[:, None, None], (3, 2, 5))))
    hoisted = jax.jit(lambda p: apply_head_hoisted(p, CFG, head_condition(p, CFG, z), x, t))
    ref, got = np.asarray(plain(params["head"])), np.asarray(hoisted(params["head"]))
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    assert np.abs(ref[0] - ref[1]).max() > 1e-3  # the timestep matters
    # The precomputed-modulation path (every adaLN modulation from c = TimestepEmbedding(t) + Dense(z)).

    def modulated(p):
        c = head_condition(p, CFG, z) + time_embedding(p, CFG, t)[:, None, None]
        return apply_head_modulated(p, CFG, x, head_modulations(p, CFG, c))

    np.testing.assert_allclose(np.asarray(jax.jit(modulated)(params["head"])), ref, rtol=1e-5, atol=1e-5)
    mods = head_modulations(params["head"], CFG, z[0, 0])
    assert [m.shape for m in mods] == [(5, 3 * CFG.head_width)] * CFG.head_blocks + [(5, 2 * CFG.head_width)]
    with pytest.raises(ValueError, match="expected 4 modulations"):
        apply_head_modulated(params["head"], CFG, x[0, 0], mods[:-1])


@pytest.mark.slow
def test_fresh_diffusion_head_predicts_zero_and_has_a_gradient():
    head = init_head(CFG, jax.random.key(0))
    z, x = jnp.ones((4, CFG.width)), jnp.ones((4, 56))
    t = jnp.full((4,), 10.0)
    np.testing.assert_array_equal(np.asarray(apply_head(head, CFG, z, x, t)), 0.0)
    g = jax.jit(jax.grad(lambda p: jnp.sum(apply_head(p, CFG, z, x, t) * jnp.arange(56.0)[None])))(head)
    assert float(jnp.abs(g["final"]["out"]["kernel"]).sum()) > 0
    with pytest.raises(ValueError, match="noisy frames"):
        apply_head(head, CFG, z)


@pytest.mark.slow
def test_learned_sigma_head_doubles_output_and_mlp_head_works():
    cfg = TimarConfig.small(**{**CFG.__dict__, "learn_sigma": True})
    p = _perturbed(init_params(cfg, jax.random.key(0)))
    out = apply_head(p["head"], cfg, jnp.ones((3, cfg.width)), jnp.ones((3, 56)), jnp.zeros((3,)))
    assert out.shape == (3, 112)
    mlp = TimarConfig.small(**{**CFG.__dict__, "head": "mlp"})
    pm = init_params(mlp, jax.random.key(0))
    assert apply_head(pm["head"], mlp, jnp.ones((3, mlp.width))).shape == (3, 56)


def test_positional_table_starts_frame_aligned_across_spans():
    from jaxtalk.models.timar.encoder import aligned_position_init
    from jaxtalk.models.timar.tokens import turn_layout

    cfg = TimarConfig.small(width=16, max_turns=2, frames_per_turn=3)
    table = np.asarray(aligned_position_init(cfg)(None, (2 * cfg.tokens_per_turn, 16)))
    lay = turn_layout(3)
    frame_part = table[:, :12]  # the last quarter codes the turn slot
    for j in range(3):
        rows = frame_part[np.flatnonzero(lay.frame == j)]  # frame j in the four spans of turn 0
        np.testing.assert_array_equal(rows, np.broadcast_to(rows[0], rows.shape))
    # Different frames and separators have different codes; the two turns share frame codes but
    # differ in the turn channels.
    codes = {tuple(np.round(r, 6)) for r in frame_part[: cfg.tokens_per_turn]}
    assert len(codes) == 3 + 10
    np.testing.assert_array_equal(frame_part[: cfg.tokens_per_turn], frame_part[cfg.tokens_per_turn :])
    assert np.abs(table[0, 12:] - table[cfg.tokens_per_turn, 12:]).max() > 0.1


def test_config_presets_training_settings_and_errors():
    paper = TimarConfig.paper()
    assert (paper.width, paper.num_layers, paper.num_heads, paper.head_width, paper.head_blocks) == (1024, 16, 16, 1024, 3)
    assert paper.tokens_per_turn == 110 and paper.num_timesteps == 1000 and paper.sample_steps == 5
    assert TimarConfig.small().width < paper.width
    # The paper's (and MAR's) training and sampling: r ~ TN[0.7, 1], 4 draws per frame, learned variance, DDPM.
    assert (paper.mask_ratio_min, paper.diffusion_batch_mul, paper.learn_sigma, paper.sampler) == (0.7, 4, True, "ddpm")
    from jaxtalk.runs import model_spec

    settings = model_spec("timar").settings("paper")
    assert (settings.lr, settings.batch_size, settings.warmup_steps, settings.final_lr_ratio) == (1e-4, 32, 100, 1.0)
    small = model_spec("timar").settings("small")
    assert (small.lr, small.batch_size, TimarConfig.small().sampler) == (1e-3, 16, "ddim")
    for bad in ({"width": 30, "num_heads": 4}, {"head": "x"}, {"attention": "causal"}, {"mask_ratio_min": 1.5},
                {"cfg_dropout": 1.0}, {"num_layers": 0}, {"sample_steps": 2000}, {"param_dim": 50}, {"sampler": "euler"}):
        with pytest.raises(ValueError):
            TimarConfig.small(**bad)
