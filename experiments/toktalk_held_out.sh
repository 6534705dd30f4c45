#!/usr/bin/env bash
# Does the default `jaxtalk train toktalk` on SynthTalk small stay better than the mean pose on held-out
# speakers however long it trains?
#
# For each seed: 6,000 steps of the default recipe with its streamed validation every 500 steps on ALL 20
# val clips (held-out speakers; 1 and `sample_steps` Euler steps at the preset's temperature), then the
# newest and the validation-chosen checkpoints scored on all 20 test clips by `jaxtalk eval`. Runs one
# seed at a time (2 cores); a killed run resumes where it stopped when the script is run again.
#
#   bash experiments/toktalk_held_out.sh [OUT_DIR] [SEEDS...]     # default: runs/held_out, seeds 0 1
#
# Each run folder gets checkpoint/history.jsonl (the validation curve) and test_last.json /
# test_best.json (the eval tables); experiments/results/toktalk_degradation.json collects them.
set -euo pipefail
out=${1:-runs/held_out}
shift || true
seeds=("$@")
[ ${#seeds[@]} -eq 0 ] && seeds=(0 1)
for seed in "${seeds[@]}"; do
  run="$out/seed$seed"
  jaxtalk train toktalk --data synthtalk:small --steps 6000 --seed "$seed" --out "$run" \
    --set eval_every=500 --set val_clips=20
  jaxtalk eval "$run" --split test --max-clips 20 --sample-steps 1,10 --json "$run/test_last.json"
  jaxtalk eval "$run" --best --split test --max-clips 20 --sample-steps 1,10 --json "$run/test_best.json"
done
