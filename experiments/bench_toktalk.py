"""TokTalk speed: per-chunk streaming latency, FLOPs and achieved FLOP/s; latency vs utterance length.

Cases (10 Euler steps on the cosine grid, CFG = conditional + unconditional as one batch of 2):
* ``small`` preset, 0.4 s chunk (10 frames) with its 20-frame left context: real-time factor
  (latency / chunk duration), target <= 0.25.
* ``paper`` preset (about 82M decoder parameters): a 10-frame window (chunk only) and a 50-frame
  window (chunk + 40 context frames); the PyTorch reference takes 1.11 s and 1.73 s on this CPU,
  target <= 0.45 s and <= 1.1 s. FLOPs from XLA's cost analysis of one CFG velocity evaluation
  times the number of steps (XLA counts a scan body once).
* The causal decoder's cost per chunk next to the offline decoder's on the same window (the offline
  model may not stream; its window is timed outside the engine, as is the causal one's in that table).
* Latency of chunk 2 vs chunk 50 of one stream (the fixed window keeps them equal; the reference
  recomputes the whole prefix).

Weights are random (speed does not depend on them). The measuring code lives in ``jaxtalk.bench``
(shared with ``jaxtalk bench``).

Usage: ``python experiments/bench_toktalk.py [--skip-paper] [--out experiments/results/bench_toktalk.json]``
"""

from __future__ import annotations

import argparse

from jaxtalk.bench import toktalk_chunk, toktalk_growth, toktalk_window, with_peak
from jaxtalk.benchmarking import machine_info, measure_matmul_peak, measure_memory_bandwidth, print_table, write_json
from jaxtalk.models.toktalk import TokTalkConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-paper", action="store_true")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", default="experiments/results/bench_toktalk.json")
    args = parser.parse_args()
    few = max(3, args.repeats // 3)
    rows = [toktalk_chunk(TokTalkConfig.small(), "small, chunk 0.4 s", args.repeats)]
    if not args.skip_paper:
        rows.append(toktalk_chunk(TokTalkConfig.paper(context_frames=0, overlap_frames=0), "paper, 10 frames", few))
        rows.append(toktalk_chunk(TokTalkConfig.paper(context_frames=40), "paper, 50 frames", few))
    peak, bandwidth = measure_matmul_peak() / 1e9, measure_memory_bandwidth() / 1e9
    rows = with_peak(rows, peak, bandwidth)
    print_table(rows, f"TokTalk per-chunk latency (Euler steps + CFG); matmul peak {peak:.0f} GFLOP/s")
    decoders = [toktalk_window(TokTalkConfig.small(causal=c), "small, chunk 0.4 s", args.repeats) for c in (True, False)]
    print_table(decoders, "one chunk's sampler on the streaming window: the causal decoder vs the offline one")
    growth = toktalk_growth(TokTalkConfig.small(), 50, args.repeats)
    print_table([growth], "small preset: per-chunk latency at chunk 2 vs chunk 50 (target ratio <= 1.10)")
    write_json(args.out, {"machine": machine_info(), "matmul_peak_gflop_s": peak, "memory_bandwidth_gb_s": bandwidth,
                          "latency": rows, "growth": growth, "decoders": decoders})


if __name__ == "__main__":
    main()
