"""The one loader every model trains from: a prepared dataset (``jaxtalk prepare``) read through grain.

* :class:`PreparedData` opens a prepared folder: the manifest, the splits, and random access to each
  clip's record in the ArrayRecord shards (only the arrays asked for are decoded).
* A model's recipe says how windows are cut: ``recipe.table(data, split)`` lists every window as a
  row of integers (clip, start, ...) from the manifest alone, and ``recipe.example(data, row)`` reads
  one window. :func:`make_loader` turns that into batches with grain: a seeded shuffle that differs
  every epoch, the recipe's map, batching, and per-process sharding of the batches (each of
  ``jax.process_count()`` processes reads its own part of every global batch). Its position
  (``get_state``/``set_state``) is saved in the orbax checkpoint by the training loop, so an
  interrupted run resumes on the same batch.

Memory stays bounded by the batch, not the dataset: windows are read from disk when they are needed,
and each loader keeps at most ``cache_bytes`` (:data:`CACHE_BYTES`, 256 MiB) of decoded records. A
window reads only the one-second chunks of its clip that it overlaps (``record(..., frames=...)``).
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import functools
import json
import threading
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from jaxtalk.data.prepare import FORMAT_VERSION, MANIFEST, SHARDS, decode_array, is_current, record_positions

__all__ = ["PreparedData", "WindowRecipe", "WindowLoader", "make_loader", "open_data", "iter_windows"]

# Batches read ahead, by this many threads. grain's default (500 elements, here batches, 16 threads)
# would hold hundreds of batches in memory (gigabytes of STM's padded vertices) and keep 16 threads
# busy long after the training step stopped asking.
PREFETCH_BATCHES = 8
READ_THREADS = 4
# Decoded arrays a loader keeps, per process (LRU, by bytes). Neighbouring windows overlap (TokTalk and
# ATS hop a quarter window, STM reads each clip once per mesh) and TokTalk reads a second clip per
# window for its style, so without it every window reads and decodes its chunks again.
CACHE_BYTES = 256 * 2**20


class _RecordCache:
    """Least-recently-used decoded records, at most ``budget`` bytes of them (thread-safe).

    Keyed by ``(clip, key, chunk)`` (chunk -1 for an array that is not per frame). Cached arrays are
    read-only, so a caller that writes into one fails instead of changing later windows. A copy
    (e.g. pickled into a grain worker process) starts empty.
    """

    def __init__(self, budget: int) -> None:
        self.budget = int(budget)
        self._arrays: collections.OrderedDict[tuple[int, str, int], np.ndarray] = collections.OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:
        return {"budget": self.budget}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["budget"])

    def get(self, key: tuple[int, str, int]) -> np.ndarray | None:
        with self._lock:
            array = self._arrays.get(key)
            if array is not None:
                self._arrays.move_to_end(key)
            return array

    def put(self, key: tuple[int, str, int], array: np.ndarray) -> None:
        array.flags.writeable = False
        if array.nbytes > self.budget:
            return
        with self._lock:
            old = self._arrays.pop(key, None)
            self._bytes += array.nbytes - (0 if old is None else old.nbytes)
            self._arrays[key] = array
            while self._bytes > self.budget:
                _, dropped = self._arrays.popitem(last=False)
                self._bytes -= dropped.nbytes


class PreparedData:
    """A prepared dataset folder.

    Attributes:
        root: the folder.
        manifest: ``manifest.json`` as a dict.
        clips: the manifest's clip entries (name, speaker, split, frames, partner, ...), in record order.
    """

    def __init__(self, root: str | Path) -> None:
        """Open ``root``.

        Raises:
            FileNotFoundError: no folder, or no ``manifest.json`` in it (not prepared yet).
            ValueError: a manifest of another format version, or shards missing from disk.
        """
        self.root = Path(root)
        path = self.root / MANIFEST
        if not path.is_file():
            raise FileNotFoundError(
                f"{str(self.root)!r} is not a prepared dataset (no {MANIFEST}); make one with `jaxtalk prepare SRC --out DIR`"
            )
        self.manifest = json.loads(path.read_text())
        if self.manifest.get("format") != FORMAT_VERSION:
            raise ValueError(f"{path}: format {self.manifest.get('format')!r}, this jaxtalk reads {FORMAT_VERSION}; "
                             "prepare again")
        self.clips: list[dict[str, Any]] = self.manifest["clips"]
        self._by_name = {c["name"]: i for i, c in enumerate(self.clips)}
        missing = [s for s in self.manifest["shards"] if not (self.root / SHARDS / s).is_file()]
        if missing:
            raise ValueError(f"{self.root}: shards missing from disk: {missing[:3]}; prepare again")

    def __len__(self) -> int:
        return len(self.clips)

    def __repr__(self) -> str:
        counts = {s: len(v) for s, v in self.manifest["splits"].items() if v}
        return f"PreparedData({str(self.root)!r}, clips={len(self)}, splits={counts})"

    def __getstate__(self) -> dict:
        # Readers hold file handles: a copy (e.g. a grain worker) reopens them.
        return {k: v for k, v in self.__dict__.items() if k != "_readers"}

    @property
    def key(self) -> str:
        """Identifies the prepared content (source spec and feature settings), for run records."""
        return f"{self.manifest['source']['spec']}#{self.manifest['settings_hash']}"

    def index(self, name: str) -> int:
        """The position of clip ``name``.

        Raises:
            KeyError: no such clip (naming it).
        """
        if name not in self._by_name:
            raise KeyError(f"no clip {name!r} in {self.root}")
        return self._by_name[name]

    def split(self, name: str, *, motion: bool = True) -> list[int]:
        """Clip positions of a split (only clips with motion when ``motion``).

        Raises:
            ValueError: an unknown split.
        """
        if name not in self.manifest["splits"]:
            raise ValueError(f"unknown split {name!r}; known: {', '.join(self.manifest['splits'])}")
        return [i for i, c in enumerate(self.clips) if c["split"] == name and (c["has_motion"] or not motion)]

    def partner(self, i: int) -> int | None:
        """Position of clip ``i``'s conversation partner, or None."""
        p = self.clips[i]["partner"]
        return self._by_name.get(p) if p is not None else None

    @functools.cached_property
    def _readers(self) -> dict[str, Any]:
        from array_record.python.array_record_module import ArrayRecordReader

        return {s: ArrayRecordReader(str(self.root / SHARDS / s)) for s in self.manifest["shards"]}

    _cache: _RecordCache | None = None

    def cached(self, budget: int = CACHE_BYTES) -> PreparedData:
        """This dataset with a cache of up to ``budget`` bytes of decoded arrays (LRU, per process).

        Called with ``keys``, its :meth:`record` returns the arrays that are not per frame READ-ONLY
        (copy before writing); what it returns is bitwise what the uncached one does. ``budget <= 0``:
        no cache.
        """
        other = copy.copy(self)  # shares the manifest; opens its own readers
        other._cache = _RecordCache(budget) if budget > 0 else None
        return other

    def record(self, i: int, keys: Sequence[str] | None = None, frames: tuple[int, int] | None = None) -> dict[str, np.ndarray]:
        """The arrays of clip ``i``.

        Args:
            i: the clip's position.
            keys: only these arrays (default all); absent keys are left out.
            frames: ``(start, stop)``: the per-frame arrays (:data:`~jaxtalk.data.prepare.FRAME_KEYS`)
                cut to rows ``[start, stop)`` (as ``array[start:stop]``), read from the chunks that
                hold them and no others; the other arrays are whole.

        Raises:
            ValueError: ``frames`` with ``start < 0`` or ``stop < start``.
        """
        c = self.clips[i]
        size, chunks = self.manifest["chunk_frames"], c["chunks"]
        if frames is None:
            start, stop = 0, chunks * size
        else:
            start, stop = (int(v) for v in frames)
            if start < 0 or stop < start:
                raise ValueError(f"frames must be (start, stop) with 0 <= start <= stop, got {frames}")
        # At least one chunk, so that a range past the clip's end gives empty arrays, as slicing does.
        first = min(start // size, chunks - 1)
        last = max(min(-(-stop // size), chunks), first + 1)
        names = c["head"] + c["framed"] if keys is None else list(dict.fromkeys(keys))
        got = self._read(i, record_positions(c, names, range(first, last)), cached=keys is not None)
        out = {k: got[(k, -1)] for k in names if k in c["head"]}
        for k in names:
            if k in c["framed"]:
                whole = np.concatenate([got[(k, ch)] for ch in range(first, last)])
                out[k] = whole[start - first * size:stop - first * size]
        return out

    def _read(self, i: int, where: list[tuple[str, int, int]], *, cached: bool) -> dict[tuple[str, int], np.ndarray]:
        """The arrays of records ``where`` (:func:`~jaxtalk.data.prepare.record_positions`) of clip
        ``i`` by ``(key, chunk)``: the cache's (when ``cached``), the others read in one call."""
        cache = self._cache if cached else None
        got: dict[tuple[str, int], np.ndarray] = {}
        missing = []
        for k, ch, index in where:
            hit = cache.get((i, k, ch)) if cache is not None else None
            if hit is None:
                missing.append((k, ch, index))
            else:
                got[(k, ch)] = hit
        if missing:
            records = self._readers[self.clips[i]["shard"]].read([index for _, _, index in missing])
            for (k, ch, _), data in zip(missing, records):
                # Chunks are concatenated (copied) by the caller; a head array is returned as it is.
                array = decode_array(data, copy=ch < 0 and cache is None)
                got[(k, ch)] = array
                if cache is not None:
                    cache.put((i, k, ch), array)
        return got

    def motion_stats(self, floor: float = 0.05) -> dict[str, np.ndarray]:
        """Mean and std of the training split's 56-d motion (per channel), a standardizer.

        Args:
            floor: each std is at least ``floor`` x the mean std (see
                :func:`jaxtalk.data.standardize.fit_standardizer`), so a channel that barely moves in
                the training data is not blown up into noise.

        Raises:
            ValueError: a dataset whose training split has no motion.
        """
        from jaxtalk.data.standardize import floor_std

        stats = self.manifest["stats"]
        if stats is None:
            raise ValueError(f"{self.root}: the training split has no motion clips (no statistics)")
        return {"mean": np.asarray(stats["motion_mean"], np.float32),
                "std": floor_std(np.asarray(stats["motion_std"], np.float64), floor)}

    def tokenizer(self) -> Any:
        """The VQ tokenizer fitted by ``prepare`` (``--tokens vq``), or None."""
        if not self.manifest.get("tokenizer"):
            return None
        from jaxtalk.audio import VQTokenizer

        return VQTokenizer.load(self.root / self.manifest["tokenizer"])


def open_data(spec: str | Path, *, cache_dir: str | Path = ".cache/prepared", progress: bool = True,
              features: str | None = None) -> PreparedData:
    """A prepared dataset from a folder, or ``synthtalk:SIZE[:SEED]`` (prepared once into ``cache_dir``).

    Args:
        spec: a prepared folder (``jaxtalk prepare``) or ``synthtalk:SIZE[:SEED]``.
        cache_dir: where ``synthtalk:`` data is prepared: log-mel into ``synthtalk-SIZE-seedS``, a
            speech encoder's features into ``synthtalk-SIZE-seedS-KIND-DIGEST``, ``DIGEST`` the start of
            :meth:`~jaxtalk.data.prepare.PrepareSettings.digest` (which covers the checkpoint's files),
            so every front end has a folder of its own and each is prepared once.
        progress: show the progress bar while preparing.
        features: the speech front end (``logmel``, ``hubert:PATH`` or ``wav2vec2:PATH``, as
            ``jaxtalk prepare --features`` takes it). None: ``logmel`` for ``synthtalk:``, the folder's
            own for a folder. A folder prepared with other features is refused: its features were
            computed once, by ``prepare``.

    Raises:
        FileNotFoundError: a folder that is not prepared, or a speech encoder's checkpoint folder, its
            ``config.json`` or its weights missing (checked before any corpus is generated).
        ValueError: unknown ``features``, or a folder prepared with other features (both named).
    """
    from jaxtalk.data.features import parse_audio_features
    from jaxtalk.data.prepare import PrepareSettings

    text = str(spec)
    if text.startswith("synthtalk:"):
        from jaxtalk.data.prepare import prepare
        from jaxtalk.data.sources import open_source

        settings = PrepareSettings(audio=features or "logmel")
        parts = text.split(":")
        seed = parts[2] if len(parts) > 2 else "0"
        name = f"synthtalk-{parts[1]}-seed{seed}"
        if settings.audio != "logmel":  # log-mel keeps the folder it always had
            name += f"-{settings.audio.partition(':')[0]}-{settings.digest()[:8]}"
        out = Path(cache_dir) / name
        if not is_current(out):  # not prepared, or prepared by an older jaxtalk
            prepare(open_source(text, cache_dir=Path(cache_dir) / "synthtalk"), out, settings, progress=progress)
        return PreparedData(out)
    data = PreparedData(spec)
    if features is not None:
        own = data.manifest["settings"]["audio"]
        if features != own and parse_audio_features(features).spec != own:
            raise ValueError(f"{data.root} was prepared with --features {own}, not {features}: drop --features to "
                             f"use its own, or prepare the data again with --features {features}")
    return data


@runtime_checkable
class WindowRecipe(Protocol):
    """How a model cuts its training examples from prepared clips.

    Runtime-checkable so that a type checker applied at run time (the test suite's jaxtyping/beartype
    hook) can check a ``recipe: WindowRecipe`` argument instead of failing at import.
    """

    def table(self, data: PreparedData, split: str) -> np.ndarray:
        """Every window of ``split`` as an ``(N, k)`` int64 table, a pure function of the manifest."""

    def example(self, data: PreparedData, row: np.ndarray) -> dict[str, np.ndarray]:
        """The arrays of one window (no batch axis)."""


@dataclasses.dataclass(frozen=True)
class _Example:
    # A top-level callable (not a lambda) so that grain can copy the pipeline into workers.
    data: PreparedData
    recipe: Any

    def __call__(self, row: np.ndarray) -> dict[str, np.ndarray]:
        return self.recipe.example(self.data, row)


class WindowLoader(Iterator[dict[str, np.ndarray]]):
    """Endless, deterministic batches of windows with a checkpointable position (see :func:`make_loader`).

    Attributes:
        num_windows: this process's share of the windows (all of them over the number of processes).
        batch_size: windows per batch (this process's part of a global batch).
        variable_axes: ``()``: every batch has the same shape.
    """

    variable_axes: tuple[int, ...] = ()

    def __init__(self, dataset: Any, fingerprint: dict[str, Any], num_windows: int, batch_size: int) -> None:
        self._dataset = dataset
        self._fingerprint = fingerprint
        self._it = iter(dataset)
        self.num_windows = num_windows
        self.batch_size = batch_size

    def __next__(self) -> dict[str, np.ndarray]:
        return next(self._it)

    def get_state(self) -> dict[str, Any]:
        """The position (JSON-serialisable) plus what it is valid for."""
        return {**self._fingerprint, "grain": self._it.get_state()}

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Continue from a :meth:`get_state` position.

        A position counts global batches, the same on every process (see :func:`make_loader`), so
        any process's position continues every process of a run with as many processes (a
        multi-process checkpoint holds process 0's).

        Raises:
            ValueError: a position saved for other data, windows, seed, batch size or process count.
        """
        for k, v in self._fingerprint.items():
            saved = state.get(k)
            if k == "shard" and isinstance(saved, list) and len(saved) == 2:
                saved, v = saved[1], v[1]  # the process count; the index does not matter
                if saved != v:
                    raise ValueError(f"loader state was saved with shard={state.get(k)!r} (of {saved} processes), "
                                     f"this loader has {self._fingerprint[k]!r}")
            elif saved != v:
                raise ValueError(f"loader state was saved with {k}={saved!r}, this loader has {v!r}")
        self._it.set_state(state["grain"])


def make_loader(
    data: PreparedData,
    recipe: WindowRecipe,
    split: str,
    batch_size: int,
    *,
    seed: int = 0,
    shuffle: bool = True,
    num_epochs: int | None = None,
    shard: tuple[int, int] | None = None,
    cache_bytes: int = CACHE_BYTES,
) -> WindowLoader:
    """Batches of ``recipe`` windows of ``split``, through grain.

    Args:
        data: the prepared dataset.
        recipe: the model's window recipe.
        split: which split.
        batch_size: windows per batch on this process.
        seed: shuffle seed (epoch ``e`` has its own order).
        shuffle: shuffle the windows (False: table order).
        num_epochs: stop after this many passes (None: endless).
        shard: ``(index, count)`` of this process (default ``jax.process_index()``,
            ``jax.process_count()``). The stream is the single-process stream of global batches of
            ``batch_size * count`` windows (the same shuffled table on every process), and process
            ``i`` yields rows ``[i * batch_size, (i + 1) * batch_size)`` of each: the part of the
            global batch :func:`jaxtalk.train.make_mesh` puts on its devices. So a run on ``count``
            processes sees the same global batches, row for row, as one process with
            ``batch_size * count`` (same seed), and resumes the same way; sharding the table instead
            (process ``i`` shuffling windows ``i::count``) would give other batches for every
            process count. Each process decodes only its own rows (grain is lazy). With
            ``num_epochs``, the processes together still read every window of each pass, so a
            last partial global batch leaves some processes one batch short: train multi-process
            on an endless loader (``num_epochs=None``, as the recipes do), or a collective step
            would wait forever for them.
        cache_bytes: decoded arrays the loader keeps (:meth:`PreparedData.cached`; 0: none). The
            batches are the same either way; the cache saves reading and decoding a clip's chunks
            again for each window that overlaps them.

    Returns:
        :class:`WindowLoader`.

    Raises:
        ValueError: no window in the split, or fewer windows than one global batch.
    """
    import grain

    if shard is None:
        import jax

        shard = (jax.process_index(), jax.process_count())
    table = np.asarray(recipe.table(data, split), np.int64)
    if table.size == 0:
        raise ValueError(f"split {split!r} of {data.root} has no {type(recipe).__name__} window")
    index, count = shard
    ds = grain.MapDataset.source(table)
    if len(table) < batch_size * count:
        raise ValueError(f"split {split!r} has {len(table)} windows, fewer than batch_size={batch_size} x {count} "
                         "process(es) (one global batch)")
    if shuffle:
        ds = ds.shuffle(seed=seed)
    ds = ds.repeat(num_epochs).map(_Example(data.cached(cache_bytes), recipe)).batch(batch_size, drop_remainder=True)
    if count > 1:  # batch k is block k % count of global batch k // count (see ``shard``)
        ds = ds[index::count]
    n = len(range(index, len(table), count))
    fingerprint = {"data": data.key, "split": split, "windows": int(len(table)), "seed": seed,
                   "batch_size": batch_size, "shard": list(shard), "recipe": type(recipe).__name__}
    return WindowLoader(ds.to_iter_dataset(grain.ReadOptions(num_threads=READ_THREADS, prefetch_buffer_size=PREFETCH_BATCHES)),
                        fingerprint, n, batch_size)


def iter_windows(data: PreparedData, recipe: WindowRecipe, split: str) -> Iterator[dict[str, np.ndarray]]:
    """Every window of ``split`` once, in table order (evaluation)."""
    for row in np.asarray(recipe.table(data, split), np.int64):
        yield recipe.example(data, row)
