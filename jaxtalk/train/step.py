"""The jitted train step: value_and_grad of the model's loss, optax update, frozen leaves kept bitwise,
bias-corrected EMA, optional data-parallel shardings; the state is donated."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh

from jaxtalk.train.ema import ema_update
from jaxtalk.train.optim import OptimConfig, make_schedule
from jaxtalk.train.sharding import batch_sharding, replicated_sharding
from jaxtalk.train.state import TrainState

__all__ = ["make_train_step", "LossFn", "RESERVED_METRICS"]

PyTree = Any
# loss_fn(params, batch, key) -> (scalar loss, dict of scalar metrics)
LossFn = Callable[[PyTree, PyTree, jax.Array], tuple[jax.Array, dict[str, jax.Array]]]
RESERVED_METRICS = ("loss", "grad_norm", "lr")


def make_train_step(
    loss_fn: LossFn,
    tx: optax.GradientTransformation,
    config: OptimConfig,
    *,
    mask: PyTree | None = None,
    mesh: Mesh | None = None,
    donate: bool = True,
) -> Callable[[TrainState, PyTree], tuple[TrainState, dict[str, jax.Array]]]:
    """Build ``step(state, batch) -> (state, metrics)``, jitted with the state donated.

    Frozen leaves (``mask`` False) enter the loss through ``stop_gradient`` (so XLA can drop their
    gradient computation) and are copied through unchanged, which keeps them bitwise equal even for
    values like ``-0.0`` that ``p + 0`` would alter.

    Args:
        loss_fn: ``(params, batch, key) -> (loss, metrics)``; loss a scalar, metrics a dict of
            scalars whose names avoid ``RESERVED_METRICS``.
        tx: optimiser from :func:`jaxtalk.train.make_optimizer` (built with the same ``mask``).
        config: optimiser settings (schedule for the ``lr`` metric, EMA decay). The EMA is the
            bias-corrected average of the parameters after each update (weight 0 on the initial
            ones; :mod:`jaxtalk.train.ema`).
        mask: pytree of Python bools, True for trainable leaves (None: all trainable).
        mesh: data mesh: the batch is sharded on its leading axis, the state replicated.
        donate: donate the input state's buffers to the output state.

    Returns:
        The jitted step. ``metrics`` holds ``loss``, ``grad_norm`` (of the trainable gradients,
        before clipping), ``lr`` (used for this update) and the model's metrics.

    Raises:
        ValueError: (at the first call, while tracing) a non-scalar loss, or a metric that is not a
            scalar or uses a reserved name.
    """
    schedule = make_schedule(config)

    def step(state: TrainState, batch: PyTree) -> tuple[TrainState, dict[str, jax.Array]]:
        leaf_mask = mask if mask is not None else jax.tree.map(lambda _: True, state.params)
        key = jax.random.fold_in(state.rng, state.step)

        def objective(params):
            params = jax.tree.map(lambda p, m: p if m else jax.lax.stop_gradient(p), params, leaf_mask)
            loss, metrics = loss_fn(params, batch, key)
            _check_outputs(loss, metrics)  # before grad, whose own error would be less clear
            return loss, metrics

        (loss, model_metrics), grads = jax.value_and_grad(objective, has_aux=True)(state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        stepped = optax.apply_updates(state.params, updates)
        params = jax.tree.map(lambda new, old, m: new if m else old, stepped, state.params, leaf_mask)
        ema = state.ema_params
        if ema is not None:
            # Bias-corrected: this is update number step + 1, and the weight on the initial
            # parameters is 0 (see jaxtalk.train.ema); the count is the state's own step, so a
            # resumed run continues the same average bitwise.
            ema = ema_update(ema, params, config.ema_decay, leaf_mask, step=state.step + 1)
        trainable_grads = [g for g, m in zip(jax.tree.leaves(grads), jax.tree.leaves(leaf_mask)) if m]
        metrics = {
            **model_metrics,
            "loss": loss,
            "grad_norm": optax.tree.norm(trainable_grads),
            "lr": schedule(state.step),
        }
        new_state = state.replace(step=state.step + 1, params=params, opt_state=opt_state, ema_params=ema)
        return new_state, metrics

    donate_argnums = (0,) if donate else ()
    if mesh is None:
        return jax.jit(step, donate_argnums=donate_argnums)
    rep = replicated_sharding(mesh)
    return jax.jit(
        step,
        in_shardings=(rep, batch_sharding(mesh)),
        out_shardings=(rep, rep),
        donate_argnums=donate_argnums,
    )


def _check_outputs(loss: Any, metrics: Any) -> None:
    """Trace-time validation of what ``loss_fn`` returned."""
    if jnp.shape(loss) != ():
        raise ValueError(f"loss_fn must return a scalar loss, got shape {jnp.shape(loss)}")
    if not isinstance(metrics, dict):
        raise ValueError(f"loss_fn must return (loss, dict of metrics), got metrics of type {type(metrics).__name__}")
    for name, value in metrics.items():
        if name in RESERVED_METRICS:
            raise ValueError(f"loss_fn metric name {name!r} is reserved by the train loop ({RESERVED_METRICS})")
        if jnp.shape(value) != ():
            raise ValueError(f"loss_fn metric {name!r} must be a scalar, got shape {jnp.shape(value)}")
