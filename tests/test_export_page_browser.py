"""The page ``jaxtalk export-model`` writes, in headless Chromium: the exported stream runs in the browser
(onnxruntime-web) on a fake microphone fed from a WAV (speech, then silence, looped), served by a plain static
file server.

* No request goes anywhere but to the folder's own files: no WebSocket, no other origin, nothing the folder
  does not hold (no Python process computes anything).
* Every drawn frame is the frame the reference host (``host.py`` on onnxruntime) computes for the audio the
  page captured and the noise it drew.
* With a model trained for 200 steps (the ``small`` preset on SynthTalk tiny), the drawn jaw follows the
  WAV's loudness: wider open while it speaks than in its silence.

Tools as in test_export_browser: Node.js/npm (tests/js, installed on first use) and Chromium; without them
the tests skip and say which.
"""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest
import soundfile
from test_export_browser import chromium, node_tools, run_browser  # noqa: F401  (node_tools: a fixture)

pytest.importorskip("jax2onnx")
pytest.importorskip("onnxruntime")

pytestmark = [pytest.mark.external, pytest.mark.slow]

SIZE = 320
STREAM_S = 8  # wall seconds the page streams for: two loops of the WAV
SPEECH_S, SILENCE_S = 2.0, 1.5


@pytest.fixture(scope="module")
def wav(tmp_path_factory, synthtalk_tiny) -> str:
    """2 s of the tiny corpus's speech, then 1.5 s of silence (Chromium loops the file)."""
    speech = np.asarray(synthtalk_tiny.audio(synthtalk_tiny.split("test")[0]), np.float32)[: int(SPEECH_S * 16000)]
    path = tmp_path_factory.mktemp("mic") / "mic.wav"
    soundfile.write(path, np.concatenate([speech / np.abs(speech).max() * 0.5, np.zeros(int(SILENCE_S * 16000), np.float32)]),
                    16000, subtype="PCM_16")
    return str(path)


def _learned_model(prepared_tiny, learned):
    """conftest's ``learned_toktalk_small`` (200 steps) as a live model, with the data's tokenizer."""
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.live import LiveModel

    config, params = learned
    clip = prepared_tiny.record(prepared_tiny.split("train")[0], ("motion",))["motion"][None, : 4 * config.style_frames]
    return LiveModel(params, config, prepared_tiny.tokenizer(), tt.encode_style(params, config, clip))


def test_the_page_runs_the_model_in_the_browser_and_the_jaw_follows_the_microphones_loudness(
        node_tools, wav, prepared_tiny, learned_toktalk_small, tmp_path, capsys):  # noqa: F811
    from jaxtalk.export.onnx_host import OnnxStream
    from jaxtalk.models.toktalk.portable import export_stream
    from jaxtalk.viewer import write_stream_page

    folder = tmp_path / "web"
    manifest = export_stream(_learned_model(prepared_tiny, learned_toktalk_small), folder, run_name="small-200")
    write_stream_page(folder, tmp_path / "viewer-cache")
    out = tmp_path / "page.json"
    summary = run_browser("stream_page.mjs", chromium(), SIZE, SIZE, folder, wav, STREAM_S, out)
    report = json.loads(out.read_text())
    assert summary["errors"] == [] and report["errors"] == [], (summary, report["errors"])
    assert report["state"] == "streaming"

    # Files of the folder and nothing else: no WebSocket, no other origin, no path the folder lacks.
    assert all(r.startswith(report["origin"] + "/") for r in report["requested"]), report["requested"]
    assert not [s for s in report["served"] if s["upgrade"] or s["method"] != "GET"]
    files = {"/" + p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
    assert {s["path"] for s in report["served"]} <= files
    assert {"/step.onnx", "/frontend.onnx", "/morph.onnx"} <= {s["path"] for s in report["served"]}

    # The drawn frames are the reference host's for the captured audio and the noise the page drew.
    captured = np.frombuffer(base64.b64decode(report["audio"]), "<f4")
    noise = [np.asarray(n, np.float32).reshape(-1, manifest["param_dim"]) for n in report["noise"]]
    host = OnnxStream(folder, white=lambda first, frames: noise.pop(0))
    params = np.concatenate([host.push(captured[i:i + 640]) for i in range(0, captured.size, 640)])
    drawn = [d for d in report["drawn"] if d["frame"] < params.shape[0]]
    assert len(drawn) >= 5 * STREAM_S
    frames = np.asarray([d["frame"] for d in drawn])
    np.testing.assert_allclose(np.asarray([d["params"] for d in drawn], np.float32), params[frames], atol=1e-4)

    # The jaw follows the loudness of the audio the page captured for each frame.
    rms = np.asarray(report["frameRms"], np.float64)[frames]
    jaw = np.asarray([d["jaw"] for d in drawn])
    speaking, silent = rms > 0.02, rms < 1e-3
    assert speaking.sum() >= 10 and silent.sum() >= 10  # both halves of the looped WAV came through
    corr = float(np.corrcoef(jaw, np.log(rms + 1e-4))[0, 1])
    compute = np.asarray([c["compute_ms"] for c in report["chunks"][3:]])
    with capsys.disabled():
        print(f"\nexported page: jaw {jaw[speaking].mean():.3f} rad speaking vs {jaw[silent].mean():.3f} silent, "
              f"corr(jaw, log rms) {corr:.2f}; compute per 0.4-s chunk median {np.median(compute):.0f} ms, "
              f"first frame {report['firstFrameMs']:.0f} ms after the first sample ({report['backend']})")
    assert jaw[speaking].mean() > jaw[silent].mean() + 0.02
    assert corr > 0.4
