"""Every model's training recipe end to end through ``jaxtalk train --data`` (prepared SynthTalk tiny),
and the data paths agreeing: SynthTalk prepared from memory and from its generic-layout export train
to the same parameters with the same seed.

Models are shrunk with ``--set`` so each compiles in seconds; two steps each. TokTalk, TIMAR and ATS are
the session's runs (``trained_toktalk`` and the others in conftest, made by the same command); STM trains
here.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from helpers import TINY_TRAIN_ARGS, cli_ok as _ok


# The smallest graphs of each model (compile time dominates two-step runs).
SMALL = {**TINY_TRAIN_ARGS, "stm": ["--set", "val_clips=1"]}


@pytest.fixture(scope="module")
def cache(prepared_tiny):
    return str(prepared_tiny.root.parent)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["toktalk", "timar", "ats", "stm"])
def test_train_recipe_runs_end_to_end_and_writes_a_loadable_run(model, cache, tmp_path, request):
    from jaxtalk.runs import RunRecord, load_run

    if model == "stm":  # the session has no trained STM (training renders meshes): this test trains it
        out = tmp_path / model
        output = _ok(["train", model, "--data", "synthtalk:tiny", "--cache-dir", cache, "--steps", "2", "--set",
                      "batch_size=2", *SMALL[model], "--no-progress", "--out", str(out)])
    else:  # the session's run, trained with the same command (conftest)
        trained = request.getfixturevalue(f"trained_{model}")
        out, output = trained.dir, trained.output
    assert f"{model}: step 0 -> 2" in output and "validation loss" in output
    record = RunRecord.load(out)
    assert record.model == model and record.train["batch_size"] == 2 and record.data["spec"] == "synthtalk:tiny"
    features = json.loads((out / "features.json").read_text())
    assert features["audio"] == "logmel"
    loaded = load_run(out)
    assert loaded.step == 2
    assert all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree.leaves(loaded.params))
    want_extra = {"toktalk": {"window_frames"}, "timar": {"normalizer", "num_turns", "still"},
                  "ats": {"window", "stats"}, "stm": {"meshes", "resolution", "window"}}[model]
    assert want_extra <= set(record.extra)
    if model == "toktalk":
        assert (out / "tokenizer.npz").is_file() and (out / "style.npy").is_file()


@pytest.mark.slow
def test_memory_and_generic_export_paths_train_to_identical_parameters(cache, synthtalk_tiny, trained_toktalk,
                                                                       tmp_path):
    from jaxtalk.runs import load_run
    from jaxtalk.data.sources import export_generic

    folder = export_generic(synthtalk_tiny, tmp_path / "generic")
    _ok(["prepare", str(folder), "--out", str(tmp_path / "prepared"), "--no-progress"])
    # The in-memory path is the session's run (trained with this command on synthtalk:tiny).
    _ok(["train", "toktalk", "--data", str(tmp_path / "prepared"), "--cache-dir", cache, "--steps", "2", "--set",
         "batch_size=2", *SMALL["toktalk"], "--no-progress", "--out", str(tmp_path / "export")])
    runs = {"memory": load_run(trained_toktalk.dir).params, "export": load_run(tmp_path / "export").params}
    for a, b in zip(jax.tree.leaves(runs["memory"]), jax.tree.leaves(runs["export"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_dualtalk_export_reads_back_the_corpus_motion(synthtalk_tiny, tmp_path):
    from jaxtalk.data.sources import export_dualtalk, open_source

    source = open_source(export_dualtalk(synthtalk_tiny, tmp_path / "dualtalk"))
    assert source.layout == "dualtalk"
    pairs = synthtalk_tiny.conversations()
    assert len(source.entries) == 2 * len(pairs)
    a, b = pairs[0]
    first = [e for e in source.entries if e.name.startswith(f"clip{a:05d}_conv_speaker")]
    assert [e.partner for e in first] == [f"clip{a:05d}_conv_speaker2", f"clip{a:05d}_conv_speaker1"]
    for entry, clip in zip(first, (a, b)):
        raw = entry.read()
        np.testing.assert_array_equal(raw.params, synthtalk_tiny.motion(clip))
        np.testing.assert_array_equal(raw.audio, synthtalk_tiny.audio(clip))
        assert entry.split == synthtalk_tiny.clips[clip].split
