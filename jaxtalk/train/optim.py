"""Optimiser configuration: AdamW with linear warm-up + cosine decay, global-norm clipping, and a
trainable mask that freezes part of the parameters (no update, no weight decay, no Adam moments)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax
import optax

__all__ = ["OptimConfig", "make_schedule", "make_optimizer", "trainable_mask", "path_name"]

PyTree = Any
# A predicate on ("encoder/dense/kernel", leaf) or a pytree of bools with the params' structure.
Trainable = Callable[[str, Any], bool] | PyTree | None


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """Static optimiser settings (a change recompiles the train step).

    Attributes:
        lr: peak learning rate reached at the end of the warm-up.
        weight_decay: decoupled AdamW weight decay (scaled by the scheduled learning rate).
        warmup_steps: linear warm-up from 0 to ``lr`` over this many steps.
        total_steps: cosine decay ends here (learning rate ``lr * final_lr_ratio``); also the
            default training length of :func:`jaxtalk.train.train`.
        clip_norm: clip the global gradient norm (of the trainable leaves) to this; None: no clip.
        b1, b2, eps: Adam moments' decay rates and epsilon.
        ema_decay: keep an exponential moving average of the parameters with this decay (None: off).
            The average is bias-corrected (``jaxtalk.train.ema``): after ``t`` steps it is the mean
            of the parameters after steps ``1..t`` weighted ``(1 - d) d**(t-i) / (1 - d**t)``, with
            no weight left on the initialisation; ``1 / (1 - d)`` steps is its time scale.
        final_lr_ratio: learning rate at ``total_steps`` as a fraction of ``lr``.
    """

    lr: float = 1e-4
    weight_decay: float = 1e-2
    warmup_steps: int = 100
    total_steps: int = 10_000
    clip_norm: float | None = 1.0
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    ema_decay: float | None = None
    final_lr_ratio: float = 0.0

    def __post_init__(self) -> None:
        checks = {
            "lr": self.lr > 0 and math.isfinite(self.lr),
            "weight_decay": self.weight_decay >= 0,
            "total_steps": self.total_steps >= 1,
            "warmup_steps": 0 <= self.warmup_steps <= self.total_steps,
            "clip_norm": self.clip_norm is None or self.clip_norm > 0,
            "b1": 0 <= self.b1 < 1,
            "b2": 0 <= self.b2 < 1,
            "eps": self.eps >= 0,
            "ema_decay": self.ema_decay is None or 0 <= self.ema_decay < 1,
            "final_lr_ratio": 0 <= self.final_lr_ratio <= 1,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"OptimConfig.{name} is invalid: {getattr(self, name)!r} ({self})")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (stored in checkpoint metadata)."""
        return dataclasses.asdict(self)


def make_schedule(config: OptimConfig) -> optax.Schedule:
    """Learning rate per step: linear 0 -> lr over ``warmup_steps``, cosine to the end value.

    Args:
        config: optimiser settings.

    Returns:
        ``schedule(step) -> lr`` (jit-able).
    """
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0,
        peak_value=config.lr,
        warmup_steps=config.warmup_steps,
        decay_steps=config.total_steps,
        end_value=config.lr * config.final_lr_ratio,
    )


def path_name(path: tuple[Any, ...]) -> str:
    """``"encoder/dense/kernel"`` for a pytree key path (dict keys, attributes, sequence indices)."""
    parts = []
    for k in path:
        for attr in ("key", "name", "idx"):
            if hasattr(k, attr):
                parts.append(str(getattr(k, attr)))
                break
        else:
            parts.append(str(k))
    return "/".join(parts)


def trainable_mask(params: PyTree, trainable: Trainable) -> PyTree:
    """Resolve ``trainable`` to a pytree of Python bools with the structure of ``params``.

    Args:
        params: parameter pytree.
        trainable: None (all trainable), a predicate ``(path_name, leaf) -> bool``, or a pytree of
            bools with the structure of ``params``.

    Returns:
        Pytree of bools (static, so it can select code paths at trace time).

    Raises:
        ValueError: a bool pytree whose structure differs from ``params``, or no trainable leaf.
    """
    if trainable is None:
        mask = jax.tree.map(lambda _: True, params)
    elif callable(trainable):
        mask = jax.tree_util.tree_map_with_path(lambda p, x: bool(trainable(path_name(p), x)), params)
    else:
        want, got = jax.tree.structure(params), jax.tree.structure(trainable)
        if want != got:
            raise ValueError(f"trainable mask structure {got} does not match the params structure {want}")
        mask = jax.tree.map(bool, trainable)
    if not any(jax.tree.leaves(mask)):
        raise ValueError("trainable selects no parameter: every leaf would be frozen")
    return mask


def make_optimizer(config: OptimConfig, mask: PyTree | None = None) -> optax.GradientTransformation:
    """AdamW + schedule + global-norm clipping on trainable leaves; frozen leaves get zero updates.

    ``optax.multi_transform`` gives frozen leaves ``set_to_zero`` so they carry no Adam moments and
    weight decay never reaches them, and the clipping norm is computed over the trainable gradients
    only.

    Args:
        config: optimiser settings.
        mask: pytree of bools from :func:`trainable_mask` (None: everything trainable).

    Returns:
        The optax gradient transformation.
    """
    parts = [] if config.clip_norm is None else [optax.clip_by_global_norm(config.clip_norm)]
    parts.append(
        optax.adamw(
            make_schedule(config), b1=config.b1, b2=config.b2, eps=config.eps, weight_decay=config.weight_decay
        )
    )
    tx = optax.chain(*parts)
    if mask is None:
        return tx
    labels = jax.tree.map(lambda t: "trainable" if t else "frozen", mask)
    return optax.multi_transform({"trainable": tx, "frozen": optax.set_to_zero()}, labels)
