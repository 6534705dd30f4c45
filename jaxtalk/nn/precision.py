"""Mixed precision: every model's ``compute_dtype`` setting (``--set compute_dtype=bfloat16``).

The policy (as DeepMind's ``jmp``: parameters in float32, computation in the compute dtype, outputs in
float32): a model's network runs through :func:`compute_in`, which casts the float32 leaves of its
parameters and inputs to the compute dtype and its floating outputs back to float32. So

* parameters, their gradients (the cast's transpose casts them back), the optimiser state and the
  EMA stay float32: only the network's copy of the weights is bfloat16;
* the matmuls and convolutions inside the network run in bfloat16: while the network runs, every
  matmul layer (Flax's ``Dense``, ``DenseGeneral``, ``Conv``, ``ConvTranspose``, ``Einsum`` and the
  jaxtalk layers registered with :func:`matmul_layer`) gets its floating inputs cast to the compute
  dtype (a Flax method interceptor, so a float32 value made inside the network, such as a
  sinusoidal time embedding or a float mask, cannot silently promote the layers after it back to
  float32), and the activations between them follow;
* normalisation statistics stay float32 (Flax's norms compute mean and variance in at least
  float32; :mod:`jaxtalk.nn.attention` computes logits and softmax in float32), and so do the losses
  and the samplers' states, which see only the float32 outputs.

``float32`` (every config's default) calls the function untouched, so float32 programs are bitwise
the ones without this module.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxtalk.types import COMPUTE_DTYPES, check_compute_dtype

__all__ = ["COMPUTE_DTYPES", "check_compute_dtype", "cast_floating", "compute_in", "matmul_layer", "MATMUL_LAYERS"]

PyTree = Any

# Layers whose inputs :func:`compute_in` casts to the compute dtype (their matmuls then run in it).
MATMUL_LAYERS: set[type] = {nn.Dense, nn.DenseGeneral, nn.Conv, nn.ConvTranspose, nn.Einsum}


def matmul_layer(cls: type) -> type:
    """Class decorator: register a Flax module that multiplies its inputs by its weights (its own
    ``self.param`` kernel), so that :func:`compute_in` runs it in the compute dtype too.

    Returns:
        ``cls`` itself.
    """
    MATMUL_LAYERS.add(cls)
    return cls


def _floating(x: Any) -> bool:
    dtype = getattr(x, "dtype", None)
    return dtype is not None and jnp.issubdtype(dtype, jnp.floating)


def cast_floating(tree: PyTree, dtype: Any, *, only: Any = jnp.float32) -> PyTree:
    """``tree`` with its floating leaves of dtype ``only`` (any floating dtype when None) cast to ``dtype``.

    Integer, boolean and key leaves and non-array leaves are returned as they are.

    Args:
        tree: any pytree.
        dtype: the target dtype.
        only: cast only leaves of this dtype (None: every floating leaf).

    Returns:
        The cast pytree.
    """
    def cast(x: Any) -> Any:
        if not _floating(x) or (only is not None and x.dtype != jnp.dtype(only)):
            return x
        return x.astype(dtype)

    return jax.tree.map(cast, tree)


def compute_in(dtype_name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` run in the compute dtype ``dtype_name``: its float32 arguments (parameters included,
    keyword arguments too) cast to it, its floating outputs cast back to float32.

    Args:
        dtype_name: one of :data:`COMPUTE_DTYPES` (``"float32"``: ``fn`` itself).
        fn: typically a Flax module's ``apply`` or a function of parameters.

    Returns:
        The wrapped function.

    Raises:
        ValueError: an unknown dtype name.
    """
    check_compute_dtype(dtype_name)
    if dtype_name == "float32":
        return fn
    dtype = jnp.dtype(dtype_name)

    layers = tuple(MATMUL_LAYERS)

    def to_compute(next_fun: Callable[..., Any], args: tuple, kwargs: dict, context: Any) -> Any:
        if context.method_name == "__call__" and isinstance(context.module, layers):
            args, kwargs = cast_floating(args, dtype, only=None), cast_floating(kwargs, dtype, only=None)
        return next_fun(*args, **kwargs)

    @functools.wraps(fn)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        with nn.intercept_methods(to_compute):
            out = fn(*cast_floating(args, dtype), **cast_floating(kwargs, dtype))
        return cast_floating(out, jnp.float32, only=dtype)

    return wrapped
