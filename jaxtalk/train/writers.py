"""Metric writers of a training run: ``metrics.jsonl`` and TensorBoard event files in the run folder.

:func:`jaxtalk.train.train` with ``log_dir`` (the recipes pass the run folder, the parent of the
checkpoint directory) writes, on process 0 only::

    <run>/metrics.jsonl                          one JSON object per logged step
    <run>/events.out.tfevents.<time>.<host>...   the same scalars for TensorBoard (tensorboardX)

Both hold the same scalars under the same names:

* ``train/loss``, ``train/grad_norm`` and every metric of the model's loss (``train/<name>``): means
  over the log window (the ``log_every`` steps ending at the row's step, as ``history.jsonl``);
* ``train/lr``: the schedule's learning rate of the update that reached the row's step;
* ``train/steps_per_s``: optimiser steps per second over the window (as the progress bar);
* ``eval/<name>``: every metric the ``eval_fn`` returned at that step.

A ``metrics.jsonl`` row is ``{"step": 20, "wall_time": <Unix seconds>, "train/loss": ..., ...}``:
one row per step, the training window and an evaluation of the same step merged, steps strictly
increasing; non-finite values are written as ``null`` (strict JSON) and read back as NaN
(:func:`read_metrics`). Rows are appended and flushed at each log flush; the event file is flushed
at the same time.

Resuming (``start_step``: the restored checkpoint's step) never repeats a step:

* ``metrics.jsonl``: rows after ``start_step`` (logged by a run killed after its last checkpoint,
  which the resumed run logs again) and a torn last line are dropped first, with one atomic rewrite;
  a scalar already recorded at a step up to ``start_step`` (an evaluation of the checkpointed step,
  repeated by a resumed run with nothing left to train) is not written again, to either sink.
* Event files: each resume writes a new event file (TensorBoard reads every file of the folder as
  one run). The older files lose their events after ``start_step`` (each is rewritten atomically
  without them, record bytes copied unchanged), so any reader sees each step once; the new file
  also starts with TensorBoard's purge marker (a ``SessionLog.START`` at ``start_step + 1``, as
  ``tensorboardX.SummaryWriter(purge_step=...)`` writes), which makes a TensorBoard that had already
  loaded the dropped steps discard them.

The event files are written synchronously through tensorboardX's ``EventsWriter`` (no background
thread or queue), so a flush means the scalars are on disk.
"""

from __future__ import annotations

import json
import math
import os
import struct
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from jaxtalk.files import atomic_write_bytes, atomic_write_text

__all__ = ["RunMetrics", "read_metrics", "METRICS_FILE", "EVENTS_PREFIX"]

METRICS_FILE = "metrics.jsonl"
EVENTS_PREFIX = "events.out.tfevents."


class RunMetrics:
    """The metric writers of one run folder: ``metrics.jsonl`` plus a TensorBoard event file.

    Args:
        run_dir: the run folder (created if missing).
        start_step: the step training starts from (the restored checkpoint's; 0 for a new run).
            Everything logged after it by an earlier process is removed first (module docstring).
        tensorboard: also write TensorBoard events.

    Use :meth:`log` for each step's scalars, :meth:`flush` at each log flush, :meth:`close` at the end.
    """

    def __init__(self, run_dir: str | os.PathLike, *, start_step: int, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.run_dir / METRICS_FILE
        self.start_step = int(start_step)
        rows = _truncate_metrics(self.path, self.start_step)
        # What earlier processes already recorded up to the resume point (never written again).
        self._recorded: dict[int, set[str]] = {}
        for row in rows:
            self._recorded.setdefault(int(row["step"]), set()).update(k for k in row if k not in ("step", "wall_time"))
        self._last_step = max(self._recorded, default=-1)
        self._pending: dict[str, Any] | None = None
        self._events = None
        if tensorboard:
            from tensorboardX.event_file_writer import EventsWriter
            from tensorboardX.proto.event_pb2 import Event, SessionLog

            for old in sorted(self.run_dir.glob(f"{EVENTS_PREFIX}*")):
                if old.is_file() and not old.name.startswith("."):
                    _truncate_events(old, self.start_step)
            # tensorboardX names files by the second and host; the pid and start step keep a quick
            # resume from reusing (and truncating) the file of the process before it.
            self._events = EventsWriter(str(self.run_dir / "events"),
                                        filename_suffix=f".{os.getpid()}.from{self.start_step}")
            if self.start_step > 0:
                self._events.write_event(Event(step=self.start_step + 1, wall_time=time.time(),
                                               session_log=SessionLog(status=SessionLog.START)))
            self._events.flush()

    def log(self, step: int, scalars: Mapping[str, float]) -> None:
        """Record ``scalars`` (``tag -> value``) at ``step``; written at the next :meth:`flush`.

        Scalars logged for the same step before a flush share one row. A scalar already recorded
        at ``step`` is skipped; so is a step not after the last written row (rows only go forward).
        """
        step = int(step)
        done = self._recorded.get(step, set())
        fresh = {k: float(v) for k, v in scalars.items() if k not in done}
        if not fresh:
            return
        if self._pending is not None and self._pending["step"] != step:
            self._write_pending()
        if self._pending is None:
            if step <= self._last_step:
                return  # a row for this step is on disk already; a second one would repeat the step
            self._pending = {"step": step, "wall_time": time.time()}
        self._pending.update(fresh)

    def flush(self) -> None:
        """Write the pending row to ``metrics.jsonl`` and the event file, and flush both to disk."""
        if self._pending is not None:
            self._write_pending()
            if self._events is not None:
                self._events.flush()

    def close(self) -> None:
        """Flush and close the event file (the JSONL file is closed after every row)."""
        self.flush()
        if self._events is not None:
            self._events.close()
            self._events = None

    def _write_pending(self) -> None:
        row, self._pending = self._pending, None
        step = row["step"]
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(json_line(row))
        if self._events is not None:
            from tensorboardX.proto.event_pb2 import Event
            from tensorboardX.proto.summary_pb2 import Summary

            values = [Summary.Value(tag=k, simple_value=v) for k, v in row.items() if k not in ("step", "wall_time")]
            self._events.write_event(Event(step=step, wall_time=row["wall_time"], summary=Summary(value=values)))
        self._recorded.setdefault(step, set()).update(k for k in row if k not in ("step", "wall_time"))
        self._last_step = step


def read_metrics(run_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of ``<run_dir>/metrics.jsonl`` (empty when there is none).

    A torn last line (a run killed while appending) is skipped; a bad line elsewhere is an error.
    ``null`` values (non-finite when written) come back as NaN.

    Args:
        run_dir: the run folder.

    Returns:
        One dict per row in file order: ``step``, ``wall_time`` and ``tag -> value``.

    Raises:
        ValueError: a line other than the last is not a JSON object with a ``step`` (names the line).
    """
    from jaxtalk.train.checkpoint import read_jsonl_rows

    rows = read_jsonl_rows(Path(run_dir) / METRICS_FILE, "metrics row", required=("step",))
    return [{k: math.nan if v is None else v for k, v in row.items()} for row in rows]


def json_line(row: Mapping[str, Any]) -> str:
    """``row`` as one line of strict JSON (no NaN/Infinity tokens, which many readers reject:
    non-finite floats, also inside nested dicts, become ``null``)."""

    def clean(v: Any) -> Any:
        if isinstance(v, Mapping):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, float) and not math.isfinite(v):
            return None
        return v

    return json.dumps(clean(row), allow_nan=False) + "\n"


def _truncate_metrics(path: Path, start_step: int) -> list[dict[str, Any]]:
    """Drop rows after ``start_step`` (and a torn last line) from ``path``; the rows kept."""
    rows = read_metrics(path.parent)
    kept = [r for r in rows if int(r["step"]) <= start_step]
    if path.is_file():
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
        if len(lines) != len(kept):
            # Atomic: a reader sees the old or the new file, never a mix.
            atomic_write_text(path, "".join(json_line(r) for r in kept))
    return kept


def _truncate_events(path: Path, start_step: int) -> None:
    """Rewrite the event file ``path`` without its events after ``start_step`` (and a torn tail).

    Kept records are copied byte for byte, framing and checksums included.
    """
    from tensorboardX.proto.event_pb2 import Event

    data = path.read_bytes()
    kept, offset, changed = [], 0, False
    while offset < len(data):
        # TFRecord framing: uint64 length, uint32 masked CRC of the length, payload, uint32 masked CRC.
        if offset + 12 > len(data):
            changed = True  # torn header
            break
        (length,) = struct.unpack("<Q", data[offset:offset + 8])
        end = offset + 12 + length + 4
        if end > len(data):
            changed = True  # torn payload: the writer was killed mid-record
            break
        try:
            event = Event.FromString(data[offset + 12:offset + 12 + length])
        except Exception:  # protobuf's DecodeError; an unreadable record ends what can be trusted
            changed = True
            break
        if event.step > start_step:
            changed = True
        else:
            kept.append(data[offset:end])
        offset = end
    if changed:
        atomic_write_bytes(path, b"".join(kept))
