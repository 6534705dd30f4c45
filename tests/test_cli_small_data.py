"""Small datasets train: ``jaxtalk train`` with default settings on a DualTalk-layout folder with fewer
training windows than the default batch trains with the largest batch the split allows, says so in one
line naming ``--set batch_size=N``, records that batch in ``run.json`` and resumes with it.

The folder is SynthTalk tiny exported in DualTalk's release layout (one conversation per split) with
the training conversation's second speaker left without motion, as in DualTalk's own demo clips; a
second variant prepares the real demo clips when ``../shared/data/dualtalk_demo`` is there.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from helpers import cli_ok as _ok


DEMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "dualtalk_demo"
WARNING = "warning: the training split has {n} windows, fewer than batch_size=16: training with the largest " \
          "batch it allows (--set batch_size={n})"


def _train(model: str, data: Path, out: Path, steps: int) -> tuple[str, dict]:
    output = _ok(["train", model, "--data", str(data), "--steps", str(steps), "--no-progress", "--out", str(out)])
    return output, json.loads((out / "run.json").read_text())



@pytest.fixture(scope="module")
def small_dualtalk(synthtalk_tiny, tmp_path_factory):
    from jaxtalk.data.sources import export_dualtalk

    root = tmp_path_factory.mktemp("small_dualtalk")
    raw = export_dualtalk(synthtalk_tiny, root / "raw")
    [listener] = (raw / "train").glob("*_speaker2.npz")
    listener.unlink()  # the training conversation's second side: audio only
    _ok(["prepare", str(raw), "--out", str(root / "prepared"), "--no-progress"])
    return root / "prepared"


def _windows(output: str, model: str) -> int:
    """The training windows the summary line reports (this process's share: all of them here)."""
    match = re.search(rf"^{model}: step \d+ -> \d+ on (\d+) windows", output, re.MULTILINE)
    assert match, output
    return int(match.group(1))


@pytest.fixture(scope="module")
def first_timar(small_dualtalk, tmp_path_factory) -> tuple[Path, str, dict]:
    """TIMAR trained one step with default settings on the small folder: ``(run, output, run.json)``."""
    out = tmp_path_factory.mktemp("small_timar") / "timar"
    return (out, *_train("timar", small_dualtalk, out, 1))


@pytest.mark.slow
@pytest.mark.parametrize("model", ["timar", "toktalk"])
def test_default_settings_train_on_fewer_windows_than_the_default_batch(model, small_dualtalk, tmp_path, request):
    if model == "timar":  # the run the resume test continues
        _, output, record = request.getfixturevalue("first_timar")
    else:
        output, record = _train(model, small_dualtalk, tmp_path / model, 1)
    windows = _windows(output, model)
    assert windows < 16  # the case this test is about
    assert WARNING.format(n=windows) in output.splitlines()
    assert f"{model}: step 0 -> 1 on" in output
    assert record["train"]["batch_size"] == windows  # the batch actually used


@pytest.mark.slow
def test_a_resumed_small_data_run_keeps_its_batch_without_warning_again(first_timar, small_dualtalk, tmp_path):
    run, first, _ = first_timar
    windows = _windows(first, "timar")
    assert WARNING.format(n=windows) in first.splitlines()
    shutil.copytree(run, tmp_path / "timar")
    output, record = _train("timar", small_dualtalk, tmp_path / "timar", 2)
    assert "resuming timar" in output and "step 1 -> 2" in output
    assert "warning" not in output.lower()
    assert record["train"]["batch_size"] == windows


@pytest.mark.slow
@pytest.mark.skipif(not DEMO.is_dir(), reason="the DualTalk demo clips (../shared/data/dualtalk_demo) are not here")
@pytest.mark.parametrize("model", ["timar", "toktalk"])
def test_default_settings_train_on_the_real_dualtalk_demo_clips(model, tmp_path):
    raw = tmp_path / "dualtalk"
    for split, conv in (("train", "UbjUDM1MiGE_sub_video_72"), ("test", "xkHwlcDSOjc_sub_video_109_000")):
        (raw / split).mkdir(parents=True)
        for f in DEMO.glob(f"{conv}_speaker*"):
            shutil.copy(f, raw / split / f.name)
    _ok(["prepare", str(raw), "--out", str(tmp_path / "prepared"), "--no-progress"])
    output, record = _train(model, tmp_path / "prepared", tmp_path / model, 1)
    windows = _windows(output, model)
    assert f"{model}: step 0 -> 1 on" in output
    assert record["train"]["batch_size"] == min(16, windows)
    assert (WARNING.format(n=windows) in output.splitlines()) == (windows < 16)
