"""TIMAR's context gain on the part of the motion context can explain: each side's prediction and truth
centred on their own means (a per-speaker rest pose, which neither the user's motion nor the speech
reveals, is left out, as in ``timar_context_control.py``'s probe), scored as pooled R^2 per group
(neck, upper face) at n = 0, 1, 3, 7 turns of context, for the guided posterior mean, with its two
parts: the correlation and the amplitude ratio (``R2 = 2 a rho - a^2``).

Usage: python experiments/timar_context_centred.py MODEL.pkl [--size small] [--effects mimicry_1.2] [--out PATH]
"""

from __future__ import annotations

import argparse

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models.timar.data import conversations

from timar_common import EFFECTS, load_corpus, load_model, predict  # noqa: E402
from timar_context_control import GROUP_CHANNELS  # noqa: E402


def centred_fit(preds: list[np.ndarray], truths: list[np.ndarray], channels: np.ndarray) -> dict[str, float]:
    """Each side's centred prediction against its centred truth, pooled: ``R2`` (``1 - SSE / SST``),
    and the two things it is made of, ``corr`` (the pooled correlation rho) and ``amp`` (the
    prediction's RMS over the truth's, a): ``R2 = 2 a rho - a^2``, so a negative R^2 says whether the
    prediction moves the wrong way (rho) or too much (a)."""
    spp = spt = stt = 0.0
    for p, t in zip(preds, truths):
        n = min(len(p), len(t))
        p, t = p[:n, channels].astype(np.float64), t[:n, channels].astype(np.float64)
        p, t = p - p.mean(0), t - t.mean(0)
        spp, spt, stt = spp + float(np.sum(p * p)), spt + float(np.sum(p * t)), stt + float(np.sum(t * t))
    return {"R2": 1.0 - (spp - 2 * spt + stt) / stt, "corr": spt / np.sqrt(spp * stt), "amp": np.sqrt(spp / stt)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--size", default="small")
    ap.add_argument("--effects", default="default", choices=sorted(EFFECTS))
    ap.add_argument("--cache-dir", default=".cache/prepared")
    ap.add_argument("--cfg-scale", type=float, default=0.5, help="guidance weight w (the paper's omega - 1)")
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
            fits = {g: centred_fit(preds, truths, ch) for g, ch in GROUP_CHANNELS.items()}
            rows.append({"split": split, "context": n, **{f"{k}_{g}": v for g, fit in fits.items() for k, v in fit.items()}})
            print(rows[-1], flush=True)
    print_table(rows, f"TIMAR's centred R^2 (guided posterior mean) on SynthTalk-{args.size}, effects {args.effects}")
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "rows": rows})


if __name__ == "__main__":
    main()
