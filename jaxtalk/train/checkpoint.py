"""Orbax checkpoints of the train state, the data-iterator position and a JSON metadata record.

Layout of a checkpoint directory written by :func:`jaxtalk.train.train`::

    <dir>/<step>/{state,data,meta}        the latest ``keep_checkpoints`` steps (resume from the newest)
    <dir>/best/<step>/{state,data,meta}   with ``best_metric``: the single best-validated step; its
                                          ``meta`` has ``best = {metric, mode, value, step, eval}``
    <dir>/history.jsonl                   with evaluation: one JSON object per line, ``type`` "train"
                                          (window-mean loss/metrics at each log flush) or "eval"

Orbax writes each step into ``<dir>/<step>.orbax-checkpoint-tmp...`` and renames it when complete,
and lists only finalised step directories, so a run killed mid-save leaves the previous checkpoint
as the latest one (tested). Orbax only lists all-digit names as steps, so ``best/`` and
``history.jsonl`` never count as checkpoints of ``<dir>``.

Readers choose "latest" or "best" by directory: ``Checkpointer(dir)`` or
``Checkpointer(best_checkpoint_dir(dir))``; both support :meth:`Checkpointer.restore_saved` and
:meth:`Checkpointer.read_metadata`. :func:`read_best` gives the best record, :func:`read_history` the
curve.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any

import jax

from jaxtalk.train.state import TrainState

__all__ = [
    "Checkpointer",
    "CheckpointMismatchError",
    "save_checkpoint",
    "restore_checkpoint",
    "latest_checkpoint_step",
    "BEST_DIR",
    "HISTORY_FILE",
    "best_checkpoint_dir",
    "read_best",
    "read_history",
]

BEST_DIR = "best"
HISTORY_FILE = "history.jsonl"

PyTree = Any


class CheckpointMismatchError(ValueError):
    """A checkpoint that cannot be read, or whose arrays do not fit the train state it is restored into
    (e.g. written by another model configuration)."""


# Orbax's absl warnings that report expected behaviour of this module, not a problem: every read-only
# open (how `jaxtalk eval`, `sample` and a resumed `train` read a run) and the wait for the previous
# background save, which the loop's evaluation and save cadence triggers on any short run (its cost
# shows in the progress bar's steps/s). Matched on orbax's exact format strings; everything else
# orbax logs still shows.
_ORBAX_NOISE = (
    "Given directory is read only=%s",
    "Waiting for previous save to complete took %f seconds. If this number is high, consider checkpointing less "
    "frequently.",
)


class _OrbaxNoiseFilter(logging.Filter):
    """Drops the records of :data:`_ORBAX_NOISE` from absl's logger."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.msg not in _ORBAX_NOISE


_NOISE_FILTER = _OrbaxNoiseFilter()


def _quiet_orbax() -> None:
    # Idempotent (logging keeps one copy of a filter object); installed on first use of a
    # Checkpointer rather than at import, so importing jaxtalk changes no logging.
    logging.getLogger("absl").addFilter(_NOISE_FILTER)


def _saveable(state: TrainState) -> dict[str, PyTree]:
    # A plain dict (orbax maps over the tree with None leaves, which a typed class would reject)
    # and the typed key stored as its raw uint32 data.
    return {
        "step": state.step,
        "params": state.params,
        "opt_state": state.opt_state,
        "ema_params": state.ema_params,
        "rng": jax.random.key_data(state.rng),
    }


def _abstract(tree: PyTree) -> PyTree:
    def one(x):
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None))

    return jax.tree.map(one, tree)


class Checkpointer:
    """A run's checkpoint directory: keep the last ``max_to_keep`` steps, save and restore.

    Args:
        directory: checkpoint directory (created on the first save).
        max_to_keep: number of most recent checkpoints kept (older ones are deleted).
        async_save: write in a background thread after copying the arrays off the device (the
            train loop continues meanwhile); :meth:`close` waits for pending writes.
        read_only: open for restoring only (the directory must exist).
        barrier_prefix: in a multi-process run (where every process saves, and orbax synchronises
            them with barriers named after the step), a name that sets this checkpointer's barriers
            apart from those of another one saving at the same time, e.g. the same step into
            another directory (the training loop's best checkpoint: ``"best"``). The same on
            every process.

    Raises:
        ValueError: ``max_to_keep < 1``, or ``directory`` exists and is not a directory.
        FileNotFoundError: ``read_only`` and the directory does not exist.
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        *,
        max_to_keep: int = 3,
        async_save: bool = True,
        read_only: bool = False,
        barrier_prefix: str | None = None,
    ) -> None:
        import orbax.checkpoint as ocp  # heavy import, deferred to first use

        if max_to_keep < 1:
            raise ValueError(f"max_to_keep must be >= 1, got {max_to_keep}")
        self.directory = Path(directory).absolute()
        if self.directory.exists() and not self.directory.is_dir():
            raise ValueError(f"checkpoint path {self.directory} exists and is not a directory")
        if read_only and not self.directory.is_dir():
            raise FileNotFoundError(f"checkpoint directory {self.directory} does not exist")
        self._ocp = ocp
        _quiet_orbax()
        options = ocp.CheckpointManagerOptions(
            # A read-only manager keeps and saves nothing; orbax logs a warning for each of these
            # settings it has to override when given otherwise, so give it what it would set.
            max_to_keep=None if read_only else max_to_keep,
            save_interval_steps=0 if read_only else 1,
            create=not read_only,
            read_only=read_only,
            enable_async_checkpointing=async_save,
            cleanup_tmp_directories=not read_only,  # leftovers of a killed save are removed
            # Two checkpointers saving the same step at once would otherwise meet at one barrier
            # ("Barrier _async_write_complete.<step> is already ongoing") and fail.
            multiprocessing_options=ocp.options.MultiprocessingOptions(barrier_sync_key_prefix=barrier_prefix),
        )
        self._manager = ocp.CheckpointManager(self.directory, options=options, item_names=("state", "data", "meta"))

    # ------------------------------------------------------------------ queries
    def latest_step(self) -> int | None:
        """Newest complete checkpoint step, or None if there is none."""
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        """All complete checkpoint steps, ascending."""
        return sorted(self._manager.all_steps())

    # ------------------------------------------------------------------ save / restore
    def save(self, state: TrainState, *, data_state: dict | None = None, metadata: dict | None = None) -> None:
        """Save ``state`` under step ``int(state.step)`` (possibly in the background).

        Args:
            state: the train state.
            data_state: JSON-serialisable data-iterator position (``get_state()``).
            metadata: JSON-serialisable record (config, model name, batch spec...).
        """
        ocp = self._ocp
        step = int(state.step)
        self._manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(_saveable(state)),
                data=ocp.args.JsonSave(data_state or {}),
                meta=ocp.args.JsonSave({"step": step, **(metadata or {})}),
            ),
            force=True,
        )

    def restore(self, template: TrainState, step: int | None = None) -> tuple[TrainState, dict, dict]:
        """Restore a checkpoint into the structure, dtypes and shardings of ``template``.

        Args:
            template: a state with the same structure (e.g. a fresh :func:`create_train_state`).
            step: which step (default: the latest).

        Returns:
            ``(state, data_state, metadata)``.

        Raises:
            FileNotFoundError: the directory holds no complete checkpoint, or ``step`` is absent.
            ValueError: the checkpoint is corrupt or does not fit ``template`` (names the path).
        """
        ocp = self._ocp
        step = self._complete_step(step)
        path = self.directory / str(step)
        saved_template = _saveable(template)
        try:
            restored = self._manager.restore(
                step,
                args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(_abstract(saved_template)),
                    data=ocp.args.JsonRestore(),
                    meta=ocp.args.JsonRestore(),
                ),
            )
            raw = restored.state
            if jax.tree.structure(raw) != jax.tree.structure(saved_template):
                raise ValueError(
                    f"structure {jax.tree.structure(raw)} != expected {jax.tree.structure(saved_template)}"
                )
        except Exception as err:  # orbax/tensorstore raise many types; name the path for the user
            detail = str(err).splitlines()[0][:400] if str(err) else type(err).__name__  # tensorstore specs are huge
            raise CheckpointMismatchError(
                f"checkpoint {path} is corrupt or does not match the train state: {detail}"
            ) from err
        impl = jax.random.key_impl(template.rng)
        state = TrainState(
            step=raw["step"],
            params=raw["params"],
            opt_state=raw["opt_state"],
            ema_params=raw["ema_params"],
            rng=jax.random.wrap_key_data(raw["rng"], impl=impl),
        )
        return state, dict(restored.data or {}), dict(restored.meta or {})

    def _complete_step(self, step: int | None) -> int:
        # The newest complete step, or ``step`` after checking that it is complete.
        self._manager.wait_until_finished()
        steps = self.all_steps()
        if not steps:
            raise FileNotFoundError(f"no complete checkpoint in {self.directory}")
        step = steps[-1] if step is None else int(step)
        if step not in steps:
            raise FileNotFoundError(f"no checkpoint for step {step} in {self.directory} (have {steps})")
        return step

    def restore_saved(self, step: int | None = None) -> tuple[dict[str, Any], int]:
        """The saved train state exactly as stored (a dict of arrays), without a template.

        For readers that only need parameters (inference, the CLI) and should not have to rebuild each
        model's training-time structure (data-dependent entries, the optimiser's frozen-leaf mask).

        Args:
            step: checkpoint step (default: the newest complete one).

        Arrays come back with their saved sharding when this process has those devices; otherwise
        (saved by a run on more devices or processes, e.g. ``jaxtalk train --distributed``, read by
        one process) on this process's first device.

        Returns:
            ``(state, step)``: ``state`` has ``step``, ``params``, ``opt_state``, ``ema_params`` and
            ``rng`` (raw key data).

        Raises:
            FileNotFoundError: the directory holds no complete checkpoint, or ``step`` is absent.
            ValueError: the checkpoint cannot be read (names the path).
        """
        ocp = self._ocp
        step = self._complete_step(step)
        path = self.directory / str(step)
        try:
            # Without a fallback, orbax refuses a checkpoint whose saved shardings name devices this
            # process does not have ("Topology mismatch").
            fallback = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
            restored = self._manager.restore(
                step, args=ocp.args.Composite(state=ocp.args.StandardRestore(fallback_sharding=fallback))
            )
        except Exception as err:  # orbax/tensorstore raise many types; name the path for the user
            detail = str(err).splitlines()[0][:400] if str(err) else type(err).__name__
            raise ValueError(f"checkpoint {path} cannot be read: {detail}") from err
        return dict(restored.state), step

    def read_metadata(self, step: int | None = None) -> dict[str, Any]:
        """The JSON metadata record saved with a checkpoint, without reading its arrays.

        Args:
            step: checkpoint step (default: the newest complete one).

        Returns:
            The record: ``step`` plus what :meth:`save` was given as ``metadata``.

        Raises:
            FileNotFoundError: the directory holds no complete checkpoint, or ``step`` is absent.
            ValueError: the record cannot be read (names the path).
        """
        ocp = self._ocp
        step = self._complete_step(step)
        path = self.directory / str(step)
        try:
            restored = self._manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        except Exception as err:  # orbax raises many types; name the path for the user
            detail = str(err).splitlines()[0][:400] if str(err) else type(err).__name__
            raise ValueError(f"checkpoint metadata of {path} cannot be read: {detail}") from err
        return dict(restored.meta or {})

    def delete(self, step: int) -> None:
        """Delete the checkpoint of ``step`` (after finishing pending saves).

        Raises:
            FileNotFoundError: no complete checkpoint for ``step``.
        """
        self._manager.wait_until_finished()
        if int(step) not in self.all_steps():
            raise FileNotFoundError(f"no checkpoint for step {step} in {self.directory} (have {self.all_steps()})")
        self._manager.delete(int(step))

    def wait(self) -> None:
        """Block until background saves are written."""
        self._manager.wait_until_finished()

    def close(self) -> None:
        """Finish pending saves (and the background removal of killed saves' tmp dirs); release."""
        self._manager.wait_until_finished()
        # Orbax awaits its tmp-dir cleanup only inside save(); a run that saves nothing must not
        # leave it pending at exit. (Private hook, guarded: absent in other orbax versions.)
        await_cleanup = getattr(self._manager, "_maybe_await_cleanup_tmp_directory", None)
        if await_cleanup is not None:
            await_cleanup()
        self._manager.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def save_checkpoint(
    directory: str | os.PathLike,
    state: TrainState,
    *,
    data_state: dict | None = None,
    metadata: dict | None = None,
    max_to_keep: int = 3,
) -> None:
    """Save ``state`` at step ``int(state.step)`` into ``directory`` and wait until it is written.

    Args:
        directory: checkpoint directory (created if missing).
        state: train state.
        data_state: JSON-serialisable data-iterator position.
        metadata: JSON-serialisable record stored beside the arrays.
        max_to_keep: checkpoints kept in the directory.
    """
    with Checkpointer(directory, max_to_keep=max_to_keep, async_save=False) as ckpt:
        ckpt.save(state, data_state=data_state, metadata=metadata)


def restore_checkpoint(
    directory: str | os.PathLike, template: TrainState, *, step: int | None = None
) -> tuple[TrainState, dict, dict]:
    """Restore the latest (or a given) checkpoint of ``directory`` shaped like ``template``.

    Args:
        directory: checkpoint directory.
        template: state with the target structure, dtypes and shardings.
        step: step to restore (default: latest).

    Returns:
        ``(state, data_state, metadata)``.

    Raises:
        FileNotFoundError: missing directory or no complete checkpoint in it (names the path).
        ValueError: corrupt or incompatible checkpoint (names the path).
    """
    with Checkpointer(directory, read_only=True) as ckpt:
        return ckpt.restore(template, step)


def latest_checkpoint_step(directory: str | os.PathLike) -> int | None:
    """Newest complete checkpoint step in ``directory`` (None if missing or empty)."""
    if not Path(directory).is_dir():
        return None
    with Checkpointer(directory, read_only=True) as ckpt:
        return ckpt.latest_step()


def best_checkpoint_dir(directory: str | os.PathLike) -> Path:
    """Where :func:`jaxtalk.train.train` keeps the best-validated checkpoint of run ``directory``.

    Open it like any checkpoint directory, e.g.
    ``Checkpointer(best_checkpoint_dir(d), read_only=True).restore_saved()``.

    Args:
        directory: the run's checkpoint directory (``ckpt_dir`` of ``train``).

    Returns:
        ``<directory>/best``.
    """
    return Path(directory) / BEST_DIR


def read_best(directory: str | os.PathLike) -> dict[str, Any] | None:
    """The best-checkpoint record of run ``directory``: which metric chose it and its value.

    Args:
        directory: the run's checkpoint directory (``ckpt_dir`` of ``train``).

    Returns:
        ``{"metric", "mode", "value", "step", "eval"}`` (``eval``: all evaluation metrics of that
        step), or None when the run has no best checkpoint.

    Raises:
        ValueError: a best checkpoint whose metadata cannot be read or has no ``best`` record.
    """
    best = best_checkpoint_dir(directory)
    if not best.is_dir():
        return None
    with Checkpointer(best, read_only=True) as ckpt:
        if ckpt.latest_step() is None:
            return None
        meta = ckpt.read_metadata()
    record = meta.get("best")
    if not isinstance(record, dict) or not {"metric", "mode", "value", "step"} <= set(record):
        raise ValueError(f"checkpoint {best} has no best-checkpoint record in its metadata (got keys {sorted(meta)})")
    return record


def read_history(directory: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of ``<directory>/history.jsonl`` (empty when there is none).

    A torn last line (a run killed while appending) is skipped; a bad line elsewhere is an error.
    Non-finite values are stored as JSON ``null`` and read back as NaN.

    Args:
        directory: the run's checkpoint directory.

    Returns:
        One dict per row, in file order: ``{"type": "train", "step", "loss", "metrics", "window",
        "time"}`` or ``{"type": "eval", "step", "eval", "time"}`` (plus ``"best": bool`` when the
        run tracked a best metric).

    Raises:
        ValueError: a line other than the last is not a JSON object (names the file and line).
    """
    return [_nan_from_null(row) for row in read_jsonl_rows(Path(directory) / HISTORY_FILE, "history row")]


def read_jsonl_rows(path: str | os.PathLike, what: str, *, required: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """The JSON objects of a log a run appends to, one per line (empty when the file is missing).

    A torn last line (a run killed while appending) is skipped; a bad line elsewhere is an error.

    Args:
        path: the ``.jsonl`` file.
        what: what a row is, for the error message.
        required: keys every row must have.

    Raises:
        ValueError: a line other than the last is not such an object (names the file and line).
    """
    path = Path(path)
    if not path.is_file():
        return []
    lines = path.read_text(encoding="utf-8").splitlines()
    rows = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
            if not isinstance(row, dict) or any(k not in row for k in required):
                raise ValueError("not a JSON object" + (f" with {', '.join(required)}" if required else ""))
        except ValueError as err:
            if number == len(lines):
                break  # torn final append
            raise ValueError(f"{path}:{number} is not a {what}: {err}") from None
        rows.append(row)
    return rows


def _nan_from_null(row: dict[str, Any]) -> dict[str, Any]:
    # Metric values written as null (JSON has no NaN) come back as NaN floats.
    out = dict(row)
    if "loss" in out and out["loss"] is None:
        out["loss"] = math.nan
    for key in ("metrics", "eval"):
        if isinstance(out.get(key), dict):
            out[key] = {k: math.nan if v is None else v for k, v in out[key].items()}
    return out
