"""The grain loader over a prepared dataset: batch shapes of the model recipes, bitwise resume from
``get_state``, state validation, per-process shards, per-epoch shuffling; ``PreparedData`` errors."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import pickle
import threading
import time

import numpy as np
import pytest

from jaxtalk.data import loader as loader_mod
from jaxtalk.data.loader import PreparedData, iter_windows, make_loader


@dataclasses.dataclass(frozen=True)
class Rows:
    """A recipe whose examples carry their own table row: ``(clip, start)`` of 25-frame windows."""

    window: int = 25

    def table(self, data: PreparedData, split: str) -> np.ndarray:
        rows = [(i, s) for i in data.split(split) for s in range(0, data.clips[i]["frames"] - self.window + 1, self.window)]
        return np.asarray(rows, np.int64).reshape(-1, 2)

    def example(self, data: PreparedData, row: np.ndarray) -> dict[str, np.ndarray]:
        i, s = (int(v) for v in row)
        return {"row": np.asarray(row, np.int64), "motion": data.record(i, ("motion",))["motion"][s:s + self.window]}


@pytest.fixture(scope="module")
def data(prepared_tiny):
    """The tiny SynthTalk corpus prepared once per session (read only here)."""
    return prepared_tiny


def _take(loader, n):
    return [next(loader) for _ in range(n)]


def _rows(batches):
    return [tuple(int(v) for v in r) for b in batches for r in b["row"]]


def _assert_batches_equal(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert sorted(x) == sorted(y)
        for k in x:
            assert x[k].dtype == y[k].dtype and x[k].tobytes() == y[k].tobytes(), k


# ------------------------------------------------------------------------------------------ shapes
def test_toktalk_batches_have_the_recipes_shapes_and_equal_its_examples(data):
    from jaxtalk.models.toktalk.config import TokTalkConfig
    from jaxtalk.models.toktalk.recipe import TokTalkWindows

    config = TokTalkConfig()
    recipe = TokTalkWindows(config, 100)
    loader = make_loader(data, recipe, "train", 4, shuffle=False, shard=(0, 1))
    batch = next(loader)
    assert batch["motion"].shape == (4, 100, 56) and batch["motion"].dtype == np.float32
    assert batch["tokens"].shape == (4, 50, 64)
    assert batch["style"].shape == (4, config.style_frames, 56)
    assert batch["mask"].shape == (4, 100) and batch["mask"].dtype == bool
    table = recipe.table(data, "train")
    assert loader.num_windows == len(table)
    for k in range(4):
        example = recipe.example(data, table[k])
        for key, value in example.items():
            np.testing.assert_array_equal(batch[key][k], value)


def test_toktalk_reference_clip_is_another_clip_of_the_speaker_or_the_target_as_configured(data):
    from jaxtalk.models.toktalk.config import TokTalkConfig
    from jaxtalk.models.toktalk.recipe import TokTalkWindows

    other = TokTalkWindows(TokTalkConfig(), 100).table(data, "train")
    speaker = {i: c["speaker"] for i, c in enumerate(data.clips)}
    assert all(speaker[int(r[2])] == speaker[int(r[0])] for r in other)
    assert (other[:, 2] != other[:, 0]).mean() > 0.9  # the tiny corpus has several clips per speaker
    target = TokTalkWindows(TokTalkConfig(style_source="target"), 100).table(data, "train")
    np.testing.assert_array_equal(target[:, 2], target[:, 0])


def test_toktalk_reference_clips_shorter_than_style_frames_are_zero_padded_and_masked(data):
    import jax.numpy as jnp

    from jaxtalk.models.toktalk.config import TokTalkConfig
    from jaxtalk.models.toktalk.model import anchor_pose
    from jaxtalk.models.toktalk.recipe import TokTalkWindows

    longest = max(c["frames"] for c in data.clips)
    recipe = TokTalkWindows(TokTalkConfig(style_frames=longest + 7), 100)
    for row in recipe.table(data, "train")[:6]:
        example = recipe.example(data, row)
        ref, r0 = int(row[2]), int(row[3])
        clip = data.record(ref, ("motion",))["motion"][r0:]
        n = len(clip)
        assert n < longest + 7
        np.testing.assert_array_equal(example["style_mask"], np.arange(longest + 7) < n)
        np.testing.assert_array_equal(example["style"][:n], clip)
        assert not example["style"][n:].any()
        # The anchor pose of the masked clip is the mean of its real frames only.
        anchor = anchor_pose({}, jnp.asarray(example["style"][None]), jnp.asarray(example["style_mask"][None]))
        np.testing.assert_allclose(np.asarray(anchor)[0], clip.mean(axis=0), rtol=1e-5, atol=1e-6)


def test_ats_whole_clip_examples_are_zero_padded_to_the_longest_clip_and_masked(data):
    from jaxtalk.models.freetalk.recipe import ATSWindows, fit_displacement_stats

    stats = fit_displacement_stats(data)
    longest = max(data.clips[i]["frames"] for i in data.split("train"))
    recipe = ATSWindows(0, stats, pad_to=longest)
    table = recipe.table(data, "train")
    assert sorted(int(r[0]) for r in table) == sorted(data.split("train")) and not table[:, 1].any()
    for row in table[:3]:
        example = recipe.example(data, row)
        rec = data.record(int(row[0]), ("landmarks", "speech"))
        n = rec["landmarks"].shape[0]
        assert example["displacements"].shape[0] == example["audio"].shape[0] == longest
        np.testing.assert_array_equal(example["mask"], np.arange(longest) < n)
        np.testing.assert_array_equal(example["audio_mask"], example["mask"])
        np.testing.assert_allclose(example["displacements"][:n], stats.normalize(rec["landmarks"]), rtol=1e-6)
        assert not example["displacements"][n:].any() and not example["audio"][n:].any()
    # A clip longer than pad_to is cut into pad_to-frame pieces.
    short = ATSWindows(0, stats, pad_to=40)
    i = data.split("train")[0]
    starts = [int(r[1]) for r in short.table(data, "train") if int(r[0]) == i]
    assert starts == list(range(0, data.clips[i]["frames"], 40))


def test_timar_batches_have_the_recipes_shapes(data):
    from jaxtalk.models.timar.config import TimarConfig
    from jaxtalk.models.timar.recipe import make_windows

    recipe = make_windows(TimarConfig(), data)
    loader = make_loader(data, recipe, "train", 2, shard=(0, 1))
    batch = next(loader)
    frames = recipe.num_turns * 25
    assert {k: v.shape for k, v in batch.items()} == {
        "user_speech": (2, frames, 80), "user_motion": (2, frames, 56),
        "agent_speech": (2, frames, 80), "agent_motion": (2, frames, 56)}
    assert all(np.isfinite(v).all() for v in batch.values())


def test_iter_windows_yields_every_window_once_in_table_order(data):
    recipe = Rows()
    got = [tuple(int(v) for v in e["row"]) for e in iter_windows(data, recipe, "val")]
    assert got == [tuple(int(v) for v in r) for r in recipe.table(data, "val")]


# ------------------------------------------------------------------------------------------ resume
def test_resume_from_saved_state_gives_the_same_next_batches_bitwise(data):
    recipe = Rows()
    per_epoch = len(recipe.table(data, "train")) // 16
    k, m = per_epoch - 2, 5  # the resumed stretch crosses an epoch boundary
    first = make_loader(data, recipe, "train", 16, seed=3, shard=(0, 1))
    _take(first, k)
    state = json.loads(json.dumps(first.get_state()))  # JSON round trip, as a checkpoint stores it
    expected = _take(first, m)
    resumed = make_loader(data, recipe, "train", 16, seed=3, shard=(0, 1))
    resumed.set_state(state)
    _assert_batches_equal(_take(resumed, m), expected)
    # A fresh loader without the state starts over (the resumed batches are not the first ones).
    assert _rows(_take(make_loader(data, recipe, "train", 16, seed=3, shard=(0, 1)), m)) != _rows(expected)


@pytest.mark.parametrize("change, field", [
    (dict(seed=4), "seed"),
    (dict(batch_size=8), "batch_size"),
    (dict(shard=(1, 2)), "shard"),
    (dict(split="val"), "split"),
])
def test_set_state_saved_for_another_loader_raises(data, change, field):
    recipe = Rows()
    args = dict(split="train", batch_size=4, seed=3, shard=(0, 1))
    state = make_loader(data, recipe, **{**args, "batch_size": 4}).get_state()
    other = make_loader(data, recipe, **{**args, **change})
    with pytest.raises(ValueError, match=f"saved with {field}="):
        other.set_state(state)


def test_set_state_from_another_recipe_raises(data):
    from jaxtalk.models.toktalk.config import TokTalkConfig
    from jaxtalk.models.toktalk.recipe import TokTalkWindows

    state = make_loader(data, Rows(), "train", 4, shard=(0, 1)).get_state()
    with pytest.raises(ValueError, match="saved with"):
        make_loader(data, TokTalkWindows(TokTalkConfig(), 100), "train", 4, shard=(0, 1)).set_state(state)


# ------------------------------------------------------------------------------------------ shards
@pytest.mark.parametrize("shuffle", [False, True])
def test_process_shards_are_disjoint_and_together_cover_one_epoch(data, shuffle):
    recipe = Rows()
    table = {tuple(int(v) for v in r) for r in recipe.table(data, "train")}
    parts = []
    for index in range(2):
        loader = make_loader(data, recipe, "train", 1, shuffle=shuffle, num_epochs=1, shard=(index, 2))
        rows = _rows(loader)  # the loader stops after one epoch
        assert len(rows) == loader.num_windows == len(set(rows))
        parts.append(set(rows))
    assert not parts[0] & parts[1]
    assert parts[0] | parts[1] == table
    assert abs(len(parts[0]) - len(parts[1])) <= 1


def test_two_processes_together_yield_the_single_process_global_batches(data):
    recipe = Rows()
    single = _take(make_loader(data, recipe, "train", 8, seed=5, shard=(0, 1)), 6)
    parts = [_take(make_loader(data, recipe, "train", 4, seed=5, shard=(i, 2)), 6) for i in range(2)]
    for k in range(6):
        joined = {key: np.concatenate([parts[0][k][key], parts[1][k][key]]) for key in single[k]}
        _assert_batches_equal([joined], [single[k]])


def test_unshuffled_loader_reads_the_table_in_order_and_stops_after_num_epochs(data):
    recipe = Rows()
    table = [tuple(int(v) for v in r) for r in recipe.table(data, "val")]
    assert _rows(make_loader(data, recipe, "val", 1, shuffle=False, num_epochs=2, shard=(0, 1))) == table + table
    assert _rows(make_loader(data, recipe, "val", 1, shuffle=False, num_epochs=1, shard=(1, 3))) == table[1::3]


# ------------------------------------------------------------------------------------------ shuffle
def test_shuffled_order_differs_between_epochs_and_repeats_for_the_same_seed(data):
    recipe = Rows()
    n = len(recipe.table(data, "train"))
    table = sorted(tuple(int(v) for v in r) for r in recipe.table(data, "train"))
    rows = _rows(_take(make_loader(data, recipe, "train", 1, seed=7, shard=(0, 1)), 2 * n))
    epoch0, epoch1 = rows[:n], rows[n:]
    assert sorted(epoch0) == sorted(epoch1) == table  # each epoch is a permutation of the windows
    assert epoch0 != epoch1
    assert epoch0 != table
    again = _rows(_take(make_loader(data, recipe, "train", 1, seed=7, shard=(0, 1)), 2 * n))
    assert again == rows
    other = _rows(_take(make_loader(data, recipe, "train", 1, seed=8, shard=(0, 1)), n))
    assert other != epoch0


# ------------------------------------------------------------------------------------------ errors
def test_make_loader_rejects_an_empty_split_or_a_batch_larger_than_the_shard(data):
    recipe = Rows(window=10_000)
    with pytest.raises(ValueError, match="no Rows window"):
        make_loader(data, recipe, "train", 1, shard=(0, 1))
    n = len(Rows().table(data, "val"))
    with pytest.raises(ValueError, match="fewer than batch_size"):
        make_loader(data, Rows(), "val", n // 2 + 1, shard=(0, 2))


def test_prepared_data_errors_name_the_problem(data, tmp_path):
    with pytest.raises(FileNotFoundError, match="not a prepared dataset"):
        PreparedData(tmp_path)
    manifest = dict(data.manifest)
    (tmp_path / "manifest.json").write_text(json.dumps({**manifest, "format": 99}))
    with pytest.raises(ValueError, match="format 99"):
        PreparedData(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="shards missing"):
        PreparedData(tmp_path)  # no shards/ next to this copy of the manifest
    with pytest.raises(KeyError, match="no clip 'nope'"):
        data.index("nope")
    with pytest.raises(ValueError, match="unknown split"):
        data.split("dev")


def test_prepared_data_survives_pickling_after_reading(data):
    before = data.record(0)
    copy = pickle.loads(pickle.dumps(data))
    after = copy.record(0)
    assert sorted(before) == sorted(after)
    for k in before:
        np.testing.assert_array_equal(before[k], after[k])
    assert data.split("train", motion=False) == copy.split("train", motion=False)
    stats = data.motion_stats()
    assert stats["mean"].shape == stats["std"].shape == (56,)


# ------------------------------------------------------------------------------------------ chunked records
class _CountingReader:
    """An ArrayRecord reader that logs the record indices of every read."""

    def __init__(self, reader, reads):
        self.reader, self.reads = reader, reads

    def read(self, indices):
        self.reads.append(list(indices))
        return self.reader.read(indices)


def _counting(data):
    """``data`` (a copy with its own readers) whose reads are logged in the returned list."""
    reads = []
    data.__dict__["_readers"] = {k: _CountingReader(v, reads) for k, v in data._readers.items()}
    return data, reads


def test_frames_reads_only_the_asked_arrays_in_the_chunks_it_overlaps_and_gives_the_whole_arrays_rows(data):
    from jaxtalk.data.prepare import record_positions

    whole = data.record(0)
    c = data.clips[0]
    size, n, chunks = data.manifest["chunk_frames"], c["frames"], c["chunks"]
    assert size == 25 and chunks == -(-n // size) and n > 2 * size
    assert sorted(whole) == sorted(c["head"] + c["framed"])
    copy, reads = _counting(pickle.loads(pickle.dumps(data)))
    keys = ("motion", "landmarks", "tokens")
    cases = {(0, size): [0], (size - 1, size + 1): [0, 1], (13, 63): [0, 1, 2],
             (n - 5, n + 40): list(range((n - 5) // size, chunks)), (n + 3, n + 9): [chunks - 1],
             (0, n): list(range(chunks)), (30, 30): [1]}
    for (start, stop), expected in cases.items():
        reads.clear()
        got = copy.record(0, keys, frames=(start, stop))
        assert reads == [[index for _, _, index in record_positions(c, keys, expected)]], (start, stop)
        assert len(reads[0]) == 1 + 2 * len(expected)
        for k in ("motion", "landmarks"):
            assert got[k].dtype == whole[k].dtype and got[k].tobytes() == whole[k][start:stop].tobytes(), (start, stop, k)
            assert got[k].shape == whole[k][start:stop].shape and got[k].flags.writeable
        np.testing.assert_array_equal(got["tokens"], whole["tokens"])
    reads.clear()
    assert sorted(copy.record(0, ("speech", "nope"), frames=(30, 45))) == ["speech"]
    assert reads == [[index for _, _, index in record_positions(c, ["speech"], [1])]]
    with pytest.raises(ValueError, match="0 <= start <= stop"):
        copy.record(0, ("motion",), frames=(10, 5))


def test_cached_reads_equal_uncached_bitwise_and_repeat_reads_touch_no_record(data):
    cached, reads = _counting(data.cached())
    for frames in [(13, 63), (13, 63), (0, 90), None]:
        got = cached.record(0, ("motion", "speech", "tokens"), frames=frames)
        want = data.record(0, ("motion", "speech", "tokens"), frames=frames)
        assert sorted(got) == sorted(want)
        for k in want:
            assert got[k].tobytes() == want[k].tobytes() and got[k].shape == want[k].shape, (frames, k)
    reads.clear()
    got = cached.record(0, ("motion", "speech", "tokens"), frames=(13, 63))
    assert reads == []
    with pytest.raises(ValueError, match="read-only"):
        got["tokens"][0, 0] = 1.0  # a cached array: writing into it would change later windows
    cached.record(0, ("oracle",), frames=(13, 63))  # an array not read yet: its three chunks
    assert len(reads) == 1 and len(reads[0]) == 3


# ------------------------------------------------------------------------------------------ threads
@dataclasses.dataclass(frozen=True, eq=False)
class CountingRows(Rows):
    calls: list = dataclasses.field(default_factory=list)

    def example(self, data, row):
        self.calls.append(1)
        return super().example(data, row)


def test_loader_reads_a_bounded_number_of_batches_ahead(data):
    recipe = CountingRows()
    loader = make_loader(data, recipe, "train", 2, shard=(0, 1))
    next(loader)
    time.sleep(1.0)
    ahead = loader_mod.PREFETCH_BATCHES + loader_mod.READ_THREADS + 1
    assert len(recipe.calls) <= ahead * 2, len(recipe.calls)


def test_records_decode_in_threads_while_another_thread_parses_python(data):
    # NumPy's .npy header parser is ast.literal_eval; on CPython < 3.11.8 concurrent AST conversions
    # corrupt each other ("SystemError: AST constructor recursion depth mismatch"), as the loader's
    # threads decoding records did against the main thread importing a module.
    errors, stop = [], threading.Event()

    def decode():
        while not stop.is_set():
            try:
                data.record(0)
            except Exception as err:  # noqa: BLE001
                errors.append(err)

    threads = [threading.Thread(target=decode) for _ in range(3)]
    for t in threads:
        t.start()
    source = inspect.getsource(loader_mod)
    try:
        for _ in range(40):
            ast.parse(source)
    finally:
        stop.set()
        for t in threads:
            t.join()
    assert errors == []
