"""Time embeddings, adaLN blocks and the MLP: hand-computed values, init identities, references."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import perturbed
from test_nn_support import random_params

from jaxtalk.nn import (
    MLP,
    AdaLNFinalLayer,
    AdaLNResBlock,
    TimestepEmbedding,
    modulate,
    sinusoidal_embedding,
)



# dim 4, max_period 1e4, freq_shift 0: frequencies [1, 1e4^(-1/2) = 0.01].
SIN_COS_T1 = [0.8414709848, 0.0099998333, 0.5403023059, 0.9999500004]  # [sin 1, sin .01, cos 1, cos .01]
SIN_COS_T2 = [0.9092974268, 0.0199986667, -0.4161468365, 0.9998000067]


def test_sinusoidal_hand_computed_sin_cos_and_cos_sin():
    t = jnp.array([0.0, 1.0, 2.0])
    np.testing.assert_allclose(
        sinusoidal_embedding(t, 4), [[0, 0, 1, 1], SIN_COS_T1, SIN_COS_T2], atol=1e-6
    )
    cos_sin = [[1, 1, 0, 0], SIN_COS_T1[2:] + SIN_COS_T1[:2], SIN_COS_T2[2:] + SIN_COS_T2[:2]]
    np.testing.assert_allclose(sinusoidal_embedding(t, 4, order="cos_sin"), cos_sin, atol=1e-6)


def test_sinusoidal_odd_dim_pads_one_zero_and_keeps_leading_axes():
    t = jnp.array([[1.0], [2.0]])  # leading axes (2, 1)
    emb = sinusoidal_embedding(t, 5)
    assert emb.shape == (2, 1, 5)
    np.testing.assert_allclose(emb[:, 0], [SIN_COS_T1 + [0.0], SIN_COS_T2 + [0.0]], atol=1e-6)


def test_sinusoidal_scale_max_period_and_freq_shift():
    # scale multiplies t: 1000 * 0.001 = 1.
    np.testing.assert_allclose(
        sinusoidal_embedding(jnp.array(0.001), 4, scale=1000.0), SIN_COS_T1, atol=1e-6
    )
    # max_period 100 -> frequencies [1, 0.1].
    np.testing.assert_allclose(
        sinusoidal_embedding(jnp.array(1.0), 4, max_period=100.0),
        [0.8414709848, 0.0998334166, 0.5403023059, 0.9950041653],
        atol=1e-6,
    )
    # freq_shift 1 (CosyVoice) -> frequencies [1, 1e4^(-1/(2-1)) = 1e-4].
    np.testing.assert_allclose(
        sinusoidal_embedding(jnp.array(1.0), 4, freq_shift=1.0),
        [0.8414709848, 1e-4, 0.5403023059, 1.0],
        atol=1e-6,
    )


def test_sinusoidal_matches_cosyvoice_and_dit_conventions():
    """Against the two reference formulas written out independently in float64."""
    t = np.array([0.0, 0.137, 0.5, 0.999])
    half = 160
    freqs = np.exp(np.arange(half) * -(math.log(10000) / (half - 1)))
    args = 1000 * t[:, None] * freqs[None]
    cosyvoice = np.concatenate([np.sin(args), np.cos(args)], axis=-1)
    got = sinusoidal_embedding(jnp.asarray(t, jnp.float32), 320, scale=1000.0, freq_shift=1.0)
    np.testing.assert_allclose(got, cosyvoice, atol=2e-4)  # float32 arguments up to 1000 rad

    steps = np.array([0, 250, 999])
    freqs = np.exp(-math.log(10000) * np.arange(128) / 128)
    args = steps[:, None] * freqs[None]
    dit = np.concatenate([np.cos(args), np.sin(args)], axis=-1)
    got = sinusoidal_embedding(jnp.asarray(steps, jnp.int32), 256, order="cos_sin")
    np.testing.assert_allclose(got, dit, atol=2e-4)


def test_sinusoidal_errors():
    with pytest.raises(ValueError, match="dim >= 2"):
        sinusoidal_embedding(jnp.zeros(3), 1)
    with pytest.raises(ValueError, match="freq_shift"):
        sinusoidal_embedding(jnp.zeros(3), 2, freq_shift=1.0)  # half - shift = 0
    with pytest.raises(ValueError, match="max_period"):
        sinusoidal_embedding(jnp.zeros(3), 4, max_period=0.0)


def test_timestep_embedding_is_sinusoid_dense_silu_dense(key):
    t = jnp.array([[0.1, 0.7, 0.3], [0.0, 1.0, 0.5]])
    module = TimestepEmbedding(12, hidden_features=10, frequency_dim=8, order="sin_cos", scale=1000.0)
    params = random_params(module, t)["params"]
    p = jax.tree_util.tree_map(np.asarray, params)
    emb = np.asarray(sinusoidal_embedding(t, 8, scale=1000.0), np.float64)
    h = emb @ p["hidden"]["kernel"] + p["hidden"]["bias"]
    h = h / (1 + np.exp(-h))
    expected = h @ p["out"]["kernel"] + p["out"]["bias"]
    out = module.apply({"params": params}, t)
    assert out.shape == (2, 3, 12)
    np.testing.assert_allclose(out, expected, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# adaLN


def _perturbed(params, key, scale=0.3):
    return perturbed(params, key, scale=scale)


def _ln(x, eps=1e-6):
    return (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + eps)


def _silu(x):
    return x / (1 + np.exp(-x))


def test_adaln_block_is_identity_at_init_and_follows_the_formula_after_perturbation(key):
    x = jax.random.normal(key, (2, 5, 8))
    c = jax.random.normal(jax.random.fold_in(key, 1), (2, 5, 6))
    block = AdaLNResBlock()
    params = block.init(key, x, c)
    np.testing.assert_array_equal(block.apply(params, x, c), x)

    params = _perturbed(params, jax.random.fold_in(key, 2))
    p = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params["params"])
    xn, cn = np.asarray(x, np.float64), np.asarray(c, np.float64)
    mod = _silu(cn) @ p["modulation"]["kernel"] + p["modulation"]["bias"]
    shift, scale, gate = np.split(mod, 3, axis=-1)
    h = _ln(xn) * p["norm"]["scale"] + p["norm"]["bias"]
    h = h * (1 + scale) + shift
    mlp = p["mlp"]
    h = _silu(h @ mlp["dense_0"]["kernel"] + mlp["dense_0"]["bias"])
    h = h @ mlp["dense_1"]["kernel"] + mlp["dense_1"]["bias"]
    out = block.apply(params, x, c)
    assert np.abs(out - x).max() > 1e-2
    np.testing.assert_allclose(out, xn + gate * h, atol=1e-4)


def test_adaln_final_layer_outputs_zeros_at_init_and_follows_the_formula_after(key):
    x = jax.random.normal(key, (3, 8))
    c = jax.random.normal(jax.random.fold_in(key, 1), (3, 6))
    layer = AdaLNFinalLayer(out_features=5)
    params = layer.init(key, x, c)
    out = layer.apply(params, x, c)
    assert out.shape == (3, 5)
    np.testing.assert_array_equal(out, np.zeros((3, 5)))

    params = _perturbed(params, jax.random.fold_in(key, 2))
    p = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params["params"])
    mod = _silu(np.asarray(c, np.float64)) @ p["modulation"]["kernel"] + p["modulation"]["bias"]
    shift, scale = np.split(mod, 2, axis=-1)
    h = _ln(np.asarray(x, np.float64)) * (1 + scale) + shift
    expected = h @ p["out"]["kernel"] + p["out"]["bias"]
    out = layer.apply(params, x, c)
    assert np.abs(out).max() > 1e-2
    np.testing.assert_allclose(out, expected, atol=1e-4)


def test_zero_init_still_lets_gradients_reach_the_modulation(key):
    """Zero-initialised gates must not stall training: the gate/out weights get gradients."""
    x = jax.random.normal(key, (4, 8))
    c = jax.random.normal(jax.random.fold_in(key, 1), (4, 6))
    block, final = AdaLNResBlock(), AdaLNFinalLayer(out_features=3)
    pb, pf = block.init(key, x, c), final.init(key, x, c)
    loss = lambda pb, pf: jnp.sum(final.apply(pf, block.apply(pb, x, c), c) - 1.0) ** 2  # noqa: E731
    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))
    gb, gf = grad(pb, pf)
    assert np.abs(gf["params"]["out"]["kernel"]).max() > 0
    # Once the output layer moves, the block's gate columns (last third of the modulation) follow.
    pf = _perturbed(pf, jax.random.fold_in(key, 2))
    gb, _ = grad(pb, pf)
    gate_grad = gb["params"]["modulation"]["kernel"][:, 16:]
    assert np.abs(gate_grad).max() > 0


def test_modulate():
    x, shift, scale = jnp.array([1.0, 2.0]), jnp.array([0.5, -1.0]), jnp.array([1.0, -0.5])
    np.testing.assert_allclose(modulate(x, shift, scale), [2.5, 0.0])


# ---------------------------------------------------------------------------------------------
# MLP


def test_mlp_layers_activation_placement_and_dropout(key):
    x = jax.random.normal(key, (2, 3, 4))
    mlp = MLP((6, 5), activation=jax.nn.relu)
    params = random_params(mlp, x)
    p = jax.tree_util.tree_map(np.asarray, params["params"])
    h = np.maximum(np.asarray(x) @ p["dense_0"]["kernel"] + p["dense_0"]["bias"], 0)
    expected = h @ p["dense_1"]["kernel"] + p["dense_1"]["bias"]
    np.testing.assert_allclose(mlp.apply(params, x), expected, atol=1e-5)
    final = MLP((6, 5), activation=jax.nn.relu, activate_final=True).apply(params, x)
    np.testing.assert_allclose(final, np.maximum(expected, 0), atol=1e-5)

    dropping = MLP((6, 5), activation=jax.nn.relu, dropout_rate=0.5)
    np.testing.assert_allclose(dropping.apply(params, x), expected, atol=1e-5)
    dropped = dropping.apply(params, x, deterministic=False, rngs={"dropout": jax.random.key(1)})
    assert np.abs(dropped - expected).max() > 1e-3
    with pytest.raises(ValueError, match="non-empty"):
        jax.eval_shape(MLP(()).init, key, x)
