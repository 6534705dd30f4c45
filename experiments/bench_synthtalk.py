"""SynthTalk generation speed and calibration against real FLAME tracks.

Speed: CPU seconds (process time, all threads) and wall seconds to make one minute of corpus, split
into planning + audio + motion, token encoding (two streams, tokenizers already fitted, kernels
already compiled) and landmarks (compiled). Target: < 1 CPU second per minute.
Calibration: per-dimension expression std, jaw-opening range, neck std and expression velocity std
of the tiny corpus beside the two real DualTalk demo tracks (``shared/data/dualtalk_demo``).

Run: ``python experiments/bench_synthtalk.py [--out experiments/results/bench_synthtalk.json]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import time
from pathlib import Path

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.data import synthtalk

REAL = "/work/shared/data/dualtalk_demo/*.npz"


def _timed(fn):
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c0, time.perf_counter() - w0


def speed(seed: int = 0) -> list[dict]:
    # About a minute of monologues and one conversation, rendered eagerly.
    spec = dataclasses.replace(synthtalk.SIZES["tiny"], speakers=(4, 0, 0, 0), clips_per_speaker=2,
                               clip_seconds=5.0, conversations=(1, 0, 0, 0), conversation_seconds=10.0)
    warm = synthtalk.generate(spec, seed=seed + 1)  # warm caches (filter designs, imports)
    for s in synthtalk.TOKEN_STREAMS:
        for i in range(len(warm)):
            warm.tokens(i, s)  # fits tokenizers, compiles the token kernels for these lengths
        warm.landmarks(0)
    corpus, cpu_gen, wall_gen = _timed(lambda: synthtalk.generate(spec, seed=seed))
    minutes = sum(c.seconds for c in corpus.clips) / 60.0
    # Reuse the fitted tokenizers so only encoding is timed (fitting is a one-off per corpus).
    corpus._tokenizers = dict(warm._tokenizers)
    for s in synthtalk.TOKEN_STREAMS:  # compile for this corpus's clip lengths too
        for i in range(len(corpus)):
            corpus.tokenizer(s).encode(corpus.audio(i))
    corpus._tokens.clear()
    _, cpu_tok, wall_tok = _timed(lambda: [corpus.tokens(i, s) for s in synthtalk.TOKEN_STREAMS
                                           for i in range(len(corpus))])
    [corpus.landmarks(i) for i in range(len(corpus))]
    _, cpu_lm, wall_lm = _timed(lambda: [corpus.landmarks(i) for i in range(len(corpus))])
    rows = [
        {"stage": "plan + audio + motion", "cpu_s_per_min": cpu_gen / minutes, "wall_s_per_min": wall_gen / minutes},
        {"stage": "tokens A+B (encode)", "cpu_s_per_min": cpu_tok / minutes, "wall_s_per_min": wall_tok / minutes},
        {"stage": "landmarks (identity 0)", "cpu_s_per_min": cpu_lm / minutes, "wall_s_per_min": wall_lm / minutes},
    ]
    rows.append({"stage": "total", "cpu_s_per_min": sum(r["cpu_s_per_min"] for r in rows),
                 "wall_s_per_min": sum(r["wall_s_per_min"] for r in rows)})
    for r in rows:
        r["minutes"] = minutes
    return rows


def stats(tracks: list[np.ndarray]) -> dict:
    """Calibration statistics of a list of (T, 56) tracks [exp 50 | jaw 3 | neck 3]."""
    m = np.concatenate(tracks)
    vel = np.concatenate([np.diff(t[:, :50], axis=0) for t in tracks])
    exp_std = m[:, :50].std(0)
    return {
        "frames": int(m.shape[0]),
        "exp_std_min": float(exp_std.min()), "exp_std_median": float(np.median(exp_std)),
        "exp_std_max": float(exp_std.max()),
        "jaw_open_min": float(m[:, 50].min()), "jaw_open_max": float(m[:, 50].max()),
        "neck_std_min": float(m[:, 53:].std(0).min()), "neck_std_max": float(m[:, 53:].std(0).max()),
        "exp_vel_std": float(vel.std()), "exp_vel_std_dim_min": float(vel.std(0).min()),
        "exp_vel_std_dim_max": float(vel.std(0).max()),
    }


def calibration() -> list[dict]:
    corpus = synthtalk.generate("tiny", seed=0)
    rows = [{"source": "SynthTalk tiny", **stats([corpus.motion(i) for i in range(len(corpus))])}]
    for path in sorted(glob.glob(REAL)):
        z = np.load(path)
        track = np.concatenate([z["exp"], z["pose"][:, 3:], z["pose"][:, :3]], axis=1)
        rows.append({"source": Path(path).stem[:28], **stats([track])})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="experiments/results/bench_synthtalk.json")
    args = parser.parse_args()
    speed_rows = speed()
    print_table(speed_rows, "SynthTalk: seconds to generate one minute of corpus")
    cal_rows = calibration()
    print_table(cal_rows, "Calibration: SynthTalk tiny vs real DualTalk FLAME tracks")
    path = write_json(args.out, {"machine": machine_info(), "speed": speed_rows, "calibration": cal_rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
