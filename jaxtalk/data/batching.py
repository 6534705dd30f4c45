"""Deterministic batching: per-epoch seeded shuffling, length buckets with padding masks, and an
explicit, JSON-serialisable position so a checkpoint can resume the exact batch sequence.

Two kinds of dataset are accepted:

* a mapping ``name -> array`` whose arrays share a leading example axis (fixed-size examples);
* a sequence of examples, each a mapping ``name -> array``; the arrays named in ``sequence_keys``
  share a leading time axis whose length varies per example. They are padded to the smallest bucket
  length that fits and the batch gains a ``(B, T)`` boolean padding mask (True = real frame).

The batch order of epoch ``e`` is a pure function of ``(seed, e)`` (``np.random.default_rng((seed,
e))``), so the position ``(epoch, index)`` is all that a checkpoint needs to continue the sequence.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["BatchIterator", "fit_length", "length_buckets", "window_starts"]

Batch = dict[str, np.ndarray]


def fit_length(x: np.ndarray, n: int) -> np.ndarray:
    """``x`` cropped, or extended by repeating its last row, to exactly ``n`` rows along axis 0 (a
    window's tokens past a clip's end; TIMAR's evaluation of the frames after the last whole turn)."""
    if x.shape[0] >= n:
        return x[:n]
    return np.concatenate([x, np.repeat(x[-1:], n - x.shape[0], axis=0)], axis=0)


def window_starts(num_frames: int, window: int, hop: int, *, align: int = 1, pad_short: bool = True) -> list[int]:
    """Starts of ``window``-frame windows every ``hop`` frames, the last one flush with the end (with
    ``align > 1`` rounded up to the period, so it may overhang: the caller pads).

    Every recipe, FreeTalk's evaluation and its overlapping inference windows cut clips with this.

    Args:
        num_frames: the clip's length.
        window: frames per window.
        hop: frames between window starts (rounded up to a multiple of ``align``).
        align: starts are multiples of this (a token period).
        pad_short: a clip shorter than ``window`` gives one window at 0 (the caller pads it and masks
            the padding); False: it gives none.

    Returns:
        Increasing start frames.

    Raises:
        ValueError: ``window``, ``hop`` or ``align`` below 1.
    """
    if window < 1 or hop < 1 or align < 1:
        raise ValueError(f"window, hop and align must be >= 1, got {window}, {hop}, {align}")
    if num_frames < window and not pad_short:
        return []
    hop = int(np.ceil(hop / align) * align)
    last = int(np.ceil(max(num_frames - window, 0) / align) * align)
    return sorted(set(range(0, last + 1, hop)) | {last})


def length_buckets(lengths: Sequence[int] | np.ndarray, num_buckets: int, *, multiple: int = 1) -> tuple[int, ...]:
    """Choose a small set of bucket lengths from the example lengths (quantiles, rounded up).

    Args:
        lengths: length of every example, shape ``(N,)``.
        num_buckets: the most buckets to return (duplicates after rounding are merged).
        multiple: round every bucket length up to a multiple of this (e.g. a chunk size).

    Returns:
        Sorted distinct bucket lengths; the largest one fits the longest example.

    Raises:
        ValueError: empty or non-positive lengths, ``num_buckets < 1`` or ``multiple < 1``.
    """
    lengths = np.asarray(lengths)
    if lengths.ndim != 1 or lengths.size == 0:
        raise ValueError(f"lengths must be a non-empty 1-D sequence, got shape {lengths.shape}")
    if np.any(lengths < 1):
        raise ValueError(f"every length must be >= 1, got minimum {int(lengths.min())}")
    if num_buckets < 1 or multiple < 1:
        raise ValueError(f"num_buckets and multiple must be >= 1, got {num_buckets} and {multiple}")
    # Bucket j ends at the smallest length covering a (j+1)/num_buckets share of the examples.
    qs = np.quantile(lengths, np.arange(1, num_buckets + 1) / num_buckets, method="inverted_cdf")
    rounded = (np.ceil(qs / multiple) * multiple).astype(int)
    return tuple(sorted({int(b) for b in rounded}))


class BatchIterator(Iterator[Batch]):
    """Endless (or ``num_epochs``-long) deterministic iterator of padded batches.

    Each batch is a dict of NumPy arrays with leading axis ``batch_size``. For sequence datasets the
    arrays in ``sequence_keys`` have shape ``(B, T, ...)`` with ``T`` one of the bucket lengths and
    ``batch[mask_key]`` is the ``(B, T)`` bool padding mask. With ``drop_remainder=False`` the last,
    partial batch of each bucket is filled with all-padding rows and every batch carries
    ``batch[valid_key]`` (``(B,)`` bool, False for fill rows), so every example appears exactly once
    per epoch and all batches keep the static batch size.

    Within an epoch, batches are formed inside one bucket (so padding is bounded by the bucket
    spacing) and the order of batches across buckets is shuffled with the same epoch RNG.

    The position is ``get_state() -> {"epoch", "index", ...}`` and ``set_state(state)``.
    """

    def __init__(
        self,
        dataset: Mapping[str, Any] | Sequence[Mapping[str, Any]],
        batch_size: int,
        *,
        seed: int = 0,
        shuffle: bool = True,
        drop_remainder: bool = True,
        buckets: Sequence[int] | None = None,
        sequence_keys: Sequence[str] | None = None,
        pad_value: float = 0.0,
        mask_key: str = "mask",
        valid_key: str = "valid",
        num_epochs: int | None = None,
    ) -> None:
        """Build the iterator and validate the dataset once, up front.

        Args:
            dataset: mapping of arrays sharing a leading example axis, or a sequence of examples
                (mappings of arrays) for variable-length data.
            batch_size: examples per batch (static: every batch has exactly this many rows).
            seed: base seed; epoch ``e`` shuffles with ``np.random.default_rng((seed, e))``.
            shuffle: shuffle examples and batch order each epoch (False keeps dataset order).
            drop_remainder: drop the partial batch of each bucket (True) or fill it with padding rows
                marked invalid in ``batch[valid_key]`` (False).
            buckets: bucket lengths for sequence datasets (default: one bucket, the longest example).
            sequence_keys: keys padded along their leading time axis (default: all keys). Other keys
                are stacked as they are and must have the same shape in every example.
            pad_value: value written into padded frames and fill rows.
            mask_key: name of the ``(B, T)`` padding mask added to sequence batches.
            valid_key: name of the ``(B,)`` row-validity flag added when ``drop_remainder=False``.
            num_epochs: stop after this many epochs (None: endless).

        Raises:
            ValueError: empty dataset, non-positive batch size, arrays whose example axes disagree,
                examples with missing keys or inconsistent lengths, an example longer than the
                largest bucket, a batch size that leaves an epoch with no batch, or a key clash with
                ``mask_key``/``valid_key``.
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if num_epochs is not None and num_epochs < 1:
            raise ValueError(f"num_epochs must be >= 1 or None, got {num_epochs}")
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.shuffle = bool(shuffle)
        self.drop_remainder = bool(drop_remainder)
        self.pad_value = pad_value
        self.mask_key = mask_key
        self.valid_key = valid_key
        self.num_epochs = num_epochs

        if isinstance(dataset, Mapping):
            self._init_arrays(dataset)
        else:
            self._init_sequences(dataset, buckets, sequence_keys)
        added = ((mask_key,) if self.is_sequence else ()) + (() if drop_remainder else (valid_key,))
        for reserved in added:
            if reserved in self._keys:
                raise ValueError(f"dataset key {reserved!r} clashes with a key the iterator adds to each batch")

        if self.batches_per_epoch == 0:
            raise ValueError(
                f"batch_size={batch_size} with drop_remainder=True leaves no batch per epoch "
                f"(bucket sizes {self._bucket_sizes()})"
            )
        self._epoch = 0
        self._index = 0
        self._plan: list[np.ndarray] | None = None  # batches of the current epoch (indices, -1 = fill)

    # ------------------------------------------------------------------ dataset validation
    def _init_arrays(self, dataset: Mapping[str, Any]) -> None:
        if not dataset:
            raise ValueError("dataset mapping is empty (no arrays)")
        arrays = {k: np.asarray(v) for k, v in dataset.items()}
        sizes = {k: (a.shape[0] if a.ndim else None) for k, a in arrays.items()}
        n = next(iter(sizes.values()))
        for k, s in sizes.items():
            if s is None:
                raise ValueError(f"dataset array {k!r} is a scalar; every array needs an example axis")
            if s != n:
                raise ValueError(f"dataset arrays disagree on the number of examples: {k!r} has {s}, expected {n}")
        if n == 0:
            raise ValueError("dataset is empty (0 examples)")
        self.is_sequence = False
        self._arrays = arrays
        self._keys = tuple(arrays)
        self.num_examples = int(n)
        self.buckets: tuple[int, ...] | None = None
        self._bucket_of = np.zeros(n, dtype=np.int64)

    def _init_sequences(
        self, dataset: Sequence[Mapping[str, Any]], buckets: Sequence[int] | None, sequence_keys: Sequence[str] | None
    ) -> None:
        if len(dataset) == 0:
            raise ValueError("dataset is empty (0 examples)")
        examples = [{k: np.asarray(v) for k, v in ex.items()} for ex in dataset]
        keys = tuple(examples[0])
        if not keys:
            raise ValueError("example 0 has no arrays")
        seq_keys = tuple(keys if sequence_keys is None else sequence_keys)
        for k in seq_keys:
            if k not in keys:
                raise ValueError(f"sequence key {k!r} is not in example 0 (keys {list(keys)})")
        lengths = np.empty(len(examples), dtype=np.int64)
        for i, ex in enumerate(examples):
            if set(ex) != set(keys):
                raise ValueError(f"example {i} has keys {sorted(ex)}, expected {sorted(keys)}")
            ls = {k: (ex[k].shape[0] if ex[k].ndim else None) for k in seq_keys}
            first = ls[seq_keys[0]]
            for k, length in ls.items():
                if length is None:
                    raise ValueError(f"example {i}: sequence array {k!r} is a scalar (needs a time axis)")
                if length != first:
                    raise ValueError(f"example {i}: sequence arrays disagree on length ({ls})")
                if ex[k].shape[1:] != examples[0][k].shape[1:]:
                    raise ValueError(
                        f"example {i}: {k!r} has per-frame shape {ex[k].shape[1:]}, "
                        f"expected {examples[0][k].shape[1:]}"
                    )
            for k in keys:
                if k not in seq_keys and ex[k].shape != examples[0][k].shape:
                    raise ValueError(f"example {i}: {k!r} has shape {ex[k].shape}, expected {examples[0][k].shape}")
            if first == 0:
                raise ValueError(f"example {i} has length 0")
            lengths[i] = first
        if buckets is None:
            bucket_arr = np.array([lengths.max()])
        else:
            bucket_arr = np.array(sorted(set(int(b) for b in buckets)))
            if bucket_arr.size == 0 or bucket_arr[0] < 1:
                raise ValueError(f"buckets must be positive lengths, got {list(buckets)}")
        too_long = np.nonzero(lengths > bucket_arr[-1])[0]
        if too_long.size:
            i = int(too_long[0])
            raise ValueError(
                f"example {i} has length {int(lengths[i])}, longer than the largest bucket {int(bucket_arr[-1])}"
            )
        self.is_sequence = True
        self._examples = examples
        self._keys = keys
        self.sequence_keys = seq_keys
        self.num_examples = len(examples)
        self.lengths = lengths
        self.buckets = tuple(int(b) for b in bucket_arr)
        # Smallest bucket that fits each example.
        self._bucket_of = np.searchsorted(bucket_arr, lengths, side="left")

    def _bucket_sizes(self) -> list[int]:
        return np.bincount(self._bucket_of, minlength=len(self.buckets or (0,))).tolist()

    # ------------------------------------------------------------------ epoch plan
    @property
    def batches_per_epoch(self) -> int:
        """Number of batches in every epoch (the same for all epochs)."""
        per = [(s // self.batch_size if self.drop_remainder else -(-s // self.batch_size)) for s in self._bucket_sizes()]
        return int(sum(per))

    @property
    def variable_axes(self) -> tuple[int, ...]:
        """Axes whose size may change between batches (the padded time axis of bucketed data)."""
        return (1,) if self.is_sequence and self.buckets is not None and len(self.buckets) > 1 else ()

    def epoch_plan(self, epoch: int) -> list[np.ndarray]:
        """Example indices of every batch of ``epoch`` (``-1`` marks a fill row); pure in (seed, epoch).

        Args:
            epoch: epoch number (>= 0).

        Returns:
            ``batches_per_epoch`` int64 arrays of shape ``(batch_size,)``.
        """
        rng = np.random.default_rng((self.seed, epoch))
        order = rng.permutation(self.num_examples) if self.shuffle else np.arange(self.num_examples)
        batches: list[np.ndarray] = []
        for b in range(len(self.buckets) if self.buckets else 1):
            members = order[self._bucket_of[order] == b]  # keeps the shuffled order inside the bucket
            full = len(members) // self.batch_size
            for j in range(full):
                batches.append(members[j * self.batch_size : (j + 1) * self.batch_size])
            rest = members[full * self.batch_size :]
            if rest.size and not self.drop_remainder:
                batches.append(np.concatenate([rest, np.full(self.batch_size - rest.size, -1, np.int64)]))
        if self.shuffle:
            perm = rng.permutation(len(batches))
            batches = [batches[i] for i in perm]
        return batches

    # ------------------------------------------------------------------ position state
    def get_state(self) -> dict[str, Any]:
        """The position as a JSON-serialisable dict: the next batch is batch ``index`` of ``epoch``."""
        return {
            "epoch": self._epoch,
            "index": self._index,
            "seed": self.seed,
            "num_examples": self.num_examples,
            "batch_size": self.batch_size,
            "buckets": list(self.buckets) if self.buckets else None,
        }

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Move to a position saved by :meth:`get_state`.

        Raises:
            ValueError: a missing field, or a state saved for a different seed, dataset size, batch
                size or bucket set (continuing would silently give a different sequence).
        """
        for field in ("epoch", "index", "seed", "num_examples", "batch_size", "buckets"):
            if field not in state:
                raise ValueError(f"batch iterator state is missing {field!r}: {dict(state)}")
        mine = self.get_state()
        for field in ("seed", "num_examples", "batch_size", "buckets"):
            if state[field] != mine[field]:
                raise ValueError(
                    f"batch iterator state was saved with {field}={state[field]!r}, this iterator has {mine[field]!r}"
                )
        epoch, index = int(state["epoch"]), int(state["index"])
        if epoch < 0 or not 0 <= index <= self.batches_per_epoch:
            raise ValueError(f"invalid position epoch={epoch}, index={index} ({self.batches_per_epoch} batches/epoch)")
        self._epoch, self._index, self._plan = epoch, index, None

    # ------------------------------------------------------------------ iteration
    def __iter__(self) -> BatchIterator:
        return self

    def __next__(self) -> Batch:
        if self._index >= self.batches_per_epoch:
            self._epoch, self._index, self._plan = self._epoch + 1, 0, None
        if self.num_epochs is not None and self._epoch >= self.num_epochs:
            raise StopIteration
        if self._plan is None:
            self._plan = self.epoch_plan(self._epoch)
        idx = self._plan[self._index]
        self._index += 1
        return self._gather(idx)

    def _gather(self, idx: np.ndarray) -> Batch:
        valid = idx >= 0
        safe = np.where(valid, idx, 0)
        if not self.is_sequence:
            batch = {}
            for k, a in self._arrays.items():
                rows = a[safe]
                if not valid.all():
                    rows = np.where(valid.reshape((-1,) + (1,) * (a.ndim - 1)), rows, np.asarray(self.pad_value, a.dtype))
                batch[k] = rows
        else:
            t = self.buckets[int(self._bucket_of[safe[valid][0]])]
            batch = {}
            first = self._examples[0]
            for k in self._keys:
                if k in self.sequence_keys:
                    out = np.full((self.batch_size, t) + first[k].shape[1:], self.pad_value, dtype=first[k].dtype)
                    for r, i in enumerate(safe):
                        if valid[r]:
                            out[r, : self.lengths[i]] = self._examples[i][k]
                else:
                    out = np.full((self.batch_size,) + first[k].shape, self.pad_value, dtype=first[k].dtype)
                    for r, i in enumerate(safe):
                        if valid[r]:
                            out[r] = self._examples[i][k]
                batch[k] = out
            lens = np.where(valid, self.lengths[safe], 0)
            batch[self.mask_key] = np.arange(t)[None, :] < lens[:, None]
        if not self.drop_remainder:
            batch[self.valid_key] = valid
        return batch
