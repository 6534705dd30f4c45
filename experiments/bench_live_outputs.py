"""What ``jaxtalk serve``'s outputs cost per chunk: ``params`` only, + ``morph``, + ``arkit``, all together.

The demo-size TokTalk (``jaxtalk.demo.model_config``: the ``small`` preset, 0.4-s chunks of 10 frames,
one Euler step) with random weights (a chunk's compute does not depend on training) and a random
tokenizer of the demo corpus's layout (128 codes, the 2-s noise-floor normaliser) runs as the server's
device thread does (``LiveServer._work``): each 0.4-s piece of audio is pushed into the client's stream
(tokenizer + model step) and its frames go through every output the client asked for, each output
carrying its per-client state from chunk to chunk. The four cases advance their own streams in turns
(one chunk of each per round), so that a change in the machine's load reaches all of them alike.

Reported per case: the median per-chunk compute over ``--repeats`` chunks (compile excluded: the first
``--warmup`` chunks are not timed; every output returns host arrays, so nothing is left running), the
median of that over ``--runs`` runs (fresh streams each) with each run's, and its ratio to ``params``
only; within the ``all`` case, the model step and each output's share. A random model's frames are
not speech, so the ARKit solve is also timed on speech motion (SynthTalk's rule-based motion of a
clip, in the same 10-frame chunks), with the solver's iterations (the most Newton steps a frame took).
The machine's load average is recorded before and after.

Usage: python experiments/bench_live_outputs.py [--repeats 40] [--runs 3] [--warmup 3]
    [--out experiments/results/live/outputs.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import numpy as np

from jaxtalk import benchmarking as bm

CASES = {
    "params": ("params",),
    "params+morph": ("params", "morph"),
    "params+arkit": ("params", "arkit"),
    "all": ("params", "morph", "arkit"),
}


def demo_live_model(seed: int = 0):
    """The demo's TokTalk with random weights and a random tokenizer of the demo corpus's layout."""
    from jaxtalk.audio.tokenizer import VQTokenizer
    from jaxtalk.bench import random_params
    from jaxtalk.demo import model_config
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.live import LiveModel

    config = model_config(chunk_frames=10, sample_steps=1)
    rng = np.random.default_rng(seed)
    features = 2 * 80  # stack x mel channels
    tokenizer = VQTokenizer(codebook=rng.normal(size=(128, features)), feature_mean=np.zeros(features),
                            feature_scale=np.ones(features), embedding=rng.normal(size=(128, config.speech_dim)),
                            rate=config.token_rate, floor_window=int(round(2.0 * config.token_rate)))
    params = random_params(lambda k: tt.init_params(config, k), seed)
    style = rng.normal(size=(1, config.style_vector_dim)).astype(np.float32)
    return LiveModel(params, config, tokenizer, style)


def speech_motion(seconds: float = 30.0) -> np.ndarray:
    """``(T, 56)`` SynthTalk's rule-based motion of one speaking clip."""
    from jaxtalk.data.synthtalk import SizeSpec, generate

    corpus = generate(SizeSpec((1, 0, 0, 0), 1, seconds, (0, 0, 0, 0), seconds, 8, 1e9, identities=(0,),
                               lazy=True), seed=0)
    motion, _ = corpus.motion_without_audio(0)
    return np.asarray(motion, np.float32)


def measure(live, outputs, audio: np.ndarray, warmup: int, repeats: int) -> tuple[dict, dict]:
    """One run: every case's per-chunk seconds (fresh streams, the cases in turns) and, within ``all``,
    the seconds of the model step and of each output."""
    piece = live.chunk_samples
    clients = {case: (live.open(jax.random.key(0)), {name: outputs[name].start() for name in names})
               for case, names in CASES.items()}
    times: dict[str, list[float]] = {case: [] for case in CASES}
    shares: dict[str, list[float]] = {"model": [], "params": [], "morph": [], "arkit": []}
    for r in range(warmup + repeats):
        # the first push also carries the tokenizer's look-ahead; every later one completes one chunk
        lo = 0 if r == 0 else live.lookahead_samples + piece * r
        hi = live.lookahead_samples + piece * (r + 1)
        for case, (stream, states) in clients.items():
            clock = time.perf_counter()
            frames = stream.push(audio[lo:hi])
            marks = [("model", time.perf_counter())]
            for name in CASES[case]:
                states[name], values = outputs[name].convert(states[name], frames)
                marks.append((name, time.perf_counter()))
            assert frames.shape[0] == live.chunk_frames and values.shape[0] == live.chunk_frames
            if r >= warmup:
                times[case].append(marks[-1][1] - clock)
                if case == "all":
                    before = clock
                    for name, at in marks:
                        shares[name].append(at - before)
                        before = at
    return times, shares


def main() -> None:
    from jaxtalk.serve.outputs import build_outputs

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=40, help="timed chunks per case and run")
    parser.add_argument("--runs", type=int, default=3, help="runs, each with fresh streams")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--out", default="experiments/results/live/outputs.json")
    args = parser.parse_args()
    load_before = os.getloadavg()

    live = demo_live_model()
    started = time.perf_counter()
    outputs = build_outputs(("params", "morph", "arkit"), {})
    build_s = time.perf_counter() - started
    rng = np.random.default_rng(1)
    audio = (0.1 * rng.normal(size=live.lookahead_samples + live.chunk_samples * (args.warmup + args.repeats))
             ).astype(np.float32)
    runs = [measure(live, outputs, audio, args.warmup, args.repeats) for _ in range(args.runs)]

    # The ARKit solve on speech motion, in the stream's 10-frame chunks.
    motion = speech_motion()
    arkit = outputs["arkit"]
    state, solve_times = arkit.start(), []
    for start in range(0, motion.shape[0] - live.chunk_frames + 1, live.chunk_frames):
        clock = time.perf_counter()
        state, _ = arkit.convert(state, motion[start:start + live.chunk_frames])
        solve_times.append(time.perf_counter() - clock)
    steps = arkit.retargeter(motion).iterations
    load_after = os.getloadavg()

    # Per run, each case's median; reported, the median over runs of those medians.
    per_run = [{case: statistics.median(t) for case, t in times.items()} for times, _ in runs]
    median = {case: statistics.median(m[case] for m in per_run) for case in CASES}
    rows = [{"case": case, "outputs": ", ".join(CASES[case]), "median_ms": 1e3 * median[case],
             "runs_ms": [round(1e3 * m[case], 3) for m in per_run],
             "ratio_to_params": median[case] / median["params"],
             "runs_ratio": [round(m[case] / m["params"], 3) for m in per_run]}
            for case in CASES]
    bm.print_table([{k: v for k, v in row.items() if not k.startswith("runs")} for row in rows],
                   f"Per-chunk compute, {live.chunk_frames}-frame (0.4-s) chunks, median of {args.repeats} chunks "
                   f"x {args.runs} runs")
    split = {name: 1e3 * statistics.median(statistics.median(shares[name]) for _, shares in runs)
             for name in runs[0][1]}
    print("within 'all' (median ms): " + ", ".join(f"{k} {v:.3f}" for k, v in split.items()))
    speech = {"chunks": len(solve_times) - 1, "median_ms": 1e3 * statistics.median(solve_times[1:]),
              "solver_iterations": int(steps)}
    print(f"arkit on speech motion: {speech['median_ms']:.3f} ms per chunk (median of {speech['chunks']}); "
          f"solver iterations {steps}")
    print(f"load average (1, 5, 15 min): before {load_before}, after {load_after}; {os.cpu_count()} CPUs")
    bm.write_json(args.out, {
        "rows": rows, "all_split_ms": split, "arkit_on_speech_motion": speech, "repeats": args.repeats,
        "runs": args.runs, "warmup": args.warmup, "chunk_frames": live.chunk_frames,
        "chunk_s": live.chunk_frames / live.fps, "outputs_build_s": build_s, "load_average_before": load_before,
        "load_average_after": load_after, "cpus": os.cpu_count(),
        "machine": platform.processor() or platform.machine(), "jax": jax.__version__,
        "device": str(jax.devices()[0]),
    })


if __name__ == "__main__":
    main()
