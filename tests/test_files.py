"""jaxtalk.files: the one atomic writer and the rule for what a command may replace."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from jaxtalk.files import (
    Output,
    OutputError,
    atomic_output,
    atomic_save_npy,
    atomic_savez,
    atomic_write_text,
    check_output_path,
    claim_folder,
    claim_outputs,
)


def test_atomic_output_leaves_the_old_file_and_no_temporary_when_the_write_fails(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_output(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed half way")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_atomic_writers_create_missing_folders_and_keep_the_exact_name(tmp_path):
    atomic_savez(tmp_path / "a" / "x.bin", v=np.arange(3))
    atomic_save_npy(tmp_path / "b" / "y.data", np.ones(2))
    assert np.array_equal(np.load(tmp_path / "a" / "x.bin")["v"], np.arange(3))
    assert np.array_equal(np.load(tmp_path / "b" / "y.data"), np.ones(2))
    assert not list(tmp_path.rglob("*.npz")) and not list(tmp_path.rglob("*.npy"))


def test_concurrent_writers_of_one_file_leave_one_whole_version(tmp_path):
    target = tmp_path / "t.txt"
    texts = [str(i) * 200_000 for i in range(8)]
    threads = [threading.Thread(target=atomic_write_text, args=(target, t)) for t in texts]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert target.read_text() in texts  # whole, never interleaved
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.txt"]


def test_check_output_path_refuses_a_folder_a_path_under_a_file_and_a_wrong_suffix(tmp_path):
    (tmp_path / "d.npz").mkdir()
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match="is a folder"):
        check_output_path(tmp_path / "d.npz", (".npz",))
    with pytest.raises(OutputError, match="is a file, not a folder"):
        check_output_path(tmp_path / "f" / "deeper" / "x.npz", (".npz",))
    with pytest.raises(OutputError, match=r"\.npz"):
        check_output_path(tmp_path / "x.npy", (".npz",))
    assert check_output_path(tmp_path / "new" / "x.npz", (".npz",)) == tmp_path / "new" / "x.npz"
    assert not (tmp_path / "new").exists()  # checking creates nothing


def test_claim_outputs_never_allows_an_input_even_with_overwrite_or_a_named_path(tmp_path):
    src = tmp_path / "talk.wav"
    src.write_bytes(b"user")
    for out in (Output(src, named=True), Output(src)):
        with pytest.raises(OutputError, match="is an input"):
            claim_outputs([out], inputs=[src], overwrite=True)
    # The same file under another spelling of its path.
    os.symlink(src, tmp_path / "link.wav")
    with pytest.raises(OutputError, match="is an input"):
        claim_outputs([Output(tmp_path / "sub" / ".." / "talk.wav", named=True)], inputs=[tmp_path / "link.wav"])


def test_claim_outputs_lets_named_paths_replace_and_picked_names_only_with_overwrite(tmp_path):
    existing = tmp_path / "a.npz"
    existing.write_bytes(b"user")
    assert claim_outputs([Output(existing, named=True)]) == [existing]
    with pytest.raises(OutputError, match="pass --overwrite"):
        claim_outputs([Output(existing)])
    assert claim_outputs([Output(existing)], overwrite=True) == [existing]
    assert claim_outputs([Output(tmp_path / "new.npz")]) == [tmp_path / "new.npz"]
    with pytest.raises(OutputError, match="two outputs"):
        claim_outputs([Output(tmp_path / "n.glb", named=True), Output(tmp_path / "n.glb")])
    assert existing.read_bytes() == b"user"


def test_claim_outputs_refuses_any_path_inside_an_input_folder(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoint").mkdir(parents=True)
    (run / "checkpoint" / "history.jsonl").write_text("{}")
    for out in (run / "checkpoint" / "history.jsonl", run / "new.json"):
        with pytest.raises(OutputError, match="is an input"):
            claim_outputs([Output(out, named=True)], inputs=[run], overwrite=True)
    assert claim_outputs([Output(tmp_path / "r.json", named=True)], inputs=[run]) == [tmp_path / "r.json"]


def test_claim_folder_replaces_only_its_own_previous_output_with_overwrite(tmp_path, monkeypatch):
    out = tmp_path / "ckpts"
    assert claim_folder(out, ours=("run.json",), previous_output=False) == out  # missing: fine
    out.mkdir()
    assert claim_folder(out, ours=("run.json",), previous_output=False) == out  # empty: fine
    (out / "run.json").write_text("{}")
    with pytest.raises(OutputError, match="pass --overwrite"):
        claim_folder(out, ours=("run.json",), previous_output=True)
    assert claim_folder(out, ours=("run.json",), previous_output=True, overwrite=True) == out
    # A user's file beside the command's own, or a folder that is no previous output: never replaced.
    with pytest.raises(OutputError, match="did not write"):
        claim_folder(out, ours=("run.json",), previous_output=False, overwrite=True)
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="did not write.*notes.txt"):
        claim_folder(out, ours=("run.json",), previous_output=True, overwrite=True)


def test_claim_folder_never_replaces_a_folder_holding_an_input_or_the_working_folder(tmp_path, monkeypatch):
    out = tmp_path / "ckpts"
    (out / "w2v").mkdir(parents=True)
    ckpt = out / "TIMAR.pth"
    ckpt.write_bytes(b"weights")
    for src in (ckpt, out / "w2v"):
        with pytest.raises(OutputError, match="an input of this command"):
            claim_folder(out, [src], ours=("TIMAR.pth", "w2v"), previous_output=True, overwrite=True)
    monkeypatch.chdir(out / "w2v")
    for folder in (out, out / "w2v", ".", ".."):
        with pytest.raises(OutputError, match="current folder"):
            claim_folder(folder, ours=(), previous_output=True, overwrite=True)
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a file"):
        claim_folder(tmp_path / "file", ours=(), previous_output=False)


_HOLD = """
import sys, time
from jaxtalk.files import folder_lock
with folder_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(60)
"""


def _holder(folder):
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_folder_lock_refuses_a_second_process_naming_it_and_is_reentrant_in_one(tmp_path):
    from jaxtalk.files import LOCK_FILE, FolderInUseError, folder_lock

    run = tmp_path / "run"
    proc = _holder(run)
    try:
        with pytest.raises(FolderInUseError, match=f"in use by process {proc.pid} "):
            with folder_lock(run):
                pass
    finally:
        proc.kill()
        proc.communicate()
    # The killed holder's lock file is left behind, and is taken over.
    assert (run / LOCK_FILE).is_file()
    with folder_lock(run), folder_lock(tmp_path / "run" / ".." / "run"):
        assert str(os.getpid()) in (run / LOCK_FILE).read_text()
    assert not (run / LOCK_FILE).exists()
    # A folder the lock created is removed again when nothing else was written into it.
    with folder_lock(tmp_path / "new"):
        assert (tmp_path / "new").is_dir()
    assert not (tmp_path / "new").exists()
