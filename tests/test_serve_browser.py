"""``jaxtalk view --live`` in headless Chromium, its microphone Chromium's fake device fed from a WAV (speech, then
silence, looped), streaming to ``jaxtalk serve`` on this machine.

* With a transparent stand-in model whose jaw opens with the loudness of each 40-ms frame, the drawn jaw
  follows the audio the page captured frame by frame: open while the WAV speaks, shut in its silence.
* With the session's TokTalk run, every drawn frame is exactly the frame the model gives offline for the
  audio the page sent, and the page's capture-to-drawn latency of every chunk is measured and reported
  (printed, and written to ``latency.json`` in the test's folder).

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

from jaxtalk.serve import ServeOptions, start_server
from jaxtalk.viewer import start_live_server

pytestmark = [pytest.mark.external, pytest.mark.slow]

SIZE = 320
STREAM_S = 4  # wall seconds the page streams for


class EnvelopeStream:
    """Jaw opening = 6 x the RMS of each 640-sample (one 25-fps frame) stretch of audio, up to 0.5 rad."""

    def __init__(self):
        self.buffer = np.zeros(0, np.float32)

    def _frames(self, whole: int) -> np.ndarray:
        audio, self.buffer = self.buffer[:whole * 640], self.buffer[whole * 640:]
        params = np.zeros((whole, 56), np.float32)
        params[:, 50] = np.minimum(0.5, 6 * np.sqrt(np.mean(audio.reshape(whole, 640) ** 2, axis=1)))
        return params

    def push(self, samples: np.ndarray) -> np.ndarray:
        self.buffer = np.concatenate([self.buffer, samples])
        return self._frames(self.buffer.size // 2560 * 4)

    def finish(self) -> np.ndarray:
        out = self._frames(self.buffer.size // 640)
        self.buffer = np.zeros(0, np.float32)
        return out


class EnvelopeModel:
    """A live model (the interface ``jaxtalk serve`` takes) that anyone can check by eye: see EnvelopeStream."""

    fps, sample_rate, chunk_frames, chunk_samples, lookahead_samples = 25, 16000, 4, 2560, 0

    def describe(self) -> dict:
        return {"model": "envelope", "fps": 25, "sample_rate": 16000, "chunk_frames": 4, "chunk_samples": 2560,
                "lookahead_samples": 0, "sample_steps": 0}

    def open(self, key) -> EnvelopeStream:
        return EnvelopeStream()


@pytest.fixture(scope="module")
def wav(tmp_path_factory, synthtalk_tiny) -> str:
    """2 s of the tiny corpus's speech, then 1.5 s of silence (Chromium loops the file)."""
    speech = np.asarray(synthtalk_tiny.audio(synthtalk_tiny.split("test")[0]), np.float32)[:32000]
    path = tmp_path_factory.mktemp("mic") / "mic.wav"
    soundfile.write(path, np.concatenate([speech / np.abs(speech).max() * 0.5, np.zeros(24000, np.float32)]), 16000,
                    subtype="PCM_16")
    return str(path)


@pytest.fixture(scope="module")
def viewer_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("viewer-cache")


def stream_in_chromium(model, wav: str, out, viewer_cache, **server_kw) -> dict:
    """Serve ``model``, open the live page against it in Chromium for STREAM_S, return what the page saw."""
    browser = chromium()
    server = start_server(model, ServeOptions(port=0), **server_kw)
    try:
        viewer = start_live_server(server.url, port=0, cache_dir=viewer_cache)
        try:
            summary = run_browser("live.mjs", browser, SIZE, SIZE, viewer.url, wav, STREAM_S, out)
        finally:
            viewer.close()
    finally:
        server.close()
    report = json.loads(out.read_text())
    assert summary["errors"] == [] and report["errors"] == [], (summary, report["errors"])
    assert report["state"] == "streaming" and report["ready"]["outputs"]["morph"]["channels"][-1] == "neck.qw"
    report["sent"] = np.frombuffer(base64.b64decode(report["audio"]), "<f4")
    assert report["sent"].size == report["sentSamples"] >= 16000 * (STREAM_S - 2)  # the page kept capturing
    return report


def test_the_drawn_jaw_follows_the_microphones_loudness_frame_by_frame(node_tools, wav, viewer_cache, tmp_path):  # noqa: F811
    report = stream_in_chromium(EnvelopeModel(), wav, tmp_path / "page.json", viewer_cache, key_fn=lambda seed: seed)
    rms = np.asarray(report["frameRms"], np.float64)
    drawn = [d for d in report["drawn"] if d["frame"] < rms.size]
    frames = np.asarray([d["frame"] for d in drawn])
    jaw = np.asarray([d["jaw"] for d in drawn])
    assert len(drawn) >= 5 * STREAM_S
    # The jaw drawn for frame f opens exactly as far as the loudness of the audio the page captured for f.
    np.testing.assert_allclose(jaw, np.minimum(0.5, 6 * rms[frames]), atol=1e-4)
    speaking, silent = rms[frames] > 0.02, rms[frames] < 1e-3
    assert speaking.sum() >= 10 and silent.sum() >= 10  # both halves of the looped WAV came through the microphone
    assert jaw[speaking].mean() > 0.15 and jaw[silent].max() < 0.01
    assert np.ptp(jaw[speaking]) > 0.1  # and it moves while speaking, not just open


def test_the_page_draws_the_models_frames_for_the_audio_it_captured_and_reports_its_latency(
        node_tools, wav, viewer_cache, trained_toktalk, tmp_path, capsys):  # noqa: F811
    import jax

    from jaxtalk.face import builtin_face
    from jaxtalk.models.toktalk.live import LiveModel
    from jaxtalk.runs import load_run
    from jaxtalk.serve.outputs import MorphOutput

    live = LiveModel.from_run(load_run(trained_toktalk.dir))
    report = stream_in_chromium(live, wav, tmp_path / "page.json", viewer_cache)
    # Offline: the same audio through the library's live stream and the morph output, from the same seed.
    stream = live.open(jax.random.key(0))
    morph = MorphOutput(builtin_face(0))
    _, want = morph.convert(morph.start(), stream.push(report["sent"]))
    drawn = [d for d in report["drawn"] if d["frame"] < want.shape[0]]
    # Software WebGL on a busy CPU draws ~10 pictures a second: every drawn frame is checked.
    assert len(drawn) >= 5 * STREAM_S
    got = np.asarray([d["values"] for d in drawn], np.float32)
    np.testing.assert_allclose(got, want[[d["frame"] for d in drawn]], atol=2e-6)
    assert np.ptp(got[:, -8:-4], axis=0).max() > 1e-3  # the jaw moves
    # Latency: capture of the audio message that completed a chunk -> its first frame drawn.
    chunks = report["chunks"]
    latency = np.asarray([c["latency_ms"] for c in chunks])
    compute = np.asarray([c["compute_ms"] for c in chunks])
    summary = {"chunks": len(chunks), "latency_ms": {"median": float(np.median(latency)),
               "p90": float(np.percentile(latency, 90)), "max": float(latency.max())},
               "server_compute_ms": {"median": float(np.median(compute)),
               "p90": float(np.percentile(compute, 90))}, "chunk_ms": 1e3 * live.chunk_samples / 16000,
               "send_ms": 40, "wall_s": report["wall"], "status": report["status"]}
    (tmp_path / "latency.json").write_text(json.dumps({**summary, "per_chunk": chunks}, indent=1))
    with capsys.disabled():
        print(f"\nlive page latency (capture -> drawn), {len(chunks)} chunks: {json.dumps(summary)}")
    assert len(chunks) >= 0.4 * STREAM_S / 0.16 and np.all(latency > 0)
    assert np.median(latency) < 500 and np.all(compute < latency)
