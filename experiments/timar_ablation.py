"""TIMAR Table 2 / Fig. 5 on SynthTalk: diffusion vs MLP head, turn-causal vs bidirectional attention,
and a CFG-scale sweep (FD and P-FD vs omega; omega is traced, so every scale reuses one compiled
streaming step).

Each variant is trained with the same data, steps and seed as the default model, then streamed with
n = 7 turns of context on the test split. The bidirectional variant is evaluated by recomputing the
window every turn (it cannot be cached), which is what the paper's "w/ Bi-Attention" row measures.

Usage: ``python experiments/timar_ablation.py [--size small] [--steps 2000] [--out ...]``
"""

from __future__ import annotations

import argparse
import dataclasses

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.data.synthtalk import generate
from jaxtalk.models.timar.data import conversations
from jaxtalk.models.timar.train import train_timar

from timar_common import KEYS, add_training_args, metrics, predict, training_setup  # noqa: E402  (sibling script)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_training_args(ap)
    ap.add_argument("--context", type=int, default=7)
    ap.add_argument("--scales", default="0,0.5,1,1.5,2,3")
    ap.add_argument("--eval-convs", type=int, default=None, help="evaluate on the first N test conversations only")
    ap.add_argument("--out", default="experiments/results/timar_ablation.json")
    args = ap.parse_args()

    corpus = generate(args.size, 0, cache_dir=args.cache_dir)
    test_convs = conversations(corpus, "test")[: args.eval_convs]
    config, norm, data = training_setup(args, corpus)
    variants = {
        "diffusion head + TLCA (default)": config,
        "MLP head": dataclasses.replace(config, head="mlp"),
        "bidirectional attention": dataclasses.replace(config, attention="bidirectional"),
        "paper mask ratio (r ~ TN[0.7, 1])": dataclasses.replace(config, mask_ratio_min=0.7),
    }
    rows, record, trained = [], {}, {}
    for name, cfg in variants.items():
        res = train_timar(cfg, data, steps=args.steps, batch_size=args.batch, lr=args.lr, progress=True)
        trained[name] = (cfg, res.state.eval_params)
        m = metrics(predict(cfg, res.state.eval_params, norm, test_convs, context=args.context, cfg_scale=1.5), test_convs, corpus)
        record[name] = m
        rows.append({"variant": name, **{k: m.get(k) for k in KEYS}})
    print_table(rows, f"TIMAR ablations on SynthTalk-{args.size} test (n={args.context}, published scaling)")

    cfg, params = trained["diffusion head + TLCA (default)"]
    sweep = []
    for w in (float(v) for v in args.scales.split(",")):
        m = metrics(predict(cfg, params, norm, test_convs, context=args.context, cfg_scale=w), test_convs, corpus)
        sweep.append({"omega": w, "FD_exp": m["FD_exp"], "P-FD_exp": m["P-FD_exp"], "FD_jaw": m["FD_jaw"],
                      "P-FD_jaw": m["P-FD_jaw"], "MSE_exp": m["MSE_exp"], "MSE_mouth_spk": m["MSE_mouth_spk"]})
    print_table(sweep, "CFG scale sweep (paper's omega: 0 = unconditional, 1 = conditional)")
    best = min(sweep, key=lambda r: r["FD_exp"])
    print(f"best omega by FD_exp: {best['omega']} (paper: guidance above 1 improves FD and P-FD)")
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "variants": record, "cfg_sweep": sweep,
                          "best_omega_fd_exp": best["omega"]})


if __name__ == "__main__":
    main()
