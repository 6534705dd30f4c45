"""TIMAR Table 1 on SynthTalk: conversational metrics vs context history n in {0, 1, 3, 7}.

Trains a TIMAR model on the SynthTalk conversations (both role assignments of every train
conversation, 8-turn windows), then streams every test and out-of-distribution conversation turn by
turn with n previous turns of context (past agent motion masked, window sliding once full) and
reports FD, P-FD, MSE, SID, rPCC per group (exp / jaw / pose) next to a mean-pose baseline (the
training mean, every frame) and the oracle (the generator's deterministic part). Paper claim checked:
more context improves FD and MSE.

Usage: ``python experiments/timar_context.py [--size small] [--steps 2000] [--out ...]``
(``--size tiny --steps 100`` for a smoke run).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.data.synthtalk import generate
from jaxtalk.models.timar.data import conversations
from jaxtalk.models.timar.train import train_timar

from timar_common import KEYS, add_training_args, metrics, predict, save_model, training_setup  # noqa: E402

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_training_args(ap)
    ap.add_argument("--cfg-scale", type=float, default=1.5)
    ap.add_argument("--contexts", default="0,1,3,7")
    ap.add_argument("--out", default="experiments/results/timar_context.json")
    ap.add_argument("--model-out", default="experiments/results/timar_context_model.pkl")
    args = ap.parse_args()

    corpus = generate(args.size, 0, cache_dir=args.cache_dir)
    config, norm, data = training_setup(args, corpus)
    t0 = time.perf_counter()
    result = train_timar(config, data, steps=args.steps, batch_size=args.batch, lr=args.lr, progress=True)
    train_s = time.perf_counter() - t0
    params = result.state.eval_params
    save_model(args.model_out, config, params, norm)

    rows, record = [], {}
    for split in ("test", "ood"):
        convs = conversations(corpus, split)
        gts = [c.agent_motion for c in convs]
        base = metrics([np.broadcast_to(norm.motion_mean, g.shape) + 0 * g for g in gts], convs, corpus)
        oracle = metrics([c.agent_oracle for c in convs], convs, corpus)
        record[split] = {"mean_pose": base, "oracle": oracle}
        rows.append({"split": split, "method": "mean pose", **{k: base.get(k) for k in KEYS}})
        for n in (int(v) for v in args.contexts.split(",")):
            m = metrics(predict(config, params, norm, convs, context=n, cfg_scale=args.cfg_scale), convs, corpus)
            record[split][f"timar_n{n}"] = m
            rows.append({"split": split, "method": f"TIMAR n={n}", **{k: m.get(k) for k in KEYS}})
        rows.append({"split": split, "method": "oracle", **{k: oracle.get(k) for k in KEYS}})
    print_table(rows, f"TIMAR on SynthTalk-{args.size} (published scaling; trained {args.steps} steps in {train_s:.0f} s)")
    claim = {}
    for split in ("test", "ood"):
        ns = [k for k in record[split] if k.startswith("timar_n")]
        fd = [record[split][k]["FD_exp"] for k in ns]
        mse = [record[split][k]["MSE_exp"] for k in ns]
        mouth = [record[split][k]["MSE_mouth_spk"] for k in ns]
        claim[split] = {"FD_exp_decreases_with_n": bool(fd[-1] < fd[0]), "MSE_exp_decreases_with_n": bool(mse[-1] < mse[0]),
                        "MSE_mouth_spk_decreases_with_n": bool(mouth[-1] < mouth[0])}
    print("paper claim (more context improves FD and MSE):", claim)
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "train_s": train_s,
                          "final_loss": result.history[-1]["loss"], "metrics": record, "claim": claim})


if __name__ == "__main__":
    main()
