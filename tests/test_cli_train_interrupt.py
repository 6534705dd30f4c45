"""``jaxtalk train`` interrupted and contended: Ctrl-C ends it with one line and exit 130, leaving a
checkpoint to resume; a second training into a run folder in use is refused before it writes."""

from __future__ import annotations

import hashlib
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers import TINY_TRAIN_ARGS, cli_error


def _hashes(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _train(out: Path, cache: Path, steps: int) -> subprocess.Popen:
    args = [sys.executable, "-m", "jaxtalk", "train", "toktalk", "--data", "synthtalk:tiny", "--cache-dir", str(cache),
            "--steps", str(steps), "--set", "batch_size=2", *TINY_TRAIN_ARGS["toktalk"], "--no-progress",
            "--out", str(out)]
    # `train` installs its own SIGINT handler (before it takes the lock the tests wait for), so the
    # child hears Ctrl-C even where it was started with SIGINT ignored.
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, limit_s: float = 300.0) -> None:
    end = time.monotonic() + limit_s
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < end, f"{path} never appeared"
        time.sleep(0.2)


def _error_lines(stderr: str) -> list[str]:
    assert "Traceback" not in stderr, stderr
    return [line for line in stderr.splitlines() if line.startswith("error:")]


@pytest.mark.slow
def test_ctrl_c_during_training_checkpoints_the_step_and_exits_130_with_one_line(tmp_path, prepared_tiny):
    out = tmp_path / "run"
    proc = _train(out, prepared_tiny.root.parent, steps=100_000)
    _wait_for(out / "metrics.jsonl", proc)  # the loop is running: steps are being logged
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130, stderr
    (line,) = _error_lines(stderr)
    step = int(line.split("interrupted at step ")[1].split(";")[0])
    assert step >= 1 and (out / "checkpoint" / str(step)).is_dir()
    assert (out / "run.json").is_file() and not (out / ".jaxtalk.lock").exists()


@pytest.mark.slow
def test_ctrl_c_before_the_loop_runs_exits_130_with_one_line_and_the_folder_stays_trainable(tmp_path, prepared_tiny):
    out = tmp_path / "run"
    proc = _train(out, prepared_tiny.root.parent, steps=3)
    # The lock is taken before the data is opened and the step compiled: the loop has not started.
    _wait_for(out / ".jaxtalk.lock", proc)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130, stderr
    (line,) = _error_lines(stderr)
    assert "interrupted" in line
    proc = _train(out, prepared_tiny.root.parent, steps=2)  # the lock left behind is taken over
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    assert "step 0 -> 2" in stdout


def test_a_second_training_into_a_run_in_use_is_refused_naming_the_process(trained_toktalk, tmp_path):
    run = tmp_path / "run"  # a copy: the session's run is shared by other tests
    shutil.copytree(trained_toktalk.dir, run)
    before = _hashes(run)
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom jaxtalk.files import folder_lock\n"
                               "with folder_lock(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(60)",
                               str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        cli_error(["train", "toktalk", "--out", run, "--steps", "4", "--no-progress"], "in use by process",
                  str(holder.pid))
    finally:
        holder.kill()
        holder.communicate()
    assert {k: v for k, v in _hashes(run).items() if k != ".jaxtalk.lock"} == before
