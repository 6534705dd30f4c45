"""TIMAR streaming: cached == recomputed windows, sliding window, one compiled step, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models.timar import TimarConfig, init_params
import jaxtalk.models.timar.streaming as stream_mod
from jaxtalk.models.turns.streams import to_turns
from jaxtalk.models.timar.sampling import conditions as _conditions_eager
from jaxtalk.models.timar.sampling import sample_frames as _sample_frames_eager
from jaxtalk.models.timar.streaming import stream_condition, stream, init_stream, stream_step

conditions = jax.jit(_conditions_eager, static_argnums=1, static_argnames="guidance")
sample_frames = jax.jit(_sample_frames_eager, static_argnums=1, static_argnames=("sample_steps", "sampler"))


CFG = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=32, speech_dim=8, max_turns=4, frames_per_turn=5)
B, F = 2, 5



@jax.jit
def _perturb(p, key):
    # Zero-initialised adaLN layers make a fresh head output exactly 0; perturb so tests see signal.
    leaves, tree = jax.tree.flatten(p)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(tree, [x + 0.05 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])


@pytest.fixture(scope="module")
def params():
    p = init_params(CFG, jax.random.key(0))
    return _perturb(p, jax.random.key(11))


def _streams(turns, seed=0):
    rng = np.random.default_rng(seed)
    t = turns * F
    return (rng.normal(size=(B, t, 8)).astype(np.float32), rng.normal(size=(B, t, 56)).astype(np.float32),
            rng.normal(size=(B, t, 8)).astype(np.float32))


def _window_reference(config, params, s, lo, hi):
    # Full recomputation: the window's turns lo..hi at slots 0..hi-lo, last turn's conditions.
    win = [to_turns(jnp.asarray(x[:, lo * F : (hi + 1) * F]), F) for x in s]
    zc, zu = conditions(params, config, *win)
    return np.asarray(jnp.concatenate([zc[:, -1], zu[:, -1]]))


@pytest.mark.slow
@pytest.mark.parametrize("context", [0, 1, 3])
def test_cached_stream_equals_recomputed_window(params, context):
    s = _streams(6)
    state = init_stream(CFG, jax.random.key(0), batch=B, context=context)
    for t in range(6):
        sl = slice(t * F, (t + 1) * F)
        state, z = stream_condition(params, CFG, state, s[0][:, sl], s[1][:, sl], s[2][:, sl])
        ref = _window_reference(CFG, params, s, max(0, t - context), t)
        np.testing.assert_allclose(np.asarray(z), ref, atol=1e-5, rtol=1e-5)
    assert int(state.turn) == 6


@pytest.mark.slow
def test_bidirectional_stream_recomputes_the_window(params):
    bi = TimarConfig.small(**{**CFG.__dict__, "attention": "bidirectional"})
    s = _streams(4)
    state = init_stream(bi, jax.random.key(0), batch=B, context=2)
    for t in range(4):
        sl = slice(t * F, (t + 1) * F)
        state, z = stream_condition(params, bi, state, s[0][:, sl], s[1][:, sl], s[2][:, sl])
        np.testing.assert_allclose(np.asarray(z), _window_reference(bi, params, s, max(0, t - 2), t), atol=1e-5)


@pytest.mark.slow
def test_stream_step_samples_with_the_window_conditions_and_compiles_once(params):
    s = _streams(5)
    context = 2
    state = init_stream(CFG, jax.random.key(0), batch=B, context=context)
    before = stream_mod._step._cache_size()
    for t in range(5):
        sl = slice(t * F, (t + 1) * F)
        key = jax.random.fold_in(jax.random.key(0), t)  # turn t's key under the one key policy
        state, x = stream_step(params, CFG, state, s[0][:, sl], s[1][:, sl], s[2][:, sl], cfg_scale=1.0 + 0.3 * t)
        z = _window_reference(CFG, params, s, max(0, t - context), t)
        ref = sample_frames(params, CFG, jnp.asarray(z[:B]), jnp.asarray(z[B:]), key, cfg_scale=1.0 + 0.3 * t,
                            sample_steps=CFG.sample_steps)
        np.testing.assert_allclose(np.asarray(x), np.asarray(ref), atol=1e-4)
    # Two programs (filling, sliding) serve every turn and every scale: a second stream with new
    # scales compiles nothing.
    compiled = stream_mod._step._cache_size()
    assert compiled - before <= 2
    state = init_stream(CFG, jax.random.key(0), batch=B, context=context)
    for t in range(4):
        sl = slice(t * F, (t + 1) * F)
        state, _ = stream_step(params, CFG, state, s[0][:, sl], s[1][:, sl], s[2][:, sl], cfg_scale=2.0 - 0.1 * t)
    assert stream_mod._step._cache_size() == compiled


def test_stream_under_an_outer_jit_uses_one_program_with_the_same_outputs(params):
    # Under an outer trace the turn counter is abstract: the lax.cond program must agree with the
    # host-dispatched filling/sliding programs on both kinds of turn.
    s = _streams(4)
    cond = jax.jit(lambda st, a, b, c: stream_mod._condition(params, CFG, st, a, b, c, True, "auto"))
    state_h = init_stream(CFG, jax.random.key(0), batch=B, context=1)
    state_j = init_stream(CFG, jax.random.key(0), batch=B, context=1)
    for t in range(4):
        sl = slice(t * F, (t + 1) * F)
        turn = tuple(jnp.asarray(x[:, sl]) for x in s)
        state_h, z_h = stream_condition(params, CFG, state_h, *turn)
        state_j, z_j = cond(state_j, *turn)
        np.testing.assert_allclose(np.asarray(z_j), np.asarray(z_h), atol=1e-5)


@pytest.mark.slow
def test_stream_causality_future_turn_does_not_change_past_outputs(params):
    s = _streams(4)
    s2 = tuple(x.copy() for x in s)
    s2[0][:, 3 * F :] += 4.0
    s2[1][:, 3 * F :] -= 2.0
    a = np.asarray(stream(params, CFG, *s, jax.random.key(2), context=1))
    b = np.asarray(stream(params, CFG, *s2, jax.random.key(2), context=1))
    np.testing.assert_array_equal(a[:, : 3 * F], b[:, : 3 * F])
    assert np.abs(a[:, 3 * F :] - b[:, 3 * F :]).max() > 1e-4
    # The temperature reaches every turn's sampler: at 0 the stream no longer depends on the key.
    c0 = np.asarray(stream(params, CFG, *s, jax.random.key(2), context=1, temperature=0.0))
    c1 = np.asarray(stream(params, CFG, *s, jax.random.key(3), context=1, temperature=0.0))
    np.testing.assert_array_equal(c0, c1)
    assert np.abs(c0 - a).max() > 1e-3


def test_stream_without_temperature_samples_at_mars_default_of_one(params):
    s = _streams(2)
    default = np.asarray(stream(params, CFG, *s, jax.random.key(2), context=1))
    one = np.asarray(stream(params, CFG, *s, jax.random.key(2), context=1, temperature=1.0))
    half = np.asarray(stream(params, CFG, *s, jax.random.key(2), context=1, temperature=0.5))
    np.testing.assert_array_equal(default, one)
    assert np.abs(default - half).max() > 1e-3


def test_stream_rejects_bad_input(params):
    s = _streams(1)
    with pytest.raises(ValueError, match="max_turns"):
        init_stream(CFG, jax.random.key(0), batch=B, context=4)  # window of 5 turns > max_turns=4
    with pytest.raises(ValueError, match="non-negative"):
        init_stream(CFG, jax.random.key(0), batch=B, context=-1)
    state = init_stream(CFG, jax.random.key(0), batch=B, context=1)
    with pytest.raises(ValueError, match="one turn"):
        stream_step(params, CFG, state, s[0][:, :3], s[1][:, :3], s[2][:, :3])
    with pytest.raises(ValueError, match="aligned|one turn"):
        stream_step(params, CFG, state, s[0], s[1][:1], s[2])
    with pytest.raises(ValueError, match="NaN"):
        stream_step(params, CFG, state, s[0], np.full_like(s[1], np.nan), s[2])
    with pytest.raises(ValueError, match="stream state"):
        stream_step(params, CFG, state, s[0], s[1], s[2], guidance=False)


def test_stream_and_stream_step_leave_every_caller_argument_usable(params):
    # The step donates its state; nothing the caller passed in may be deleted by that.
    s = tuple(jnp.asarray(x) for x in _streams(2))
    key = jax.random.key(5)
    stream(params, CFG, *s, key, context=1)
    state = init_stream(CFG, key, batch=B, context=1)
    stream_step(params, CFG, state, *(x[:, :F] for x in s))
    for leaf in jax.tree.leaves((params, s)):
        assert not leaf.is_deleted()
    assert not key.is_deleted()
    jax.random.fold_in(key, 1)  # the caller samples offline with the same key afterwards


def test_a_stream_at_weight_zero_skips_the_unconditional_rows_with_the_same_turns(params):
    s = _streams(3)
    key = jax.random.key(2)
    skipped = np.asarray(stream(params, CFG, *s, key, context=1, cfg_scale=0.0))
    state = init_stream(CFG, key, batch=B, context=1, guidance=True)
    both = []
    for i in range(3):
        sl = slice(i * CFG.frames_per_turn, (i + 1) * CFG.frames_per_turn)
        state, x = stream_step(params, CFG, state, s[0][:, sl], s[1][:, sl], s[2][:, sl], cfg_scale=0.0)
        both.append(np.asarray(x))
    np.testing.assert_allclose(skipped, np.concatenate(both, axis=1), atol=1e-6)
