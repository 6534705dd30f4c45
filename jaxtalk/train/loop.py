"""``train``: the one training loop every jaxtalk model uses.

The model supplies ``loss_fn(params, batch, key) -> (loss, metrics)``; the loop owns the optimiser,
EMA, frozen parameters, data-parallel sharding, progress bar, periodic evaluation, checkpoints and
exact resumption (state, optimiser, EMA, RNG and data position).

How it runs is one :class:`LoopSettings` (length, checkpoints, evaluation, logging). With
``best_metric`` the loop also keeps the best-validated state in ``<ckpt_dir>/best`` and, with
evaluation, writes the training and validation curve to ``<ckpt_dir>/history.jsonl`` (layout:
:mod:`jaxtalk.train.checkpoint`). With ``log_dir`` (the run folder) it writes ``metrics.jsonl`` and
TensorBoard event files there (:mod:`jaxtalk.train.writers`).

Metrics stay on the device and are fetched every ``log_every`` steps (and before each checkpoint or
evaluation) so the host does not wait for every step; the non-finite-loss check runs on those
fetched values, so it never lets a NaN state reach a checkpoint.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, Literal

import jax
import numpy as np
from jax.sharding import Mesh

from jaxtalk.files import atomic_write_text, folder_lock
from jaxtalk.train.checks import BatchSpec, check_finite
from jaxtalk.train.checkpoint import BEST_DIR, HISTORY_FILE, Checkpointer, best_checkpoint_dir, read_history
from jaxtalk.train.observers import StepObserver
from jaxtalk.train.optim import OptimConfig, Trainable, make_optimizer, trainable_mask
from jaxtalk.train.sharding import replicate, shard_batch
from jaxtalk.train.state import TrainState, create_train_state
from jaxtalk.train.step import LossFn, make_train_step
from jaxtalk.train.writers import RunMetrics, json_line
from jaxtalk.types import PRNGKeyArray

__all__ = ["train", "LoopSettings", "TrainResult", "NonFiniteLossError"]

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
        best: with ``best_metric``: the record of the best checkpoint so far (``metric``, ``mode``,
            ``value``, ``step``, ``eval``), including one kept from before a resume; None if no
            evaluation has produced a finite value yet, or without ``best_metric``.
    """

    state: TrainState
    history: list[dict[str, Any]]
    best: dict[str, Any] | None = None


@dataclasses.dataclass(frozen=True)
class LoopSettings:
    """How :func:`train` runs, besides what it trains: its length, checkpoints, evaluation and logging.

    Attributes:
        max_steps: stop when ``state.step`` reaches this (None: the optimiser's ``total_steps``).
        save_every: also checkpoint every this many steps (the final step is always saved).
        keep_checkpoints: how many recent checkpoints to keep.
        async_checkpoints: write checkpoints in the background.
        resume: continue from the newest checkpoint in ``ckpt_dir`` if there is one (False with
            existing checkpoints is an error rather than a silent overwrite). An optimiser config with
            another schedule length (``total_steps``, ``warmup_steps``) continues the run on the
            stretched schedule; any other difference from the checkpoint's config warns.
        eval_every: evaluation period in steps (None: only at the end); needs an ``eval_fn``.
        best_metric: a key of ``eval_fn``'s metrics. Whenever an evaluation improves it (strictly;
            a NaN/inf value never does), that state is saved to ``<ckpt_dir>/best`` (one
            checkpoint, :func:`jaxtalk.train.best_checkpoint_dir`), its metadata recording
            ``best = {metric, mode, value, step, eval}``. Resuming reads the best value back from
            there, so a resumed run only replaces it with a better one. The regular checkpoints and
            resumption are unaffected. Needs ``eval_fn`` and ``ckpt_dir``.
        best_mode: ``"min"`` (lower is better, e.g. a loss) or ``"max"``.
        write_history: append one JSON line per log flush (window-mean loss and metrics) and per
            evaluation to ``<ckpt_dir>/history.jsonl`` (read with :func:`jaxtalk.train.read_history`).
            None: when ``ckpt_dir`` and ``eval_fn`` are both given. On resume, rows after the
            restored step (from a run killed after its last checkpoint) are dropped first.
        log_dir: the run folder: ``metrics.jsonl`` and TensorBoard event files of the training
            scalars (window-mean loss, gradient norm before clipping and model metrics; learning
            rate; steps/s) and of every evaluation, flushed at each log flush, written by process 0
            (:mod:`jaxtalk.train.writers`; a resume never repeats a step in them). None: neither.
        progress: show a tqdm bar with loss and steps/s (on process 0 of a multi-process run).
        log_every: fetch metrics from the device every this many steps.
        check_batches: scan every batch for NaN/inf before its step (costs a host pass).
        variable_axes: batch axes allowed to change size between batches (None: the iterator's
            ``variable_axes`` attribute, else none). All other sizes must match the first batch.

    Raises:
        ValueError: a period or count below 1, or a ``best_mode`` other than ``"min"``/``"max"``.
    """

    max_steps: int | None = None
    save_every: int | None = None
    keep_checkpoints: int = 3
    async_checkpoints: bool = True
    resume: bool = True
    eval_every: int | None = None
    best_metric: str | None = None
    best_mode: Literal["min", "max"] = "min"
    write_history: bool | None = None
    log_dir: str | os.PathLike | None = None
    progress: bool = True
    log_every: int = 10
    check_batches: bool = True
    variable_axes: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("log_every", "keep_checkpoints"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("max_steps", "save_every", "eval_every"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1 or None, got {value}")
        if self.best_mode not in ("min", "max"):
            raise ValueError(f"best_mode must be 'min' or 'max', got {self.best_mode!r}")
        if self.variable_axes is not None:  # a tuple, so settings compare and hash by value
            object.__setattr__(self, "variable_axes", tuple(int(axis) for axis in self.variable_axes))


def train(
    loss_fn: LossFn,
    init_params: PyTree,
    data_iter: Iterable[PyTree],
    config: OptimConfig,
    *,
    key: PRNGKeyArray,
    settings: LoopSettings = LoopSettings(),
    ckpt_dir: str | os.PathLike | None = None,
    metadata: dict[str, Any] | None = None,
    eval_fn: EvalFn | None = None,
    trainable: Trainable = None,
    mesh: Mesh | None = None,
    observers: Sequence[StepObserver] = (),
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
        settings: how the loop runs (:class:`LoopSettings`: length, checkpoints, evaluation, logging).
        ckpt_dir: checkpoint directory (None: no checkpoints).
        metadata: JSON-serialisable record saved with each checkpoint (e.g. ``{"model": "toktalk"}``);
            the optimiser config and the batch spec are added.
        eval_fn: ``(params, ema_params or None, step) -> metrics``, called every
            ``settings.eval_every`` steps and at the end; its metrics go into the history and the
            progress bar.
        trainable: which parameters train: None (all), a predicate ``(path, leaf) -> bool`` on
            ``"a/b/kernel"`` paths, or a pytree of bools. Frozen leaves stay bitwise unchanged.
        mesh: device mesh for data parallelism (batch sharded, state replicated).
        observers: :class:`~jaxtalk.train.observers.StepObserver` s that watch the steps (a profiler
            trace of some steps, the benchmark's timing probe); each is closed when the loop ends. One
            whose ``should_stop()`` turns true ends the run after the current step: its state is
            checkpointed (without the final evaluation) and returned, to resume later.

    Returns:
        :class:`TrainResult` with the final state, per-step history and best record.

    Raises:
        ValueError: settings that do not fit the call (``eval_every`` without ``eval_fn``,
            ``best_metric`` without ``eval_fn`` or ``ckpt_dir``, ``write_history`` without
            ``ckpt_dir``), an evaluation without the ``best_metric`` key, or a best checkpoint chosen
            by another metric or mode on resume; a batch with NaN/inf, a different
            structure/shape/dtype than the first batch (naming the array and both shapes), or a batch
            size not divisible by the mesh's device count; a corrupt checkpoint (naming the path).
        NonFiniteLossError: the loss became NaN/inf (names the step; nothing after the last good
            checkpoint is saved).
        jaxtalk.files.FolderInUseError: another process is training into ``log_dir`` (or
            ``ckpt_dir`` without ``log_dir``).
    """
    max_steps = config.total_steps if settings.max_steps is None else settings.max_steps
    eval_every, best_metric, log_dir = settings.eval_every, settings.best_metric, settings.log_dir
    if eval_every is not None and eval_fn is None:
        raise ValueError("eval_every is set but eval_fn is None")
    if best_metric is not None and (eval_fn is None or ckpt_dir is None):
        raise ValueError(f"best_metric={best_metric!r} needs eval_fn and ckpt_dir (it saves to <ckpt_dir>/best)")
    if settings.write_history and ckpt_dir is None:
        raise ValueError("write_history=True needs ckpt_dir (the history goes to <ckpt_dir>/history.jsonl)")
    write_history = settings.write_history
    if write_history is None:
        write_history = ckpt_dir is not None and eval_fn is not None
    variable_axes = settings.variable_axes
    if variable_axes is None:
        variable_axes = tuple(getattr(data_iter, "variable_axes", ()))

    mask = trainable_mask(init_params, trainable)
    tx, step_fn = _step_for(loss_fn, config, jax.tree.structure(mask), tuple(jax.tree.leaves(mask)), mesh)
    state = create_train_state(init_params, tx, key, ema=config.ema_decay is not None)
    if mesh is not None:
        state = replicate(state, mesh)

    meta = {"config": config.to_dict(), **(metadata or {})}
    ckpt = None
    best = None
    metrics_log = None
    spec: BatchSpec | None = None
    has_position = hasattr(data_iter, "get_state") and hasattr(data_iter, "set_state")
    # One writer per run: a second training into the same folder is refused before it writes anything.
    # Process 0 holds it; the other processes of a multi-process run write the same folder with it.
    locks = contextlib.ExitStack()
    lock_dir = log_dir if log_dir is not None else ckpt_dir
    if lock_dir is not None and jax.process_index() == 0:
        locks.enter_context(folder_lock(lock_dir))
    try:
        if ckpt_dir is not None:
            ckpt = Checkpointer(ckpt_dir, max_to_keep=settings.keep_checkpoints, async_save=settings.async_checkpoints)
        if best_metric is not None:
            best = _BestKeeper(best_checkpoint_dir(ckpt_dir), best_metric, settings.best_mode,
                               settings.async_checkpoints)
        for existing in (ckpt, None if best is None else best.ckpt):
            if existing is not None and not settings.resume and existing.latest_step() is not None:
                raise ValueError(
                    f"checkpoint directory {existing.directory} already holds checkpoints (latest step "
                    f"{existing.latest_step()}); resume it (LoopSettings(resume=True)) or choose an empty directory"
                )
        if best is not None:
            best.load_record()  # the best-so-far survives a resume (and a restart from step 0)
        if ckpt is not None and settings.resume and ckpt.latest_step() is not None:
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
            was, now = dict(saved_meta.get("config") or {}), meta["config"]
            # Another schedule length is how a run is continued for longer (`jaxtalk train --steps`
            # stretches the schedule, its warm-up capped to a tenth of the run); other changes surprise.
            changes = ", ".join(f"{k} {was.get(k)} -> {now.get(k)}" for k in sorted({*was, *now})
                                if was.get(k) != now.get(k) and k not in ("total_steps", "warmup_steps"))
            if changes:
                warnings.warn(f"optimiser settings differ from the checkpoint's: {changes}", stacklevel=2)
        history_file = None
        if write_history and jax.process_index() == 0:  # one writer per run, as for orbax's files
            history_file = _HistoryFile(Path(ckpt_dir) / HISTORY_FILE, start_step=int(state.step))
        if log_dir is not None and jax.process_index() == 0:
            metrics_log = RunMetrics(log_dir, start_step=int(state.step))
        loop = _Loop(
            state=state,
            step_fn=step_fn,
            data_iter=iter(data_iter),
            position=data_iter if has_position else None,
            ckpt=ckpt,
            meta=meta,
            spec=spec,
            mesh=mesh,
            check_batches=settings.check_batches,
            variable_axes=tuple(variable_axes),
            eval_fn=eval_fn,
            eval_every=eval_every,
            save_every=settings.save_every,
            log_every=settings.log_every,
            progress=settings.progress,
            best=best,
            history_file=history_file,
            metrics_log=metrics_log,
            observers=tuple(observers),
        )
        return loop.run(max_steps)
    finally:
        if metrics_log is not None:
            metrics_log.close()
        if ckpt is not None:
            ckpt.close()
        if best is not None:
            best.ckpt.close()
        locks.close()


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
    best: _BestKeeper | None = None
    history_file: _HistoryFile | None = None
    metrics_log: RunMetrics | None = None
    observers: tuple[StepObserver, ...] = ()

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
        # One bar per run: in a multi-process run only process 0 draws it.
        self.bar = tqdm(total=max_steps, initial=step, disable=not self.progress or jax.process_index() != 0,
                        desc="train", unit="step")
        stopped = False
        try:
            for observer in self.observers:
                observer.start(self.data_iter)
            while step < max_steps:
                try:
                    batch = next(self.data_iter)
                except StopIteration:
                    warnings.warn(f"data_iter ended after step {step}, before max_steps={max_steps}", stacklevel=3)
                    break
                batch = self._prepare(batch, step + 1)
                for observer in self.observers:
                    observer.before_step(step + 1, self.state, batch, self.step_fn)
                self.state, metrics = self.step_fn(self.state, batch)
                step += 1
                for observer in self.observers:
                    observer.after_step(step, self.state, metrics)
                self.pending.append((step, metrics))
                data_state = self.position.get_state() if self.position is not None else None
                if step % self.log_every == 0:
                    self._flush()
                if self.eval_every is not None and step % self.eval_every == 0:
                    self._evaluate(step, data_state)
                if self.save_every is not None and step % self.save_every == 0:
                    self._save(step, data_state)
                if self.metrics_log is not None:  # after this step's log flush and evaluation: one row
                    self.metrics_log.flush()
                if any(observer.should_stop() for observer in self.observers):
                    stopped = True
                    break
            self._flush()
            if not stopped and self.eval_fn is not None and not (self.history and "eval" in self.history[-1]):
                self._evaluate(step, data_state)
            if self.ckpt is not None and self.last_saved != step and step > 0:
                self._save(step, data_state)
            if self.metrics_log is not None:
                self.metrics_log.flush()
        finally:
            self.bar.close()
            for observer in self.observers:
                observer.close()
        return TrainResult(
            state=self.state, history=self.history, best=None if self.best is None else self.best.record
        )

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
        done = 0
        for (step, _), metrics in zip(self.pending, fetched):
            values = {k: float(np.asarray(v)) for k, v in metrics.items()}
            if not math.isfinite(values["loss"]):
                self.pending = []
                if done:  # the files keep the finite steps before it
                    if self.history_file is not None:
                        self.history_file.append_train(self.history[-done:], elapsed)
                    self._log_train(self.history[-done:], now)
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
            done += 1
        last_step = self.pending[-1][0]
        if self.history_file is not None:
            self.history_file.append_train(self.history[-done:], elapsed)
        rate = self._log_train(self.history[-done:], now)
        self.window = (last_step, now)
        self.pending = []
        self.bar.update(last_step - self.bar.n)
        self.postfix.update(loss=f"{self.history[-1]['loss']:.4g}", steps_per_s=f"{rate:.3g}")
        self.bar.set_postfix(self.postfix, refresh=False)

    def _log_train(self, rows: list[dict], now: float) -> float:
        """Steps/s since the last fetch, and the window's training scalars to the metric writers."""
        rate = (rows[-1]["step"] - self.window[0]) / max(now - self.window[1], 1e-9)
        if self.metrics_log is not None:
            scalars = {f"train/{k}": float(np.mean([r["metrics"][k] for r in rows if k in r["metrics"]]))
                       for k in rows[-1]["metrics"] if k != "lr"}
            scalars["train/lr"] = rows[-1]["metrics"]["lr"]  # the schedule at this step, not a mean
            scalars["train/steps_per_s"] = rate
            self.metrics_log.log(rows[-1]["step"], scalars)
        return rate

    def _evaluate(self, step: int, data_state: dict | None) -> None:
        # Flush first: a NaN loss raises here, so a NaN state never reaches the best checkpoint.
        self._flush()
        state = self.state
        metrics = self.eval_fn(state.params, state.ema_params, step)
        values = {k: float(np.asarray(v)) for k, v in dict(metrics).items()}
        elapsed = time.perf_counter() - self.start
        if self.history and self.history[-1]["step"] == step:
            self.history[-1]["eval"] = values
        else:
            self.history.append({"step": step, "eval": values, "time": elapsed})
        improved = None
        if self.best is not None:
            improved = self.best.offer(state, step, values, data_state=data_state, metadata=self.meta)
        if self.history_file is not None:
            self.history_file.append_eval(step, values, elapsed, best=improved)
        if self.metrics_log is not None:
            self.metrics_log.log(step, {f"eval/{k}": v for k, v in values.items()})
        self.postfix.update({f"eval_{k}": f"{v:.4g}" for k, v in values.items()})
        self.bar.set_postfix(self.postfix, refresh=False)

    def _save(self, step: int, data_state: dict | None) -> None:
        # Flush first: a NaN loss raises here, before the NaN state can be written.
        self._flush()
        self.ckpt.save(self.state, data_state=data_state, metadata=self.meta)
        self.last_saved = step


class _BestKeeper:
    """The best-validated checkpoint of a run: ``<ckpt_dir>/best``, one step, chosen by one metric.

    A second :class:`Checkpointer` rather than orbax's ``best_fn``: with ``best_fn`` orbax's
    ``max_to_keep`` would keep the best N instead of the latest N, and the regular checkpoints (what
    resume reads) must stay "the latest N". It often saves the same step as the regular one, while
    that save is still being written: its own barrier names keep a multi-process run's processes
    from confusing the two saves.
    """

    def __init__(self, directory: Path, metric: str, mode: str, async_save: bool) -> None:
        self.metric, self.mode = metric, mode
        self.ckpt = Checkpointer(directory, max_to_keep=1, async_save=async_save, barrier_prefix=BEST_DIR)
        self.record: dict[str, Any] | None = None

    def load_record(self) -> None:
        """Adopt the saved best record as the value to beat.

        Raises:
            ValueError: the saved best was chosen by another metric or mode (the values would not
                compare), or its metadata has no best record.
        """
        if self.ckpt.latest_step() is None:
            return
        meta = self.ckpt.read_metadata()
        record = meta.get("best")
        if not isinstance(record, dict) or "value" not in record:
            raise ValueError(f"checkpoint {self.ckpt.directory} has no best-checkpoint record in its metadata")
        if (record.get("metric"), record.get("mode")) != (self.metric, self.mode):
            raise ValueError(
                f"the best checkpoint in {self.ckpt.directory} was chosen by {record.get('metric')!r} "
                f"({record.get('mode')}), this run asks for {self.metric!r} ({self.mode}); use the same "
                "best_metric/best_mode or another ckpt_dir"
            )
        self.record = record

    def offer(
        self, state: TrainState, step: int, values: dict[str, float], *, data_state: dict | None, metadata: dict
    ) -> bool:
        """Save ``state`` as the new best if ``values[metric]`` beats the record.

        Returns:
            Whether it did.

        Raises:
            ValueError: ``values`` has no entry for the metric (naming the ones it has).
        """
        if self.metric not in values:
            raise ValueError(
                f"best_metric {self.metric!r} is not among the eval metrics at step {step}: {sorted(values)}"
            )
        value = values[self.metric]
        if not math.isfinite(value):
            return False  # a diverged evaluation is never "best"
        if self.record is not None:
            previous = float(self.record["value"])
            if not (value < previous if self.mode == "min" else value > previous):
                return False  # ties keep the earlier state
        # A best at or after this step exists only when the run went back in time (resumed from an
        # older regular checkpoint, or restarted from step 0, and this time did better). Orbax
        # refuses to overwrite a step and keeps the most recently written one, so remove it first.
        for old in self.ckpt.all_steps():
            if old >= step:
                self.ckpt.delete(old)
        record = {"metric": self.metric, "mode": self.mode, "value": value, "step": step, "eval": dict(values)}
        self.ckpt.save(state, data_state=data_state, metadata={**metadata, "best": record})
        self.record = record
        return True


class _HistoryFile:
    """Appends JSON rows to ``<ckpt_dir>/history.jsonl`` (one ``write`` per row)."""

    def __init__(self, path: Path, start_step: int) -> None:
        self.path = path
        rows = read_history(path.parent)
        # Drop what a killed run logged after its last checkpoint: the resumed run re-does it.
        kept = [r for r in rows if int(r.get("step", 0)) <= start_step]
        self.eval_steps = {int(r["step"]) for r in kept if r.get("type") == "eval"}
        if path.is_file():
            lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
            if len(lines) != len(kept):  # rows dropped, or a torn last line
                # Atomic: a reader sees the old or the new file, never a mix.
                atomic_write_text(path, "".join(json_line(r) for r in kept))

    def append_train(self, rows: list[dict[str, Any]], elapsed: float) -> None:
        """One row for a log flush: mean loss and metrics over its ``window`` of steps."""
        keys = rows[-1]["metrics"].keys()
        self._append(
            {
                "type": "train",
                "step": rows[-1]["step"],
                "window": len(rows),
                "loss": float(np.mean([r["loss"] for r in rows])),
                "metrics": {k: float(np.mean([r["metrics"][k] for r in rows if k in r["metrics"]])) for k in keys},
                "time": elapsed,
            }
        )

    def append_eval(self, step: int, values: dict[str, float], elapsed: float, *, best: bool | None) -> None:
        """One row per evaluation; a step already in the file (re-evaluated by a resumed run that
        had nothing left to train) is not repeated."""
        if step in self.eval_steps:
            return
        self.eval_steps.add(step)
        row: dict[str, Any] = {"type": "eval", "step": step, "eval": values, "time": elapsed}
        if best is not None:
            row["best"] = best
        self._append(row)

    def _append(self, row: dict[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(json_line(row))

