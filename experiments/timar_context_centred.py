"""TIMAR's context gain on the part of the motion context can explain: each side's prediction and truth
centred on their own means (a per-speaker rest pose, which neither the user's motion nor the speech
reveals, is left out, as in ``timar_context_control.py``'s probe), scored as pooled R^2 per group
(neck, upper face) at n = 0, 1, 3, 7 turns of context, for the guided posterior mean.

Usage: python experiments/timar_context_centred.py MODEL.pkl [--size small] [--effects mimicry_1.2] [--out PATH]
"""

from __future__ import annotations

import argparse

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models.timar.data import conversations

from timar_common import EFFECTS, load_corpus, load_model, predict  # noqa: E402
from timar_context_control import GROUP_CHANNELS  # noqa: E402


def centred_r2(preds: list[np.ndarray], truths: list[np.ndarray], channels: np.ndarray) -> float:
    """Pooled ``1 - SSE / SST`` of each side's centred prediction against its centred truth."""
    sse = sst = 0.0
    for p, t in zip(preds, truths):
        n = min(len(p), len(t))
        p, t = p[:n, channels].astype(np.float64), t[:n, channels].astype(np.float64)
        p, t = p - p.mean(0), t - t.mean(0)
        sse += float(np.sum((t - p) ** 2))
        sst += float(np.sum(t**2))
    return 1.0 - sse / sst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--size", default="small")
    ap.add_argument("--effects", default="default", choices=sorted(EFFECTS))
    ap.add_argument("--cache-dir", default=".cache/prepared")
    ap.add_argument("--cfg-scale", type=float, default=1.5)
    ap.add_argument("--splits", default="test,ood")
    ap.add_argument("--out", default="experiments/results/timar_context_centred.json")
    args = ap.parse_args()
    corpus = load_corpus(args)
    config, params, norm = load_model(args.model)
    rows = []
    for split in args.splits.split(","):
        convs = conversations(corpus, split)
        truths = [c.agent_motion for c in convs]
        for n in (0, 1, 3, 7):
            preds = predict(config, params, norm, convs, context=n, cfg_scale=args.cfg_scale, sampler="mean")
            rows.append({"split": split, "context": n,
                         **{f"R2_{g}": centred_r2(preds, truths, ch) for g, ch in GROUP_CHANNELS.items()}})
            print(rows[-1], flush=True)
    print_table(rows, f"TIMAR's centred R^2 (guided posterior mean) on SynthTalk-{args.size}, effects {args.effects}")
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "rows": rows})


if __name__ == "__main__":
    main()
