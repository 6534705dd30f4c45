"""Observers of the training loop: code that watches chosen steps of a real run without changing it.

:func:`jaxtalk.train.train` calls each observer's :meth:`StepObserver.start` once with the loop's data
iterator, :meth:`~StepObserver.before_step` just before the jitted step runs (with the state, the
prepared batch and the step function itself), :meth:`~StepObserver.after_step` just after it was
dispatched, and :meth:`~StepObserver.close` when the loop ends, however it ends. Steps are counted
1-based (step ``s`` is the ``s``-th update, the one that makes ``state.step == s``).

* :class:`StopRequest`: ends a run cleanly after the update in flight (``jaxtalk train`` on Ctrl-C).
* :class:`TraceSteps`: a :mod:`jax.profiler` trace of steps ``start..stop`` (``jaxtalk train
  --profile START:STOP``), viewable in Perfetto or TensorBoard.
* The benchmark's probe (:mod:`jaxtalk.bench`) times the compiled step, the loader and the loop's
  wall time per step on a real recipe run.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax

from jaxtalk.train.state import TrainState

__all__ = ["StepObserver", "StopRequest", "TraceSteps", "parse_step_range", "trace_files"]

PyTree = Any


class StepObserver:
    """Base class of loop observers: every hook does nothing unless a subclass overrides it.

    An observer must not change the state or the batch (the loop donates the state to the step:
    an observer that keeps it past :meth:`before_step` keeps a copy).
    """

    def start(self, data_iter: Iterator[PyTree]) -> None:
        """Called once before the first step with the loop's batch iterator."""

    def before_step(self, step: int, state: TrainState, batch: PyTree, step_fn: Callable[..., Any]) -> None:
        """Called just before the jitted ``step_fn(state, batch)`` of update number ``step``."""

    def after_step(self, step: int, state: TrainState, metrics: dict[str, jax.Array]) -> None:
        """Called just after update number ``step`` was dispatched (its arrays may still be computing)."""

    def should_stop(self) -> bool:
        """Asked after every update: True ends the run there (checkpointed, to resume later)."""
        return False

    def close(self) -> None:
        """Called once when the loop ends (normally or by an exception)."""


class StopRequest(StepObserver):
    """Ends a run cleanly at the next step boundary once :meth:`request` was called.

    Meant for a signal handler (``jaxtalk train`` asks it on Ctrl-C): the loop finishes the update in
    flight, checkpoints it and returns, so nothing is torn down in the middle of a compile or a save.

    Attributes:
        requested: :meth:`request` was called.
        running: the loop is between its first and last step (a request is then honoured).
    """

    def __init__(self) -> None:
        self.requested = False
        self.running = False

    def request(self) -> None:
        """Ask the loop to stop after the update in flight."""
        self.requested = True

    def start(self, data_iter: Iterator[PyTree]) -> None:
        self.running = True

    def should_stop(self) -> bool:
        return self.requested

    def close(self) -> None:
        self.running = False


def parse_step_range(text: str) -> tuple[int, int]:
    """``"START:STOP"`` -> ``(start, stop)``: the 1-based steps ``start..stop`` (both included).

    Raises:
        ValueError: not two integers with ``1 <= start <= stop``.
    """
    start, sep, stop = text.partition(":")
    try:
        first, last = int(start), int(stop)
    except ValueError:
        raise ValueError(f"--profile expects START:STOP (two step numbers), got {text!r}") from None
    if not sep or first < 1 or last < first:
        raise ValueError(f"--profile expects START:STOP with 1 <= START <= STOP, got {text!r}")
    return first, last


class TraceSteps(StepObserver):
    """Write a :mod:`jax.profiler` trace of updates ``start..stop`` into ``log_dir``.

    The trace starts before update ``start`` is dispatched and stops once update ``stop`` has
    finished (its state is waited for), so it holds whole steps; a run that ends earlier stops it at
    the end. The files land in ``log_dir/plugins/profile/<time>/`` (an ``.xplane.pb`` for
    TensorBoard's profile plugin and a ``.trace.json.gz`` that Perfetto opens).

    Args:
        start: first traced update (1-based).
        stop: last traced update.
        log_dir: trace folder (created).
    """

    def __init__(self, start: int, stop: int, log_dir: str | os.PathLike[str]) -> None:
        if start < 1 or stop < start:
            raise ValueError(f"trace steps must satisfy 1 <= start <= stop, got {start}:{stop}")
        self.start_step, self.stop_step = start, stop
        self.log_dir = Path(log_dir)
        self.active = False

    def before_step(self, step: int, state: TrainState, batch: PyTree, step_fn: Callable[..., Any]) -> None:
        if step == self.start_step and not self.active:
            jax.block_until_ready(state)  # earlier steps' work stays out of the trace
            self.log_dir.mkdir(parents=True, exist_ok=True)
            jax.profiler.start_trace(str(self.log_dir), create_perfetto_trace=True)
            self.active = True

    def after_step(self, step: int, state: TrainState, metrics: dict[str, jax.Array]) -> None:
        if step >= self.stop_step and self.active:
            jax.block_until_ready((state, metrics))  # the last traced step finishes inside the trace
            self.close()

    def close(self) -> None:
        if self.active:
            self.active = False
            jax.profiler.stop_trace()


def trace_files(log_dir: str | os.PathLike[str]) -> list[Path]:
    """The trace files :class:`TraceSteps` (or :func:`jax.profiler.start_trace`) wrote under ``log_dir``."""
    root = Path(log_dir) / "plugins" / "profile"
    return sorted(p for p in root.rglob("*") if p.is_file()) if root.is_dir() else []
