"""adaLN layers fed precomputed modulations (jaxtalk.nn.adaln): same outputs, clear errors."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import perturbed

from jaxtalk.nn import AdaLNFinalLayer, AdaLNResBlock, adaln_modulation


def _perturbed(params, key):
    # Zero-initialised modulations would make every comparison trivially 0 == 0.
    return perturbed(params, key, scale=0.1)


def _silu(x):
    return x / (1 + np.exp(-x))


@pytest.mark.parametrize("layer", [AdaLNResBlock(), AdaLNFinalLayer(out_features=5)], ids=["block", "final"])
def test_precomputed_modulation_gives_the_same_output_as_the_condition(key, layer):
    x = jax.random.normal(key, (3, 4, 8))
    c = jax.random.normal(jax.random.fold_in(key, 1), (3, 4, 6))
    params = _perturbed(layer.init(key, x, c), jax.random.fold_in(key, 2))
    mod_params = params["params"]["modulation"]
    mod = adaln_modulation(mod_params, c)
    # Hand-computed SiLU(c) W + b in float64.
    expected = _silu(np.asarray(c, np.float64)) @ np.asarray(mod_params["kernel"], np.float64) + np.asarray(
        mod_params["bias"], np.float64
    )
    np.testing.assert_allclose(mod, expected, atol=1e-5)
    chunks = 3 if isinstance(layer, AdaLNResBlock) else 2
    assert mod.shape == (3, 4, chunks * 8)
    np.testing.assert_allclose(layer.apply(params, x, modulation=mod), layer.apply(params, x, c), atol=1e-6)
    # A different modulation changes the output (the argument is really used).
    assert np.abs(layer.apply(params, x, modulation=mod + 1.0) - layer.apply(params, x, c)).max() > 1e-2


def test_modulation_argument_errors(key):
    x = jax.random.normal(key, (2, 8))
    c = jax.random.normal(key, (2, 6))
    block = AdaLNResBlock()
    params = block.init(key, x, c)
    mod = adaln_modulation(params["params"]["modulation"], c)
    with pytest.raises(ValueError, match="exactly one"):
        block.apply(params, x, c, modulation=mod)
    with pytest.raises(ValueError, match="exactly one"):
        block.apply(params, x)
    with pytest.raises(ValueError, match="3 x 8 = 24"):
        block.apply(params, x, modulation=mod[..., :16])
    with pytest.raises(ValueError, match="does not match the modulation kernel"):
        adaln_modulation(params["params"]["modulation"], c[..., :5])
