"""The exported stream (``jaxtalk export-model``) against the library's: equality over 100 chunks, and speed.

For each TokTalk preset (``tiny``, ``small``, ``paper``, with their own chunk, window and step count) with random
weights (neither equality nor a chunk's compute depends on training) and a random tokenizer of the demo
corpus's layout (128 codes, the 2-s noise-floor normaliser):

* **Export**: the graphs written by :func:`jaxtalk.models.toktalk.portable.export_stream` (seconds, bytes).
* **Equality**: SynthTalk speech of 100.5 chunks, as two utterances (60.5 chunks, then the rest),
  pushed in 0.4-s pieces through the reference host (``jaxtalk/export/onnx_host.py`` on onnxruntime, fed the
  stream key's white noise) and through the library's live stream (:class:`~jaxtalk.models.toktalk.live.LiveStream`):
  the largest difference of any frame's value, and the largest value.
* **Speed per chunk** on this machine's CPU, the same chunks for both: the library's jitted step (tokenizer
  group + model step, compile excluded: the first ``--warmup`` chunks are not timed) and onnxruntime's
  (frontend + step graph, one session each, default threads), medians over the rest of the 100 chunks, and
  the model step alone (median of ``--repeats`` calls on one window). The host runs in a process of its own
  without JAX, as an engine's would (in one process, JAX's threads and onnxruntime's compete for the cores).
  The step's FLOPs (XLA's count) give
  both runtimes' achieved FLOP/s, next to the matmul peak measured in the same run. There is no public
  TokTalk code to compare against.
* ``--browser``: the ``small`` export's page in headless Chromium (Debian's; the test tools' Chromium driver
  in ``tests/js``), its fake microphone fed the same speech: every chunk's compute in the page
  (onnxruntime-web, WebAssembly, one thread), the capture-to-drawn latency, and the time from the first
  captured sample to the first drawn frame.

Usage: python experiments/onnx_stream.py [--presets tiny small paper] [--warmup 3] [--repeats 20] [--browser]
    [--out experiments/results/onnx_stream.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk import benchmarking as bm

CHUNKS = 100
FIRST_UTTERANCE = 60  # chunks before the utterance end (plus a part chunk)


def live_model(preset: str, seed: int = 0):
    """The preset with random weights, a random tokenizer of the demo corpus's layout and a random style."""
    from jaxtalk.audio.tokenizer import VQTokenizer
    from jaxtalk.bench import random_params
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.live import LiveModel

    config = getattr(tt.TokTalkConfig, preset)()
    rng = np.random.default_rng(seed)
    features = 2 * 80
    tokenizer = VQTokenizer(codebook=rng.normal(size=(128, features)).astype(np.float32),
                            feature_mean=np.full(features, -8.0, np.float32),
                            feature_scale=np.full(features, 4.0, np.float32),
                            embedding=rng.normal(size=(128, config.speech_dim)).astype(np.float32),
                            rate=config.token_rate, floor_window=int(round(2.0 * config.token_rate)))
    params = random_params(lambda k: tt.init_params(config, k), seed)
    style = rng.normal(size=(1, config.style_vector_dim)).astype(np.float32)
    return LiveModel(params, config, tokenizer, style)


def speech(seconds: float) -> np.ndarray:
    """SynthTalk's speech (the small corpus's clips back to back), ``seconds`` long."""
    from jaxtalk.data import synthtalk

    corpus = synthtalk.generate("tiny", seed=0)
    pieces, total = [], 0
    for i in range(len(corpus)):
        pieces.append(np.asarray(corpus.audio(i), np.float32))
        total += pieces[-1].size
        if total >= seconds * 16000:
            break
    return np.concatenate(pieces)[: int(seconds * 16000)]


def _pieces(audio: np.ndarray, size: int) -> list[np.ndarray]:
    return [audio[i:i + size] for i in range(0, audio.size, size)]


# The host's side, in a process of its own with no JAX (as a game engine's or a page's would be): the exported
# folder's host.py streams the utterances, fed the white noise of the library's stream key, and times each
# push that computes a chunk and the step graph alone on one window.
HOST_SCRIPT = r"""
import sys, time, statistics, numpy as np
sys.path.insert(0, sys.argv[1])
from host import OnnxStream
data = np.load(sys.argv[2])
first, table = int(data["first_frame"]), data["white"]
host = OnnxStream(sys.argv[1], white=lambda f, n: table[f - first:f - first + n])
frames, times = [], []
for u in range(int(data["utterances"])):
    audio, chunk = data[f"audio_{u}"], int(data["chunk"])
    for i in range(0, audio.size, chunk):
        t0 = time.perf_counter()
        out = host.push(audio[i:i + chunk])
        if out.shape[0]:
            times.append(time.perf_counter() - t0)
        frames.append(out)
    frames.append(host.finish())
feed = {k[5:]: data[k] for k in data.files if k.startswith("feed_")}
for _ in range(3):
    host.step.run(None, feed)
step = []
for _ in range(int(data["repeats"])):
    t0 = time.perf_counter()
    host.step.run(None, feed)
    step.append(time.perf_counter() - t0)
np.savez(sys.argv[3], frames=np.concatenate(frames), times=np.asarray(times), step=np.asarray(step))
"""


def measure(preset: str, folder: Path, warmup: int, repeats: int, peak: float) -> tuple[dict, np.ndarray]:
    from jaxtalk.models.toktalk.noise import frame_white_noise
    from jaxtalk.models.toktalk.portable import export_stream, portable_layout, portable_step
    from jaxtalk.models.toktalk.sampling import default_grid

    model = live_model(preset)
    config = model.config
    began = time.perf_counter()
    export_stream(model, folder, run_name=f"random {preset}")
    export_s = time.perf_counter() - began
    sizes = {p.name: p.stat().st_size for p in folder.glob("*.onnx")}
    chunk = model.chunk_samples
    audio = speech((CHUNKS + 0.5) * chunk / 16000)
    cut = FIRST_UTTERANCE * chunk + chunk // 2  # the first utterance ends in the middle of a chunk
    utterances = [audio[:cut], audio[cut:]]
    key = jax.random.key(1)

    # The library's live stream, chunk by chunk (the first chunks compile).
    live = model.open(key)
    want, jax_ms = [], []
    for part in utterances:
        for piece in _pieces(part, chunk):
            t0 = time.perf_counter()
            out = live.push(piece)
            if out.shape[0]:
                jax_ms.append(1e3 * (time.perf_counter() - t0))
            want.append(out)
        want.append(live.finish())
    want = np.concatenate(want)

    # The model step alone on one window.
    layout = portable_layout(config)
    ts = jnp.asarray(default_grid(config), jnp.float32)
    rng = np.random.default_rng(0)
    feed = dict(tokens=rng.standard_normal((1, layout.window_tokens, config.speech_dim)).astype(np.float32),
                motion=np.zeros((1, layout.window_frames, config.param_dim), np.float32),
                valid=np.ones((1, layout.window_frames), bool),
                white=rng.standard_normal((1, layout.white_frames, config.param_dim)).astype(np.float32),
                chunk_tokens=rng.standard_normal((1, layout.chunk_tokens, config.speech_dim)).astype(np.float32),
                white_chunk=rng.standard_normal((1, config.chunk_frames, config.param_dim)).astype(np.float32),
                cfg_scale=np.asarray(config.cfg_scale, np.float32), temperature=np.asarray(config.temperature, np.float32))
    style = jnp.asarray(model.style)

    def step(*args):
        return portable_step(model.params, config, style, ts, *args)

    jax_step = bm.time_jitted(step, *feed.values(), repeats=repeats)
    flops = bm.xla_flops(step, *feed.values())

    # The host, in its own process: the white noise of every absolute frame the stream asks for.
    last = -(-max(u.size for u in utterances) // chunk) * config.chunk_frames + layout.white_lead_frames + 2 * config.chunk_frames
    table = np.asarray(frame_white_noise(key, layout.white_first_frame, last - layout.white_first_frame, 1,
                                         config.param_dim))[0]
    with tempfile.TemporaryDirectory() as scratch:
        inputs, outputs = Path(scratch) / "in.npz", Path(scratch) / "out.npz"
        np.savez(inputs, first_frame=layout.white_first_frame, white=table, utterances=len(utterances), chunk=chunk,
                 repeats=repeats, **{f"audio_{i}": u for i, u in enumerate(utterances)},
                 **{f"feed_{k}": v for k, v in feed.items()})
        subprocess.run([sys.executable, "-c", HOST_SCRIPT, str(folder), str(inputs), str(outputs)], check=True)
        host = np.load(outputs)
        got, ort_ms, ort_step_s = host["frames"], 1e3 * host["times"], float(np.median(host["step"]))
    assert got.shape == want.shape, (got.shape, want.shape)
    steady = slice(warmup, None)  # the first chunks compile (JAX) or warm up (onnxruntime)
    ort_chunk, jax_chunk = statistics.median(ort_ms[steady]), statistics.median(jax_ms[steady])
    result = {
        "preset": preset, "chunk_frames": config.chunk_frames, "chunk_s": chunk / 16000, "window_frames": config.window_frames,
        "sample_steps": config.sample_steps, "cfg_scale": config.cfg_scale, "temperature": config.temperature,
        "export_s": export_s, "onnx_bytes": sizes,
        "equality": {"chunks": len(jax_ms), "frames": int(got.shape[0]), "utterances": len(utterances),
                     "max_abs_diff": float(np.abs(got - want).max()), "max_abs_value": float(np.abs(want).max())},
        "per_chunk_ms": {"onnxruntime": ort_chunk, "jaxtalk_jit": jax_chunk, "ratio_onnxruntime_to_jax": ort_chunk / jax_chunk,
                         "first_chunk_onnxruntime": float(ort_ms[0]), "first_chunk_jaxtalk_incl_compile": jax_ms[0]},
        "step_only_ms": {"onnxruntime": 1e3 * ort_step_s, "jaxtalk_jit": 1e3 * jax_step.run_median_s,
                         "ratio_onnxruntime_to_jax": ort_step_s / jax_step.run_median_s,
                         "jaxtalk_compile_s": jax_step.compile_s},
        "step_flops": flops,
        "achieved_gflops": {"onnxruntime": None if flops is None else flops / ort_step_s / 1e9,
                            "jaxtalk_jit": None if flops is None else flops / jax_step.run_median_s / 1e9},
        "matmul_peak_gflops": peak / 1e9,
    }
    return result, audio


def browser(folder: Path, audio: np.ndarray, seconds: float) -> dict:
    """The exported page in headless Chromium, its fake microphone fed ``audio`` (looped)."""
    import soundfile

    from jaxtalk.viewer import write_stream_page

    write_stream_page(folder)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    tools = Path(__file__).resolve().parent.parent / "tests" / "js"
    if chromium is None or not (tools / "node_modules" / "playwright-core").is_dir():
        raise SystemExit("--browser needs Debian's chromium and the test tools (cd tests/js && npm ci)")
    with tempfile.TemporaryDirectory() as scratch:
        wav, out = Path(scratch) / "speech.wav", Path(scratch) / "page.json"
        soundfile.write(wav, audio, 16000, subtype="PCM_16")
        subprocess.run(["node", str(tools / "stream_page.mjs"), chromium, "480", "480", str(folder), str(wav), str(seconds),
                        str(out)], check=True, capture_output=True, text=True, timeout=600)
        report = json.loads(out.read_text())
    chunks = report["chunks"][3:]  # the first chunks warm the WebAssembly session up
    compute = np.asarray([c["compute_ms"] for c in chunks])
    latency = np.asarray([c["latency_ms"] for c in chunks])
    return {"backend": report["backend"], "stream_s": seconds, "chunks": len(report["chunks"]), "errors": report["errors"],
            "compute_ms": {"median": float(np.median(compute)), "p90": float(np.percentile(compute, 90)),
                           "max": float(compute.max())},
            "capture_to_drawn_ms": {"median": float(np.median(latency)), "p90": float(np.percentile(latency, 90))},
            "first_frame_ms_after_first_sample": report["firstFrameMs"],
            "first_chunks_compute_ms": [c["compute_ms"] for c in report["chunks"][:3]],
            "requests_outside_the_folder": [r for r in report["requested"] if not r.startswith(report["origin"])],
            "websocket_upgrades": [s for s in report["served"] if s["upgrade"]]}


def _table_row(row: dict) -> dict:
    chunk, flops = row["per_chunk_ms"], row["achieved_gflops"]
    return {"preset": row["preset"], "steps": row["sample_steps"], "max |diff|": row["equality"]["max_abs_diff"],
            "onnxruntime ms/chunk": chunk["onnxruntime"], "jaxtalk ms/chunk": chunk["jaxtalk_jit"],
            "ratio": chunk["ratio_onnxruntime_to_jax"], "onnxruntime GFLOP/s": flops["onnxruntime"],
            "jaxtalk GFLOP/s": flops["jaxtalk_jit"], "matmul peak GFLOP/s": row["matmul_peak_gflops"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--presets", nargs="+", default=["tiny", "small", "paper"])
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--browser", action="store_true")
    parser.add_argument("--browser-seconds", type=float, default=20.0)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/onnx_stream.json"))
    args = parser.parse_args()
    import onnxruntime

    peak = bm.measure_matmul_peak()
    rows = []
    payload = {"machine": bm.machine_info(), "onnxruntime": onnxruntime.__version__, "matmul_peak_gflops": peak / 1e9,
               "weights": "random (neither equality nor a chunk's compute depends on training)", "presets": rows}
    with tempfile.TemporaryDirectory() as scratch:
        for preset in args.presets:
            folder = Path(scratch) / preset
            row, audio = measure(preset, folder, args.warmup, args.repeats, peak)
            print(json.dumps(row))
            rows.append(row)
            if args.browser and preset == "small":
                payload["browser_small"] = browser(folder, audio, args.browser_seconds)
                print(json.dumps(payload["browser_small"]))
    bm.print_table([_table_row(r) for r in rows], "The exported stream against the library's (per chunk, this machine's CPU)")
    if "browser_small" in payload:
        page = payload["browser_small"]
        bm.print_table([{"page": "small", "backend": page["backend"], "compute ms (median)": page["compute_ms"]["median"],
                         "compute ms (max)": page["compute_ms"]["max"], "chunk ms": 400,
                         "first frame ms": page["first_frame_ms_after_first_sample"]}], "The page in headless Chromium")
    bm.write_json(args.out, payload)
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
