"""Helpers shared by the ``test_nn_*`` files (this module holds no tests).

The layer tests run many tiny programs, where XLA compile time dominates; two things keep them fast:
the suite's default of most XLA optimisations off (tests/conftest.py), and

* ``random_params``: parameters drawn in NumPy for the shapes that ``module.init`` would create,
  found by ``jax.eval_shape`` (tracing only). Compiling the initialisers (truncated normals) costs
  more than the rest of a test; tests that check initial values use ``init`` itself.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def random_params(module: Any, *args: Any, seed: int = 0, scale: float = 0.3, **kwargs: Any) -> Any:
    """Variables shaped like ``module.init(key, *args, **kwargs)``, entries ``scale * N(0, 1)``."""
    shapes = jax.eval_shape(functools.partial(module.init, **kwargs), jax.random.key(0), *args)
    rng = np.random.default_rng(seed)
    return jax.tree_util.tree_map(
        lambda s: jnp.asarray(scale * rng.standard_normal(s.shape), s.dtype), shapes
    )
