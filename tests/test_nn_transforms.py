"""Every kind of layer under jax.jit, jax.vmap over an extra axis, and bfloat16 computation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.masks import mask_to_bias
from jaxtalk.nn import (
    AdaLNResBlock,
    Conv1dBlock,
    GraphConv,
    MultiHeadAttention,
    ResnetBlock1D,
    TimestepEmbedding,
    normalized_adjacency,
)

from test_nn_support import random_params


T, C = 6, 16
MASK = jnp.arange(T)[None, :] < jnp.array([[T], [4]])
CAUSAL_BIAS = mask_to_bias(np.tril(np.ones((T, T), bool)))

# name -> (module factory taking dtype, example inputs (batch 2), extra keyword arguments)
CASES = {
    "attention": (
        lambda dtype: MultiHeadAttention(num_heads=4, head_dim=4, dtype=dtype),
        lambda x: (x,),
        {"bias": CAUSAL_BIAS},
    ),
    "conv_block": (lambda dtype: Conv1dBlock(C, dtype=dtype), lambda x: (x, MASK), {}),
    "resnet": (
        lambda dtype: ResnetBlock1D(C, causal=True, dtype=dtype),
        lambda x: (x, MASK, x[:, 0, :5]),
        {},
    ),
    "adaln": (lambda dtype: AdaLNResBlock(dtype=dtype), lambda x: (x, x[..., ::-1]), {}),
    "graph": (
        lambda dtype: GraphConv(8, normalized_adjacency([(i, i + 1) for i in range(T - 1)], T), dtype=dtype),
        lambda x: (x,),
        {},
    ),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_jit_vmap_and_bfloat16(key, name):
    factory, make_args, kwargs = CASES[name]
    x = jax.random.normal(key, (2, T, C))
    module = factory(None)
    params = random_params(module, *make_args(x), **kwargs)
    eager = module.apply(params, *make_args(x), **kwargs)

    jitted = jax.jit(lambda p, x: module.apply(p, *make_args(x), **kwargs))
    np.testing.assert_allclose(jitted(params, x), eager, atol=1e-5)

    # vmap over an extra leading axis of the inputs == the layer on each slice.
    xs = jnp.stack([x, 2.0 * x, -x])
    mapped = jax.jit(jax.vmap(lambda x: module.apply(params, *make_args(x), **kwargs)))(xs)
    for i in range(3):
        np.testing.assert_allclose(mapped[i], module.apply(params, *make_args(xs[i]), **kwargs), atol=1e-5)

    # bfloat16 computation with float32 parameters: bfloat16 out, close to the float32 result.
    low = jax.jit(lambda p, x: factory(jnp.bfloat16).apply(p, *make_args(x), **kwargs))(
        params, x.astype(jnp.bfloat16)
    )
    assert low.dtype == jnp.bfloat16
    scale = float(jnp.abs(eager).max())
    np.testing.assert_allclose(low.astype(jnp.float32), eager, atol=0.05 * scale)


def test_timestep_embedding_under_vmap_and_bfloat16(key):
    t = jnp.array([0.0, 0.3, 1.0])
    module = TimestepEmbedding(8, frequency_dim=16)
    params = random_params(module, t)
    eager = module.apply(params, t)
    mapped = jax.vmap(lambda s: module.apply(params, s))(t)  # scalar times under vmap
    np.testing.assert_allclose(mapped, eager, atol=1e-5)
    low = TimestepEmbedding(8, frequency_dim=16, dtype=jnp.bfloat16).apply(params, t)
    assert low.dtype == jnp.bfloat16
    np.testing.assert_allclose(low.astype(jnp.float32), eager, atol=0.05 * float(jnp.abs(eager).max()))
