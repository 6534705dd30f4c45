"""TIMAR Table 1 on SynthTalk: conversational metrics vs context history n in {0, 1, 3, 7}.

Trains a TIMAR model on the SynthTalk conversations with TIMAR's recipe (``timar_common.train_model``:
both role assignments of every train conversation, 8-turn windows, on the prepared corpus), then
streams every test and out-of-distribution conversation turn by turn with n previous turns of context
(past agent motion masked, window sliding once full) and
reports FD, P-FD, MSE, SID, rPCC per group (exp / jaw / pose) next to a mean-pose baseline (the
training mean, every frame) and the oracle (the generator's deterministic part), for samples (5-step
DDIM, the paper's sampling) and the model's point estimate (the guided posterior mean,
``sampler="mean"``). Paper claim checked: more context
improves FD and MSE. ``--load-model`` recomputes the table from a saved model without training.

Usage: ``python experiments/timar_context.py [--size small] [--steps 2000] [--out ...]``
(``--size tiny --steps 100 --batch 4`` for a smoke run: the tiny corpus has 6 training windows;
``--load-model experiments/results/timar_context_model.pkl`` to re-evaluate).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models.timar.data import conversations

from timar_common import (  # noqa: E402
    KEYS, add_training_args, context_sensitivity, load_corpus, load_model, metrics, model_config, predict, save_model,
    train_model,
)

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_training_args(ap)
    ap.add_argument("--cfg-scale", type=float, default=0.5, help="guidance weight w (the paper's omega - 1)")
    ap.add_argument("--contexts", default="0,1,3,7")
    ap.add_argument("--modes", default="sample,mean",
                    help="sample = 5-step DDIM samples (the paper); mean = the guided posterior mean (point estimate)")
    ap.add_argument("--out", default="experiments/results/timar_context.json")
    ap.add_argument("--model-out", default="experiments/results/timar_context_model.pkl")
    ap.add_argument("--load-model", default=None, help="evaluate this saved model instead of training one")
    ap.add_argument("--ckpt-dir", default=None, help="checkpoint directory: training resumes from it")
    ap.add_argument("--train-only", action="store_true", help="save the model and stop (evaluate later with --load-model)")
    ap.add_argument("--splits", default="test,ood", help="splits to evaluate")
    ap.add_argument("--merge", action="store_true",
                    help="keep the other splits' results already in --out (evaluate splits in separate runs)")
    ap.add_argument("--max-steps", type=int, default=None,
                    help="stop (checkpointed, no evaluation) at this step of the --steps schedule; rerun to resume")
    args = ap.parse_args()

    corpus = load_corpus(args)
    train_s, final_loss, history = None, None, []
    if args.load_model:
        config, params, norm = load_model(args.load_model)
    else:
        config = model_config(args)
        print(f"training on 8-turn windows: {config}")
        t0 = time.perf_counter()
        ckpt_dir = Path(args.ckpt_dir).resolve() if args.ckpt_dir else None
        result, norm, num_windows = train_model(args, config, ckpt_dir=ckpt_dir, max_steps=args.max_steps,
                                                  seed=args.seed)
        train_s = time.perf_counter() - t0
        print(f"trained on {num_windows} windows of 8 turns")
        # This run's steps only (a resumed run starts its history at the checkpoint).
        logged = [h for h in result.history if "loss" in h]
        history = [{"step": int(h["step"]), "loss": float(h["loss"])} for h in logged[:: max(1, len(logged) // 50)]]
        final_loss = float(logged[-1]["loss"]) if logged else None
        if int(result.state.step) < args.steps:
            print(f"stopped at step {int(result.state.step)} of {args.steps} after {train_s:.0f} s "
                  f"(last loss {final_loss}); rerun with the same --ckpt-dir to resume")
            return
        params = result.state.eval_params
        save_model(args.model_out, config, params, norm)
        if args.train_only:
            print(f"trained to step {args.steps} (this run {train_s:.0f} s, last loss {final_loss}); saved {args.model_out}")
            return

    modes = [v for v in args.modes.split(",") if v]
    splits = [v for v in args.splits.split(",") if v]
    previous = json.loads(Path(args.out).read_text()) if args.merge and Path(args.out).is_file() else {}
    rows, record = [], {k: v for k, v in previous.get("metrics", {}).items() if k not in splits}
    if args.merge and previous.get("args", {}).get("load_model") != args.load_model:
        raise SystemExit(f"--merge: {args.out} holds results of another model ({previous.get('args', {}).get('load_model')})")
    for split in splits:
        convs = conversations(corpus, split)
        gts = [c.agent_motion for c in convs]
        base = metrics([np.broadcast_to(norm.motion_mean, g.shape) + 0 * g for g in gts], convs, corpus)
        oracle = metrics([c.agent_oracle for c in convs], convs, corpus)
        # With --merge, rows of other modes already measured on this split are kept.
        record[split] = {**previous.get("metrics", {}).get(split, {}), "mean_pose": base, "oracle": oracle}
        rows.append({"split": split, "method": "mean pose", **{k: base.get(k) for k in KEYS}})
        for mode in modes:
            for n in (int(v) for v in args.contexts.split(",")):
                preds = predict(config, params, norm, convs, context=n, cfg_scale=args.cfg_scale,
                                sampler="ddim" if mode == "sample" else "mean")
                m = metrics(preds, convs, corpus)
                record[split][f"timar_n{n}_{mode}"] = m
                rows.append({"split": split, "method": f"TIMAR n={n} {mode}", **{k: m.get(k) for k in KEYS}})
        rows.append({"split": split, "method": "oracle", **{k: oracle.get(k) for k in KEYS}})
    trained = f"trained {args.steps} steps in {train_s:.0f} s" if train_s is not None else f"loaded {args.load_model}"
    print_table(rows, f"TIMAR on SynthTalk-{args.size} (published scaling; {trained})")
    claim = {}
    for split in record:
        # Every mode measured on the split (with --merge, also those of earlier runs).
        for mode in sorted({k.split("_", 2)[2] for k in record[split] if k.startswith("timar_n")}):
            ns = [k for k in record[split] if k.startswith("timar_n") and k.endswith(f"_{mode}")]
            if not ns:
                continue
            first, last = record[split][ns[0]], record[split][ns[-1]]
            claim[f"{split}_{mode}"] = {
                f"{key}_decreases_with_n": bool(last[key] < first[key])
                for key in ("FD_exp", "MSE_exp", "FD_pose", "MSE_pose", "MSE_mouth_spk")
            } | {
                f"{key}_beats_mean_pose_at_{ns[-1].split('_')[1]}": bool(last[key] < record[split]["mean_pose"][key])
                for key in ("FD_exp", "MSE_exp")
            }
    print("paper claim (more context improves FD and MSE):", claim)
    sensitivity = previous.get("sensitivity")
    if "test" in splits or sensitivity is None:
        sensitivity = context_sensitivity(config, params, norm, conversations(corpus, "test"), cfg_scale=args.cfg_scale)
        print("sensitivity of the last turn's point estimate (RMS change, normalised units):", sensitivity)
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "runs": previous.get("runs", []) + [vars(args)],
                          "train_s": train_s, "final_loss": final_loss,
                          "config": dataclasses.asdict(config), "history": history, "metrics": record, "claim": claim,
                          "sensitivity": sensitivity})


if __name__ == "__main__":
    main()
