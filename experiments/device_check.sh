#!/usr/bin/env bash
# The accelerator check, on whatever device JAX finds (GPU, TPU, or the CPU):
#   1. `jaxtalk bench --paper --train`: every model's train step (small and paper) and the sampling
#      tables, with the float32 matmul peak measured on the device;
#   2. a 2-minute TIMAR `paper` training (steps/s after the first, compiled, step);
#   3. TokTalk `paper` streaming chunks (the paper's figure to beat: 101 ms per 0.4-s chunk at
#      10 Euler steps + CFG on an L40S).
# Writes JSON (machine, device, date and command in each) under experiments/results/device_check/
# (or $OUT). Usage, inside the project's environment with the accelerator's jax installed:
#   bash experiments/device_check.sh
set -euo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-experiments/results/device_check}
mkdir -p "$out"
python -c "import jax; print('devices:', jax.devices())"
jaxtalk bench --paper --train --out "$out/bench.json"
python experiments/device_check.py timar-train --seconds 120 --out "$out/timar_paper_train.json"
python experiments/device_check.py toktalk-stream --out "$out/toktalk_paper_stream.json"
python experiments/bench_readme.py "$out/bench.json" > "$out/performance.md"
echo "results in $out"
