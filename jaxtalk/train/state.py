"""The training state pytree."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jaxtalk.types import PRNGKeyArray

__all__ = ["TrainState", "create_train_state"]

PyTree = Any


@struct.dataclass
class TrainState:
    """Everything that changes during training; a pytree, donated to each jitted step.

    Attributes:
        step: number of optimiser steps taken (int32 scalar).
        params: model parameters.
        opt_state: optax optimiser state.
        ema_params: bias-corrected exponential moving average of ``params`` over the updates done
            so far (the initial parameters have weight 0 once ``step >= 1``; equal to them at step
            0); None when EMA is off. Stored debiased, so it is what evaluation and checkpoint
            readers use as is.
        rng: base PRNG key; step ``s`` uses ``fold_in(rng, s)``, so resuming needs only ``step``.
    """

    # Leaves are typed loosely: JAX rebuilds this pytree with abstract leaves (``ShapeDtypeStruct``
    # for jax.export, ``ArgInfo`` when lowering, shapes under tree maps), which array annotations
    # would reject under a runtime type checker. In a real state: an int32 scalar and a typed key.
    step: PyTree
    params: PyTree
    opt_state: PyTree
    ema_params: PyTree | None
    rng: PyTree

    @property
    def eval_params(self) -> PyTree:
        """The parameters to evaluate or sample with: the EMA when it exists, else ``params``."""
        return self.params if self.ema_params is None else self.ema_params


def create_train_state(
    params: PyTree, tx: optax.GradientTransformation, key: PRNGKeyArray, *, ema: bool = False
) -> TrainState:
    """Fresh state at step 0.

    The parameters and the key are copied, so donating the state to the train step never invalidates the
    caller's ``params`` arrays.

    Args:
        params: initial parameters (pytree of float arrays).
        tx: optimiser from :func:`jaxtalk.train.make_optimizer`.
        key: base PRNG key for the per-step keys (a typed key, ``jax.random.key``).
        ema: keep an EMA of the parameters. Its buffer starts as a copy of ``params`` (what
            ``eval_params`` gives before the first update); the first bias-corrected update
            replaces it entirely.

    Returns:
        The state.

    Raises:
        ValueError: no parameter leaves, a non-floating or non-finite parameter, or a raw
            ``uint32`` key instead of a typed key.
    """
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    if not leaves:
        raise ValueError("params has no array leaves")
    for path, leaf in leaves:
        if not jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            raise ValueError(
                f"parameter {jax.tree_util.keystr(path)} has dtype {jnp.result_type(leaf)}; parameters must be floating"
            )
        # On the host: a one-off pass that would otherwise compile a tiny kernel per leaf shape.
        if not np.isfinite(np.asarray(leaf)).all():
            raise ValueError(f"parameter {jax.tree_util.keystr(path)} contains NaN or inf at initialisation")
    if not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        raise ValueError(f"key must be a typed PRNG key (jax.random.key), got dtype {key.dtype}")
    params = jax.tree.map(lambda x: jnp.array(x, copy=True), params)
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        opt_state=tx.init(params),
        ema_params=jax.tree.map(lambda x: jnp.array(x, copy=True), params) if ema else None,
        # A copy too: the state is donated, and the caller may reuse its key.
        rng=jax.random.wrap_key_data(jnp.array(jax.random.key_data(key), copy=True), impl=jax.random.key_impl(key)),
    )
