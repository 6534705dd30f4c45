"""``train``: the one training loop every jaxtalk model uses.

The model supplies ``loss_fn(params, batch, key) -> (loss, metrics)``; the loop owns the optimiser,
EMA, frozen parameters, data-parallel sharding, progress bar, periodic evaluation, checkpoints and
exact resumption (state, optimiser, EMA, RNG and data position).

Metrics stay on the device and are fetched every ``log_every`` steps (and before each checkpoint or
evaluation) so the host does not wait for every step; the non-finite-loss check runs on those
fetched values, so it never lets a NaN state reach a checkpoint.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh

from jaxtalk.train.checks import BatchSpec, check_finite
from jaxtalk.train.checkpoint import Checkpointer
from jaxtalk.train.optim import OptimConfig, Trainable, make_optimizer, trainable_mask
from jaxtalk.train.sharding import replicate, shard_batch
from jaxtalk.train.state import TrainState, create_train_state
from jaxtalk.train.step import LossFn, make_train_step
from jaxtalk.types import PRNGKeyArray

__all__ = ["train", "TrainResult", "NonFiniteLossError"]

PyTree = Any
# eval_fn(params, ema_params_or_None, step) -> dict of scalar metrics
EvalFn = Callable[[PyTree, PyTree | None, int], dict[str, Any]]


class NonFiniteLossError(FloatingPointError):
    """Training stopped because the loss became NaN/inf; the NaN state was not checkpointed.

    Attributes:
        step: the first step (1-based count of updates) whose loss was not finite.
        last_checkpoint_step: newest checkpoint on disk (None if none was written).
        history: history up to the failure.
    """

    def __init__(self, message: str, step: int, last_checkpoint_step: int | None, history: list[dict]) -> None:
        super().__init__(message)
        self.step = step
        self.last_checkpoint_step = last_checkpoint_step
        self.history = history


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        state: final train state (``state.eval_params`` is the EMA when enabled).
        history: one dict per step: ``step`` (updates done), ``loss``, ``metrics`` (all step metrics
            incl. ``grad_norm`` and ``lr``), ``time`` (seconds since the call started, taken when
            the metrics were fetched) and, at evaluation steps, ``eval`` (the eval metrics).
    """

    state: TrainState
    history: list[dict[str, Any]]


def train(
    loss_fn: LossFn,
    init_params: PyTree,
    data_iter: Iterable[PyTree],
    config: OptimConfig,
    *,
    key: PRNGKeyArray,
    max_steps: int | None = None,
    ckpt_dir: str | os.PathLike | None = None,
    resume: bool = True,
    save_every: int | None = None,
    keep_checkpoints: int = 3,
    async_checkpoints: bool = True,
    metadata: dict[str, Any] | None = None,
    eval_fn: EvalFn | None = None,
    eval_every: int | None = None,
    trainable: Trainable = None,
    mesh: Mesh | None = None,
    progress: bool = True,
    log_every: int = 10,
    check_batches: bool = True,
    variable_axes: Sequence[int] | None = None,
) -> TrainResult:
    """Train ``init_params`` on ``data_iter`` with AdamW (warm-up + cosine), clipping and optional EMA.

    Args:
        loss_fn: ``(params, batch, key) -> (scalar loss, dict of scalar metrics)``.
        init_params: initial parameters (copied; never donated).
        data_iter: iterator of batches (pytrees of arrays with a leading batch axis). If it has
            ``get_state()``/``set_state()`` (e.g. :class:`jaxtalk.data.batching.BatchIterator`) its
            position is checkpointed and restored; otherwise resuming warns that the data order
            restarts.
        config: optimiser settings; ``config.total_steps`` is the schedule length.
        key: base PRNG key (step ``s`` gets ``fold_in(key, s)``).
        max_steps: stop when ``state.step`` reaches this (default ``config.total_steps``).
        ckpt_dir: checkpoint directory (None: no checkpoints).
        resume: continue from the newest checkpoint in ``ckpt_dir`` if there is one (False with
            existing checkpoints is an error rather than a silent overwrite).
        save_every: also checkpoint every this many steps (the final step is always saved).
        keep_checkpoints: how many recent checkpoints to keep.
        async_checkpoints: write checkpoints in the background.
        metadata: JSON-serialisable record saved with each checkpoint (e.g. ``{"model": "toktalk"}``);
            the optimiser config and the batch spec are added.
        eval_fn: ``(params, ema_params or None, step) -> metrics``, called every ``eval_every``
            steps and at the end; its metrics go into the history and the progress bar.
        eval_every: evaluation period in steps (default: only at the end).
        trainable: which parameters train: None (all), a predicate ``(path, leaf) -> bool`` on
            ``"a/b/kernel"`` paths, or a pytree of bools. Frozen leaves stay bitwise unchanged.
        mesh: device mesh for data parallelism (batch sharded, state replicated).
        progress: show a tqdm bar with loss and steps/s.
        log_every: fetch metrics from the device every this many steps.
        check_batches: scan every batch for NaN/inf before its step (costs a host pass).
        variable_axes: batch axes allowed to change size between batches (default: the iterator's
            ``variable_axes`` attribute, else none). All other sizes must match the first batch.

    Returns:
        :class:`TrainResult` with the final state and per-step history.

    Raises:
        ValueError: bad settings; a batch with NaN/inf, a different structure/shape/dtype than the
            first batch (naming the array and both shapes), or a batch size not divisible by the
            mesh's device count; a corrupt checkpoint (naming the path).
        NonFiniteLossError: the loss became NaN/inf (names the step; nothing after the last good
            checkpoint is saved).
    """
    max_steps = config.total_steps if max_steps is None else int(max_steps)
    for name, value in (("max_steps", max_steps), ("log_every", log_every)):
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    for name, value in (("save_every", save_every), ("eval_every", eval_every)):
        if value is not None and value < 1:
            raise ValueError(f"{name} must be >= 1 or None, got {value}")
    if eval_every is not None and eval_fn is None:
        raise ValueError("eval_every is set but eval_fn is None")
    if variable_axes is None:
        variable_axes = tuple(getattr(data_iter, "variable_axes", ()))

    mask = trainable_mask(init_params, trainable)
    tx, step_fn = _step_for(loss_fn, config, jax.tree.structure(mask), tuple(jax.tree.leaves(mask)), mesh)
    state = create_train_state(init_params, tx, key, ema=config.ema_decay is not None)
    if mesh is not None:
        state = replicate(state, mesh)

    meta = {"config": config.to_dict(), **(metadata or {})}
    ckpt = None
    spec: BatchSpec | None = None
    has_position = hasattr(data_iter, "get_state") and hasattr(data_iter, "set_state")
    if ckpt_dir is not None:
        ckpt = Checkpointer(ckpt_dir, max_to_keep=keep_checkpoints, async_save=async_checkpoints)
    try:
        if ckpt is not None and not resume and ckpt.latest_step() is not None:
            raise ValueError(
                f"checkpoint directory {ckpt.directory} already holds checkpoints (latest step "
                f"{ckpt.latest_step()}); pass resume=True to continue it or choose an empty directory"
            )
        if ckpt is not None and resume and ckpt.latest_step() is not None:
            state, data_state, saved_meta = ckpt.restore(state)
            if has_position and data_state:
                data_iter.set_state(data_state)
            elif not has_position:
                warnings.warn(
                    f"resuming from {ckpt.directory} at step {int(state.step)} but data_iter has no "
                    "get_state/set_state: the data order restarts from its beginning",
                    stacklevel=2,
                )
            if "batch_spec" in saved_meta:
                spec = BatchSpec.from_json(saved_meta["batch_spec"])
            if saved_meta.get("config") != meta["config"]:
                warnings.warn(
                    f"optimiser config differs from the checkpoint's: {saved_meta.get('config')} -> {meta['config']}",
                    stacklevel=2,
                )
        loop = _Loop(
            state=state,
            step_fn=step_fn,
            data_iter=iter(data_iter),
            position=data_iter if has_position else None,
            ckpt=ckpt,
            meta=meta,
            spec=spec,
            mesh=mesh,
            check_batches=check_batches,
            variable_axes=tuple(variable_axes),
            eval_fn=eval_fn,
            eval_every=eval_every,
            save_every=save_every,
            log_every=log_every,
            progress=progress,
        )
        return loop.run(max_steps)
    finally:
        if ckpt is not None:
            ckpt.close()


@functools.lru_cache(maxsize=16)
def _step_for(
    loss_fn: LossFn, config: OptimConfig, mask_def: Any, mask_leaves: tuple[bool, ...], mesh: Mesh | None
) -> tuple[Any, Callable]:
    """The optimiser and jitted step for these static settings, built once per process.

    A new closure per :func:`train` call would miss jit's cache and recompile; resuming or
    re-running with the same loss function, config, mask and mesh reuses the compiled step.
    """
    mask = jax.tree.unflatten(mask_def, mask_leaves)
    tx = make_optimizer(config, mask)
    return tx, make_train_step(loss_fn, tx, config, mask=mask, mesh=mesh)


@dataclasses.dataclass
class _Loop:
    """Mutable driver state of one :func:`train` call (host side only)."""

    state: TrainState
    step_fn: Callable
    data_iter: Any
    position: Any
    ckpt: Checkpointer | None
    meta: dict
    spec: BatchSpec | None
    mesh: Mesh | None
    check_batches: bool
    variable_axes: tuple[int, ...]
    eval_fn: EvalFn | None
    eval_every: int | None
    save_every: int | None
    log_every: int
    progress: bool

    def run(self, max_steps: int) -> TrainResult:
        from tqdm.auto import tqdm  # deferred: keeps `import jaxtalk.train` light

        self.history: list[dict] = []
        self.pending: list[tuple[int, dict]] = []
        self.postfix: dict[str, str] = {}
        self.start = time.perf_counter()
        self.window = (int(self.state.step), self.start)  # (step, time) at the last fetch
        self.last_saved = self.ckpt.latest_step() if self.ckpt is not None else None
        step = int(self.state.step)
        data_state = self.position.get_state() if self.position is not None else None
        self.bar = tqdm(total=max_steps, initial=step, disable=not self.progress, desc="train", unit="step")
        try:
            while step < max_steps:
                try:
                    batch = next(self.data_iter)
                except StopIteration:
                    warnings.warn(f"data_iter ended after step {step}, before max_steps={max_steps}", stacklevel=3)
                    break
                batch = self._prepare(batch, step + 1)
                self.state, metrics = self.step_fn(self.state, batch)
                step += 1
                self.pending.append((step, metrics))
                data_state = self.position.get_state() if self.position is not None else None
                if step % self.log_every == 0:
                    self._flush()
                if self.eval_every is not None and step % self.eval_every == 0:
                    self._evaluate(step)
                if self.save_every is not None and step % self.save_every == 0:
                    self._save(step, data_state)
            self._flush()
            if self.eval_fn is not None and not (self.history and "eval" in self.history[-1]):
                self._evaluate(step)
            if self.ckpt is not None and self.last_saved != step and step > 0:
                self._save(step, data_state)
        finally:
            self.bar.close()
        return TrainResult(state=self.state, history=self.history)

    def _prepare(self, batch: PyTree, step: int) -> PyTree:
        if self.spec is None:
            self.spec = BatchSpec.from_batch(batch)
            self.meta["batch_spec"] = self.spec.to_json()
        else:
            self.spec.check(batch, self.variable_axes, step=step)
        if self.check_batches:
            check_finite(batch, step=step)
        if self.mesh is not None:
            return shard_batch(batch, self.mesh)  # raises if the batch does not divide the devices
        return batch

    def _flush(self) -> None:
        """Fetch pending metrics, append to the history, stop on a non-finite loss."""
        if not self.pending:
            return
        fetched = jax.device_get([m for _, m in self.pending])
        now = time.perf_counter()
        elapsed = now - self.start
        for (step, _), metrics in zip(self.pending, fetched):
            values = {k: float(np.asarray(v)) for k, v in metrics.items()}
            if not math.isfinite(values["loss"]):
                self.pending = []
                where = (
                    f"the last good checkpoint is step {self.last_saved} in {self.ckpt.directory}"
                    if self.ckpt is not None and self.last_saved is not None
                    else "no checkpoint was written"
                )
                raise NonFiniteLossError(
                    f"loss is {values['loss']} at step {step}; training stopped and this state was not "
                    f"saved ({where})",
                    step=step,
                    last_checkpoint_step=self.last_saved,
                    history=self.history,
                )
            self.history.append({"step": step, "loss": values["loss"], "metrics": values, "time": elapsed})
        last_step = self.pending[-1][0]
        rate = (last_step - self.window[0]) / max(now - self.window[1], 1e-9)
        self.window = (last_step, now)
        self.pending = []
        self.bar.update(last_step - self.bar.n)
        self.postfix.update(loss=f"{self.history[-1]['loss']:.4g}", steps_per_s=f"{rate:.3g}")
        self.bar.set_postfix(self.postfix, refresh=False)

    def _evaluate(self, step: int) -> None:
        self._flush()
        state = self.state
        metrics = self.eval_fn(state.params, state.ema_params, step)
        values = {k: float(np.asarray(v)) for k, v in dict(metrics).items()}
        if self.history and self.history[-1]["step"] == step:
            self.history[-1]["eval"] = values
        else:
            self.history.append({"step": step, "eval": values, "time": time.perf_counter() - self.start})
        self.postfix.update({f"eval_{k}": f"{v:.4g}" for k, v in values.items()})
        self.bar.set_postfix(self.postfix, refresh=False)

    def _save(self, step: int, data_state: dict | None) -> None:
        # Flush first: a NaN loss raises here, before the NaN state can be written.
        self._flush()
        self.ckpt.save(self.state, data_state=data_state, metadata=self.meta)
        self.last_saved = step
