"""Peak memory of offline sampling on long inputs (issue 32): whole-sequence vs bounded.

Every row runs in a fresh subprocess and reports its peak resident set size (``ru_maxrss``) and wall
time. TokTalk's ``sample`` holds O(frames^2) attention (a 20-minute clip asked for 45 GB on the
paper preset); ``sample_long`` (what ``jaxtalk sample`` runs) works on minute-long windows. The
whole-sequence rows stop at lengths a CPU can hold; the bounded rows go to an hour.

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
    from jaxtalk.models import toktalk as tt
    method, preset, minutes = sys.argv[1], sys.argv[2], float(sys.argv[3])
    cfg = getattr(tt.TokTalkConfig, preset)()
    params = tt.init_params(cfg, jax.random.key(0))
    tokens = np.random.default_rng(0).normal(size=(1, int(minutes * 60 * cfg.token_rate), cfg.token_dim)).astype(np.float32)
    style = np.zeros((1, cfg.style_vector_dim), np.float32)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    fn = tt.sample if method == "whole" else tt.sample_long
    out = np.asarray(fn(params, cfg, tokens, style, jax.random.key(1)))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"frames": out.shape[1], "base_mb": base / 1024, "peak_mb": peak / 1024,
                      "wall_s": time.perf_counter() - t0}))
''')


def run_row(method: str, preset: str, minutes: float) -> dict:
    """One measurement in a fresh process: ``{"frames", "base_mb", "peak_mb", "wall_s"}``."""
    proc = subprocess.run([sys.executable, "-c", WORKER, method, preset, str(minutes)], capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only rows of at most 10 minutes")
    parser.add_argument("--preset", default="tiny")
    args = parser.parse_args()
    rows = [("whole", 2.5), ("whole", 5.0), ("long", 2.5), ("long", 10.0)]
    if not args.quick:
        rows += [("long", 60.0)]
    print(f"TokTalk {args.preset}: peak RSS of offline sampling (fresh process per row)")
    print(f"{'method':>12} {'minutes':>8} {'frames':>8} {'peak MB':>9} {'wall s':>8}")
    for method, minutes in rows:
        r = run_row(method, args.preset, minutes)
        name = "sample" if method == "whole" else "sample_long"
        if "error" in r:
            print(f"{name:>12} {minutes:8.1f}  failed: {r['error']}")
        else:
            print(f"{name:>12} {minutes:8.1f} {r['frames']:8d} {r['peak_mb']:9.0f} {r['wall_s']:8.1f}", flush=True)


if __name__ == "__main__":
    main()
