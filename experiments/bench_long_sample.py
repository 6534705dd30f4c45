"""Peak memory of offline sampling on long inputs: whole-sequence vs bounded.

Every row runs in a fresh subprocess and reports its peak resident set size (``ru_maxrss``) and wall
time. TokTalk's ``sample`` holds O(frames^2) attention (a 20-minute clip asked for 45 GB on the
paper preset); ``sample_long`` (what ``jaxtalk sample`` runs) works on minute-long windows. FreeTalk's
ATS sampled every window of a clip in one call; it now samples 8 at a time (both rows use the log-mel
front end, now computed in 60-s pieces: before, a 60-min clip peaked at 4.4 GB). TIMAR streams turn by
turn with a fixed context in both ``sample`` and ``stream``. The whole-sequence rows stop at lengths a
CPU can hold; the bounded rows go to an hour.

    PYTHONPATH=$PWD python experiments/bench_long_sample.py            # the table
    PYTHONPATH=$PWD python experiments/bench_long_sample.py --quick    # short rows only
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import textwrap

WORKER = textwrap.dedent('''
    import json, resource, sys, time
    import jax, numpy as np
    model, method, minutes = sys.argv[1], sys.argv[2], float(sys.argv[3])
    rng = np.random.default_rng(0)
    if model == "toktalk":  # tiny preset; whole: toktalk.sample, bounded: toktalk.sample_long
        from jaxtalk.models import toktalk as tt
        cfg = tt.TokTalkConfig.tiny()
        params = tt.init_params(cfg, jax.random.key(0))
        tokens = rng.normal(size=(1, int(minutes * 60 * cfg.token_rate), cfg.speech_dim)).astype(np.float32)
        style = np.zeros((1, cfg.style_vector_dim), np.float32)
        fn = tt.sample if method == "whole" else tt.sample_long
        run = lambda: fn(params, cfg, tokens, style, jax.random.key(1))
    elif model == "freetalk":  # ATS landmark track; whole: every window in one call (the old batching)
        from jaxtalk.models.freetalk import ats
        from jaxtalk.models.freetalk.animate import landmark_track
        from jaxtalk.models.freetalk.config import ATSConfig
        from jaxtalk.models.freetalk.data import DisplacementStats
        from jaxtalk.models.freetalk.fit import FittedATS
        cfg = ATSConfig.small(max_frames=300, num_layers=1, sample_steps=2)
        stats = DisplacementStats(mean=np.zeros((68, 3), np.float32), std=np.full((68, 3), 0.004, np.float32))
        fitted = FittedATS(cfg, ats.init_params(cfg, jax.random.key(0)), stats, [], window=300)
        audio = (0.1 * rng.normal(size=int(minutes * 60 * 16000))).astype(np.float32)
        per_call = 10**9 if method == "whole" else 8
        run = lambda: landmark_track(fitted, audio, "neutral", 1.0, jax.random.key(1), windows_per_call=per_call)
    else:  # TIMAR small, turn by turn (its only mode: no whole-sequence variant)
        from jaxtalk.models.timar.config import TimarConfig
        from jaxtalk.models.timar.model import init_params
        from jaxtalk.models.timar.streaming import stream_conversation
        cfg = TimarConfig.small()
        params = init_params(cfg, jax.random.key(0))
        frames = int(minutes * 60) * cfg.frames_per_turn
        us = rng.normal(size=(1, frames, cfg.speech_dim)).astype(np.float32)
        um = np.zeros((1, frames, 56), np.float32)
        run = lambda: stream_conversation(params, cfg, us, um, us, jax.random.key(1), context=cfg.max_turns - 1)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    out = np.asarray(run())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"frames": out.shape[-3] if out.ndim == 3 and model == "freetalk" else out.shape[1],
                      "base_mb": base / 1024, "peak_mb": peak / 1024, "wall_s": time.perf_counter() - t0}))
''')


def run_row(model: str, method: str, minutes: float) -> dict:
    """One measurement in a fresh process: ``{"frames", "base_mb", "peak_mb", "wall_s"}``."""
    proc = subprocess.run([sys.executable, "-c", WORKER, model, method, str(minutes)],
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


ROWS = [  # (model, method, minutes, quick)
    ("toktalk", "whole", 2.5, True), ("toktalk", "whole", 5.0, True), ("toktalk", "bounded", 2.5, True),
    ("toktalk", "bounded", 10.0, True), ("toktalk", "bounded", 60.0, False),
    ("freetalk", "whole", 2.5, True), ("freetalk", "whole", 10.0, True), ("freetalk", "bounded", 2.5, True),
    ("freetalk", "bounded", 10.0, True), ("freetalk", "bounded", 60.0, False),
    ("timar", "bounded", 2.5, True), ("timar", "bounded", 10.0, True), ("timar", "bounded", 60.0, False),
]
NAMES = {("toktalk", "whole"): "toktalk.sample", ("toktalk", "bounded"): "toktalk.sample_long",
         ("freetalk", "whole"): "ATS, 1 call", ("freetalk", "bounded"): "ATS, 8 per call",
         ("timar", "bounded"): "TIMAR turns"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only rows of at most 10 minutes")
    parser.add_argument("--model", choices=("toktalk", "freetalk", "timar"), help="only this model's rows")
    args = parser.parse_args()
    print("peak RSS of offline sampling, fresh process per row "
          "(TokTalk tiny; ATS small, 1 layer, 2 DDIM steps; TIMAR small; CPU)")
    print(f"{'method':>20} {'minutes':>8} {'frames':>8} {'peak MB':>9} {'wall s':>8}")
    for model, method, minutes, quick in ROWS:
        if (args.quick and not quick) or (args.model and model != args.model):
            continue
        r = run_row(model, method, minutes)
        name = NAMES[model, method]
        if "error" in r:
            print(f"{name:>20} {minutes:8.1f}  failed: {r['error']}", flush=True)
        else:
            print(f"{name:>20} {minutes:8.1f} {r['frames']:8d} {r['peak_mb']:9.0f} {r['wall_s']:8.1f}", flush=True)


if __name__ == "__main__":
    main()
