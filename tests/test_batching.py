"""Deterministic batching: seeded order, exact resume, epoch coverage, buckets and padding masks."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from jaxtalk.data.batching import BatchIterator, length_buckets, window_starts


def _arrays(n=23):
    rng = np.random.default_rng(0)
    return {"x": rng.normal(size=(n, 3)).astype(np.float32), "id": np.arange(n)}


def _sequences(lengths=(3, 7, 5, 12, 9, 4, 11, 2, 8, 6, 10, 1, 12, 5)):
    rng = np.random.default_rng(1)
    return [
        {"x": rng.normal(size=(t, 2)).astype(np.float32), "y": rng.normal(size=(t,)).astype(np.float32), "id": np.asarray(i)}
        for i, t in enumerate(lengths)
    ]


def _take(it, n):
    return [next(it) for _ in range(n)]


def _same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.keys() == y.keys()
        for k in x:
            np.testing.assert_array_equal(x[k], y[k])


def test_same_seed_same_batches_other_seed_other_order():
    a = _take(BatchIterator(_arrays(), 4, seed=7), 12)
    b = _take(BatchIterator(_arrays(), 4, seed=7), 12)
    c = _take(BatchIterator(_arrays(), 4, seed=8), 12)
    _same(a, b)
    assert any(not np.array_equal(x["id"], y["id"]) for x, y in zip(a, c))
    for batch in a:  # rows stay aligned across keys
        np.testing.assert_array_equal(batch["x"], _arrays()["x"][batch["id"]])


def test_each_epoch_is_a_fresh_permutation_with_every_example_once():
    it = BatchIterator(_arrays(23), 4, seed=3, drop_remainder=False)
    assert it.batches_per_epoch == 6
    epochs = []
    for _ in range(3):
        ids = np.concatenate([b["id"][b["valid"]] for b in _take(it, 6)])
        assert sorted(ids.tolist()) == list(range(23))
        epochs.append(ids)
    assert not np.array_equal(epochs[0], epochs[1])
    # The single fill batch: 23 = 5 * 4 + 3, one padding row, zero-filled.
    fills = [b for b in _take(BatchIterator(_arrays(23), 4, seed=3, drop_remainder=False), 6) if not b["valid"].all()]
    assert len(fills) == 1 and fills[0]["valid"].sum() == 3
    np.testing.assert_array_equal(fills[0]["x"][~fills[0]["valid"]], 0.0)


def test_drop_remainder_drops_at_most_batch_size_minus_one_distinct_examples():
    it = BatchIterator(_arrays(23), 4, seed=0)
    assert it.batches_per_epoch == 5
    ids = np.concatenate([b["id"] for b in _take(it, 5)])
    assert len(set(ids.tolist())) == 20 and "valid" not in next(it)


def test_shuffle_false_keeps_dataset_order():
    it = BatchIterator(_arrays(8), 4, shuffle=False)
    np.testing.assert_array_equal(np.concatenate([b["id"] for b in _take(it, 4)]), [0, 1, 2, 3, 4, 5, 6, 7] * 2)


@pytest.mark.parametrize("stop", [0, 3, 5, 9])  # inside the first epoch, at its end, in later epochs
def test_resume_from_saved_position_continues_exactly(stop):
    data = _sequences()
    kw = dict(seed=11, buckets=(4, 8, 12), sequence_keys=("x", "y"))
    reference = _take(BatchIterator(data, 2, **kw), stop + 8)
    first = BatchIterator(data, 2, **kw)
    _take(first, stop)
    saved = json.loads(json.dumps(first.get_state()))  # must survive a JSON round trip
    resumed = BatchIterator(data, 2, **kw)
    resumed.set_state(saved)
    _same(_take(resumed, 8), reference[stop:])


def test_set_state_rejects_other_configuration():
    it = BatchIterator(_arrays(), 4, seed=1)
    state = it.get_state()
    with pytest.raises(ValueError, match="seed=1"):
        BatchIterator(_arrays(), 4, seed=2).set_state(state)
    with pytest.raises(ValueError, match="batch_size=4"):
        BatchIterator(_arrays(), 2, seed=1).set_state(state)
    with pytest.raises(ValueError, match="missing 'index'"):
        it.set_state({k: v for k, v in state.items() if k != "index"})
    with pytest.raises(ValueError, match="invalid position"):
        it.set_state({**state, "index": 99})


def test_buckets_pad_to_bucket_lengths_with_correct_mask():
    data = _sequences()
    lengths = np.array([len(ex["y"]) for ex in data])
    it = BatchIterator(data, 2, seed=5, buckets=(4, 8, 12), sequence_keys=("x", "y"), drop_remainder=False, pad_value=-9.0)
    seen = Counter()
    for batch in _take(it, it.batches_per_epoch):
        t = batch["x"].shape[1]
        assert t in (4, 8, 12) and batch["y"].shape == (2, t) and batch["mask"].shape == (2, t)
        assert batch["mask"].dtype == bool
        for r in range(2):
            if not batch["valid"][r]:
                assert not batch["mask"][r].any()
                continue
            i = int(batch["id"][r])
            seen[i] += 1
            n = lengths[i]
            # The smallest bucket that fits: no bucket below t would hold this example.
            assert n <= t and (t == 4 or n > {8: 4, 12: 8}[t])
            np.testing.assert_array_equal(batch["mask"][r], np.arange(t) < n)
            np.testing.assert_array_equal(batch["x"][r, :n], data[i]["x"])
            np.testing.assert_array_equal(batch["x"][r, n:], -9.0)
            np.testing.assert_array_equal(batch["y"][r, n:], -9.0)
    assert seen == Counter(range(len(data)))
    assert it.variable_axes == (1,)


def test_default_single_bucket_is_the_longest_example():
    it = BatchIterator(_sequences((3, 5, 2, 4)), 2, seed=0, sequence_keys=("x", "y"))
    batches = _take(it, 2)
    assert all(b["x"].shape == (2, 5, 2) for b in batches) and it.variable_axes == ()
    assert sorted(np.concatenate([b["mask"].sum(1) for b in batches]).tolist()) == [2, 3, 4, 5]


def test_num_epochs_stops_iteration():
    it = BatchIterator(_arrays(8), 4, seed=0, num_epochs=2)
    assert len(list(it)) == 4


def test_length_buckets_quantiles_rounded():
    assert length_buckets([1, 2, 3, 4, 5, 6, 7, 8], 2) == (4, 8)
    assert length_buckets([1, 2, 3, 4, 5, 6, 7, 8], 4, multiple=4) == (4, 8)
    assert length_buckets([5, 5, 5], 3) == (5,)
    with pytest.raises(ValueError, match="non-empty"):
        length_buckets([], 2)


@pytest.mark.parametrize(
    "make, msg",
    [
        (lambda: BatchIterator({}, 2), "empty"),
        (lambda: BatchIterator({"x": np.zeros((0, 2))}, 2), "0 examples"),
        (lambda: BatchIterator({"x": np.zeros((4, 2)), "y": np.zeros(5)}, 2), "'y' has 5, expected 4"),
        (lambda: BatchIterator(_arrays(3), 4), "no batch per epoch"),
        (lambda: BatchIterator(_arrays(), 0), "batch_size"),
        (lambda: BatchIterator([], 2), "empty"),
        (lambda: BatchIterator(_sequences((3, 9)), 1, buckets=(4, 8), sequence_keys=("x", "y")), "example 1 has length 9"),
        (lambda: BatchIterator([{"x": np.zeros((3, 2)), "y": np.zeros(4)}], 1), "disagree on length"),
        (lambda: BatchIterator([{"x": np.zeros((3, 2))}, {"z": np.zeros((3, 2))}], 1), "example 1 has keys"),
        (lambda: BatchIterator([{"x": np.zeros((3, 2)), "mask": np.zeros(3)}], 1), "'mask' clashes"),
        (lambda: BatchIterator(_sequences(), 1, sequence_keys=("q",)), "sequence key 'q'"),
    ],
)
def test_bad_datasets_raise_clear_errors(make, msg):
    with pytest.raises(ValueError, match=msg):
        make()


def test_window_starts_cover_the_sequence_with_the_last_window_flush_with_the_end():
    assert window_starts(10, 4, 3) == [0, 3, 6]
    assert window_starts(11, 4, 3) == [0, 3, 6, 7]
    assert window_starts(11, 4, 3, align=2) == [0, 4, 8]  # hop and the last start rounded up to the period
    assert window_starts(3, 4, 1) == [0]  # a short clip: one window, padded by the caller
    assert window_starts(3, 4, 1, pad_short=False) == []
    for bad in ((10, 0, 1), (10, 4, 0), (10, 4, 1, 0)):
        with pytest.raises(ValueError, match="must be >= 1"):
            window_starts(*bad[:3], align=bad[3] if len(bad) > 3 else 1)
