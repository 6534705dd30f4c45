"""Orbax checkpoints: round trip, keep-N, atomic write (tmp dir + rename), metadata JSON, and clear
errors for missing, empty and corrupt directories."""

from __future__ import annotations

import gc
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from orbax.checkpoint._src.path import async_path

from jaxtalk.data.batching import BatchIterator
from jaxtalk.train import (
    CheckpointMismatchError,
    Checkpointer,
    LoopSettings,
    OptimConfig,
    create_train_state,
    latest_checkpoint_step,
    make_optimizer,
    make_train_step,
    restore_checkpoint,
    save_checkpoint,
    train,
    trainable_mask,
)

CFG = OptimConfig(lr=0.1, weight_decay=0.01, warmup_steps=1, total_steps=6, ema_decay=0.5)


def _loss(p, batch, key):
    err = batch["x"] @ p["w"] + p["b"][None, :] - batch["y"]
    return jnp.mean(err**2) + 0.01 * jax.random.normal(key), {}


def _data():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(16, 3)).astype(np.float32)
    return {"x": x, "y": (x @ rng.normal(size=(3, 2))).astype(np.float32)}


def _params(scale=1.0):
    return {"w": jnp.full((3, 2), 0.1 * scale), "b": jnp.array([-0.0, 0.2])}


@pytest.fixture(scope="module")
def run():
    """States after 0..4 steps (one compile for the module; donation off to keep them all)."""
    key = jax.random.key(0)
    mask = trainable_mask(_params(), lambda path, leaf: path == "w")  # exercise the masked opt state
    tx = make_optimizer(CFG, mask)
    states = [create_train_state(_params(), tx, key, ema=True)]
    step = make_train_step(_loss, tx, CFG, mask=mask, donate=False)
    it = BatchIterator(_data(), 4, seed=0)
    positions = [it.get_state()]
    for _ in range(4):
        states.append(step(states[-1], next(it))[0])
        positions.append(it.get_state())
    return {"states": states, "positions": positions, "tx": tx, "key": key}


def _assert_bitwise(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()


def test_save_restore_round_trip_is_bitwise(tmp_path, run):
    state, tx, key = run["states"][3], run["tx"], run["key"]
    save_checkpoint(tmp_path / "c", state, data_state=run["positions"][3], metadata={"model": "toy"})
    template = create_train_state(_params(scale=7.0), tx, jax.random.key(99), ema=True)
    restored, data_state, meta = restore_checkpoint(tmp_path / "c", template)
    _assert_bitwise(restored.params, state.params)
    _assert_bitwise(restored.opt_state, state.opt_state)
    _assert_bitwise(restored.ema_params, state.ema_params)
    assert int(restored.step) == 3 and data_state == run["positions"][3] and meta == {"step": 3, "model": "toy"}
    assert jax.random.key_impl(restored.rng) == jax.random.key_impl(key)
    np.testing.assert_array_equal(jax.random.key_data(restored.rng), jax.random.key_data(key))


def test_restore_saved_reads_params_without_a_template_and_names_missing_steps(tmp_path, run):
    for i in (2, 3):
        save_checkpoint(tmp_path / "c", run["states"][i], data_state=run["positions"][i])
    with Checkpointer(tmp_path / "c", read_only=True) as ckpt:
        raw, step = ckpt.restore_saved()
        assert step == 3 and int(raw["step"]) == 3
        _assert_bitwise(raw["params"], run["states"][3].params)
        _assert_bitwise(raw["ema_params"], run["states"][3].ema_params)
        raw2, step2 = ckpt.restore_saved(2)
        assert step2 == 2
        _assert_bitwise(raw2["params"], run["states"][2].params)
        with pytest.raises(FileNotFoundError, match="no checkpoint for step 5"):
            ckpt.restore_saved(5)


def test_writes_go_to_a_tmp_dir_renamed_when_complete(tmp_path, run, monkeypatch):
    renames = []
    original = async_path.rename

    async def spy(src, dst):
        renames.append((src.name, dst.name, dst.exists()))
        return await original(src, dst)

    monkeypatch.setattr(async_path, "rename", spy)
    state = run["states"][2]
    save_checkpoint(tmp_path / "c", state)
    # Items are finalised inside the step's tmp dir, then the step dir itself is renamed, last.
    assert [dst for _, dst, _ in renames] == ["data", "meta", "state", "2"]
    src, dst, dst_existed = renames[-1]
    assert src.startswith("2.orbax-checkpoint-tmp") and not dst_existed

    # A save killed before its rename leaves only a tmp dir: it is not a checkpoint.
    async def killed(src, dst):
        raise OSError("simulated kill before rename")

    monkeypatch.setattr(async_path, "rename", killed)
    later = run["states"][4]
    with pytest.raises(Exception, match="simulated kill"):
        save_checkpoint(tmp_path / "c", later)
    names = sorted(p.name for p in (tmp_path / "c").iterdir())
    assert names[0] == "2" and names[1].startswith("4.orbax-checkpoint-tmp")
    assert latest_checkpoint_step(tmp_path / "c") == 2
    restored, _, _ = restore_checkpoint(tmp_path / "c", state)
    assert int(restored.step) == 2
    # Opening the directory for writing (as train does) removes the leftover.
    monkeypatch.setattr(async_path, "rename", original)
    Checkpointer(tmp_path / "c").close()
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["2"]


def test_train_keeps_last_n_and_writes_metadata_json(tmp_path, key):
    ckpt = tmp_path / "run"
    train(_loss, _params(), BatchIterator(_data(), 4, seed=0), CFG, key=key, ckpt_dir=ckpt, metadata={"model": "toy-linear"},
          settings=LoopSettings(save_every=2, keep_checkpoints=2, progress=False))
    assert sorted(p.name for p in ckpt.iterdir()) == ["4", "6"]  # 2 dropped: keep the last 2
    meta = json.loads((ckpt / "6" / "meta" / "metadata").read_text())
    assert meta["model"] == "toy-linear" and meta["step"] == 6
    assert meta["config"] == CFG.to_dict()
    assert meta["batch_spec"]["names"] == ["['x']", "['y']"] and meta["batch_spec"]["shapes"] == [[4, 3], [4, 2]]
    data_state = json.loads((ckpt / "6" / "data" / "metadata").read_text())
    assert (data_state["epoch"], data_state["index"]) == (1, 2)  # 6 batches at 4 per epoch


def test_resume_checks_batches_against_the_saved_spec(tmp_path, key):
    ckpt = tmp_path / "run"
    train(_loss, _params(), BatchIterator(_data(), 4, seed=0), CFG, key=key, ckpt_dir=ckpt,
          settings=LoopSettings(max_steps=2, progress=False))
    wider = iter([{"x": np.zeros((8, 3), np.float32), "y": np.zeros((8, 2), np.float32)}])
    with (
        pytest.raises(ValueError, match=r"\['x'\] at step 3 has shape \(8, 3\), but the model was set up for shape \(4, 3\)"),
        pytest.warns(UserWarning, match="no get_state/set_state"),
    ):
        train(_loss, _params(), wider, CFG, key=key, ckpt_dir=ckpt, settings=LoopSettings(progress=False))
    with pytest.raises(ValueError, match="already holds checkpoints"):
        train(_loss, _params(), BatchIterator(_data(), 4, seed=0), CFG, key=key, ckpt_dir=ckpt,
              settings=LoopSettings(resume=False, progress=False))
    # A position saved for another batch size is refused by the iterator itself.
    with pytest.raises(ValueError, match="saved with batch_size=4, this iterator has 8"):
        train(_loss, _params(), BatchIterator(_data(), 8, seed=0), CFG, key=key, ckpt_dir=ckpt,
              settings=LoopSettings(progress=False))


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # orbax's failed reader tasks
def test_missing_empty_and_corrupt_directories_raise_naming_the_path(tmp_path, run):
    state, key = run["states"][1], run["key"]
    with pytest.raises(FileNotFoundError, match=f"{tmp_path / 'nope'} does not exist"):
        restore_checkpoint(tmp_path / "nope", state)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=f"no complete checkpoint in {tmp_path / 'empty'}"):
        restore_checkpoint(tmp_path / "empty", state)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is not a directory"):
        restore_checkpoint(tmp_path / "file", state)

    save_checkpoint(tmp_path / "c", state)
    with pytest.raises(FileNotFoundError, match="no checkpoint for step 5"):
        restore_checkpoint(tmp_path / "c", state, step=5)
    # Wrong template (other parameter shapes) is reported, naming the step directory.
    other = create_train_state({"w": jnp.ones((2, 2)), "b": jnp.zeros(2)}, make_optimizer(CFG), key, ema=True)
    with pytest.raises(CheckpointMismatchError, match=f"checkpoint {tmp_path / 'c' / '1'} is corrupt or does not match"):
        restore_checkpoint(tmp_path / "c", other)
    # Corrupt the array store: the error names the checkpoint, both directly and through train().
    for p in (tmp_path / "c" / "1" / "state").rglob("*"):
        if p.is_file() and "manifest" in p.name:
            p.write_bytes(b"garbage")
    shutil.rmtree(tmp_path / "c" / "1" / "state" / "d", ignore_errors=True)
    with pytest.raises(ValueError, match=f"checkpoint {tmp_path / 'c' / '1'} is corrupt"):
        restore_checkpoint(tmp_path / "c", state)
    with pytest.raises(ValueError, match=f"checkpoint {tmp_path / 'c' / '1'} is corrupt"):
        train(_loss, _params(), BatchIterator(_data(), 4, seed=0), CFG, key=key, ckpt_dir=tmp_path / "c",
              settings=LoopSettings(progress=False))
    gc.collect()  # let orbax's abandoned reader tasks report here, under this test's filter
