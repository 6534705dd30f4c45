"""Exported files checked by outside tools: the Khronos glTF validator (npm ``gltf-validator``) finds no
errors, and headless Chromium plays ``jaxtalk view``'s page: between two times of a jaw-only clip the
mouth changes on screen while the background and the upper face do not, and a clip played with its
audio and paused shows the frame of the audio's time.

The tools come from the npm registry through ``tests/js/package-lock.json`` (installed here on first
use) and Debian's ``chromium``; where Node.js, npm or Chromium is missing, the tests skip and say which.
"""

from __future__ import annotations

import fcntl
import json
import shutil
import subprocess
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from test_export_gltf import flame_like_model, head_motion

from jaxtalk.export import export_face_model, export_vertex_sequence, write_audio_beside
from jaxtalk.face import builtin_face
from jaxtalk.viewer import start_server

pytestmark = pytest.mark.external  # Node.js/npm and Chromium

JS = Path(__file__).with_name("js")
SIZE = 320


@pytest.fixture(scope="module")
def node_tools():
    """``tests/js/node_modules`` (gltf-validator, playwright-core, gltfpack), installed by ``npm ci`` once."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("Node.js and npm are not installed: the glTF validator and browser tests need them")
    # One install for every pytest worker: the first takes the lock, the others wait and reuse it.
    with open(JS / ".install.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        wanted = json.loads((JS / "package.json").read_text())["dependencies"]
        if any(not (JS / "node_modules" / name / "package.json").is_file() for name in wanted):
            done = subprocess.run(["npm", "ci", "--ignore-scripts", "--no-audit", "--no-fund"], cwd=JS,
                                  capture_output=True, text=True)
            if done.returncode != 0:
                pytest.skip(f"npm ci could not install the test tools: {done.stderr.strip()[-300:]}")
    return JS


def validate(paths: list[Path]) -> list[dict]:
    done = subprocess.run(["node", str(JS / "validate.mjs"), *map(str, paths)], capture_output=True, text=True,
                          check=True)
    return [json.loads(line) for line in done.stdout.splitlines()]


def test_validator_reports_no_errors_on_face_model_flame_like_and_vertex_basis_exports(node_tools, tmp_path):
    low = builtin_face(0, resolution="low")
    files = [
        export_face_model(builtin_face(0), head_motion(40), tmp_path / "builtin.glb").path,
        export_face_model(flame_like_model(), head_motion(40), tmp_path / "flame_like.glb").path,
        export_vertex_sequence(np.asarray(low.vertices_seq(head_motion(40)), np.float32), np.asarray(low.faces),
                               tmp_path / "basis.glb").path,
        export_face_model(builtin_face(0), np.zeros((1, 56), np.float32), tmp_path / "one_frame.glb").path,
    ]
    reports = validate(files)
    assert len(reports) == len(files)
    for report in reports:
        issues = report["issues"]
        assert issues["numErrors"] == 0, (report["path"], issues["messages"])
        assert report["info"]["animationCount"] == 1 and report["info"]["hasMorphTargets"]
    flame_like = reports[1]["info"]
    assert flame_like["hasSkins"] and flame_like["maxInfluences"] == 8  # two JOINTS/WEIGHTS sets


def run_browser(script: str, *args: object) -> dict:
    """Run ``tests/js/<script>`` (Chromium through ``browser.mjs``) and return the JSON line it prints last."""
    done = subprocess.run(["node", str(JS / script), *map(str, args)], capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.splitlines()[-1])


def chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium): the browser test needs it")
    return path


def jaw_only_clip(frames: int = 50) -> np.ndarray:
    """The mouth opens from closed (t = 0) to 0.35 rad (t = 1 s); nothing else moves."""
    params = np.zeros((frames, 56), np.float32)
    params[:, 50] = 0.35 * np.clip(np.arange(frames) / 25.0, 0.0, 1.0)
    return params


def test_chromium_plays_the_page_the_mouth_moves_on_screen_and_the_background_does_not(node_tools, tmp_path):
    browser = chromium()
    folder = tmp_path / "out"
    folder.mkdir()
    export_face_model(builtin_face(0), jaw_only_clip(), folder / "jaw.glb")
    server = start_server(folder, port=0, cache_dir=tmp_path / "viewer-cache")
    shots = [tmp_path / "t0.png", tmp_path / "t1.png", tmp_path / "t1_again.png"]
    try:
        report = run_browser("screenshot.mjs", browser, SIZE, SIZE, f"{server.url}?t=0", shots[0],
                             f"{server.url}?t=1.0", shots[1], f"{server.url}?clip=jaw&t=1.0", shots[2])
    finally:
        server.close()
    assert report["errors"] == []
    closed, opened, again = (iio.imread(p)[..., :3].astype(np.int32) for p in shots)
    background = closed[0, 0]
    face = np.argwhere(np.abs(closed - background).sum(-1) > 0)
    (top, left), (bottom, right) = face.min(0), face.max(0)
    height, width = bottom - top, right - left
    assert 0.4 * SIZE < height < 0.95 * SIZE  # the face is framed, not a dot or a crop
    centre = slice(left + width // 4, right - width // 4)
    change = np.abs(opened - closed).mean(-1)  # grey levels of 255, averaged over RGB
    mouth = change[top + int(0.62 * height): bottom + 10, centre]
    upper = change[top: top + int(0.4 * height), centre]
    border = np.ones(closed.shape[:2], bool)
    border[top - 10: bottom + 10, left - 10: right + 10] = False
    # Measured (Chromium 156, SwiftShader): the mouth region changes by 30 grey levels on average and
    # 63% of its pixels by more than 10; the upper face and the background not at all.
    assert mouth.mean() > 15 and (mouth > 10).mean() > 0.4, (mouth.mean(), (mouth > 10).mean())
    assert upper.mean() < 0.5, upper.mean()
    assert change[border].max() == 0
    np.testing.assert_array_equal(opened, again)  # the same time draws the same picture


PLAY_S = 1.0


def test_chromium_plays_a_clip_with_its_audio_and_pauses_on_the_frame_of_the_audio_time(node_tools, tmp_path):
    browser = chromium()
    folder = tmp_path / "out"
    folder.mkdir()
    clip = np.zeros((76, 56), np.float32)  # 3 s over which the mouth opens steadily to 0.35 rad
    clip[:, 50] = np.linspace(0.0, 0.35, len(clip))
    glb = export_face_model(builtin_face(0), clip, folder / "jaw.glb").path
    rate = 16_000
    write_audio_beside(glb, 0.1 * np.sin(2 * np.pi * 220 * np.arange(3 * rate) / rate), rate)
    server = start_server(folder, port=0, cache_dir=tmp_path / "viewer-cache")
    paused, still, earlier = tmp_path / "paused.png", tmp_path / "still.png", tmp_path / "earlier.png"
    try:
        report = run_browser("playback.mjs", browser, SIZE, SIZE, server.url, PLAY_S, paused)
        clock = report["clock"]
        # The still page drawn at the audio's time, to compare with what the paused page shows, and
        # 0.2 s before it (which must look different, or the comparison proves nothing).
        stills = run_browser("screenshot.mjs", browser, SIZE, SIZE, f"{server.url}?t={clock['audio']!r}", still,
                             f"{server.url}?t={clock['audio'] - 0.2!r}", earlier)
    finally:
        server.close()
    assert report["errors"] == [] and stills["errors"] == []
    # The audio really played, at about wall-clock speed (its clock cannot run ahead of the wall), and
    # the page drew the audio's time, not a clock of its own.
    assert 0.5 * PLAY_S < clock["audio"] <= report["wall"] + 0.1, report
    assert clock["shown"] == clock["audio"] and not clock["playing"], report
    assert f"{clock['audio']:.2f} / {(len(clip) - 1) / 25:.2f} s" in report["label"], report
    assert "no audio" not in report["label"], report
    shown, expected, before = (iio.imread(p)[..., :3].astype(np.int32) for p in (paused, still, earlier))
    np.testing.assert_array_equal(shown, expected)
    # 0.2 s earlier the jaw is 0.024 rad less open: measured 10,203 pixels differ.
    assert (np.abs(shown - before).sum(-1) > 0).sum() > 1000
