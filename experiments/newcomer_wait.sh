#!/usr/bin/env bash
# The newcomer's wait: a fresh clone of this checkout, then README command 1
# (a new virtual environment, `pip install -e ".[test]"`, `jaxtalk demo`), each phase timed.
# Run on an otherwise idle machine. Writes the demo's log and a JSON of the phase times to
# $OUT (default experiments/results/newcomer_wait).
#   bash experiments/newcomer_wait.sh
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
out=${OUT:-$here/experiments/results/newcomer_wait}
mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
t0=$(date +%s.%N)
git clone -q "$here" "$work/jaxtalk"
cd "$work/jaxtalk"
t1=$(date +%s.%N)
python3 -m venv .venv && . .venv/bin/activate && pip install -q -e ".[test]" 2>/dev/null
t2=$(date +%s.%N)
jaxtalk demo --no-progress | tee "$out/demo.log"
t3=$(date +%s.%N)
python3 - "$out/times.json" "$t0" "$t1" "$t2" "$t3" "$(git rev-parse HEAD)" <<'PY'
import json, platform, sys
path, t0, t1, t2, t3, commit = sys.argv[1], *map(float, sys.argv[2:6]), sys.argv[6]
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), platform.processor())
times = {"clone_s": t1 - t0, "install_s": t2 - t1, "demo_s": t3 - t2, "total_s": t3 - t0}
json.dump({"commit": commit, "machine": cpu, **times}, open(path, "w"), indent=1)
print(json.dumps(times))
PY
