"""FreeTalk supplement Table 2 on SynthTalk: STM feature-combination ablation (LVE).

Variants (``STMConfig.fusion``): Concat (``[f_i | g_t]``), CA (``[f_i | c_t,i]`` with landmark
features from the raw displacements and the index encoding), CA + Concat, and GCN + CA + Concat (the
paper's model). Each is trained the same way as in ``freetalk_topology.py`` (STM's recipe) on the seen meshes and
evaluated on seen and held-out meshes of SynthTalk test clips (ground-truth landmarks in).

All variants get the same budget (``--steps``, same data, seed and optimiser). On a slow CPU run
them in several invocations with ``--fusions``: rows from earlier runs with the same settings are
kept in the JSON and the table.

Usage: python experiments/freetalk_stm_ablation.py [--size tiny|small] [--steps N] [--batch N] [--fusions ...]
       [--cache DIR] [--out PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.models.freetalk import data
from jaxtalk.models.freetalk.config import FUSIONS, STMConfig
from jaxtalk.models.freetalk.recipe import STMWindows

sys.path.insert(0, str(Path(__file__).resolve().parent))
from freetalk_topology import HELD_OUT, SEEN, evaluate_mesh, load_data, train_stm  # noqa: E402

NAMES = {"concat": "Concat.", "ca": "CA", "ca_concat": "CA + Concat.", "gcn_ca_concat": "GCN + CA + Concat. (ours)"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="tiny")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--batch", type=int, default=4, help="16-frame windows per step")
    parser.add_argument("--resolution", default="low")
    parser.add_argument("--test-clips", type=int, default=4)
    parser.add_argument("--cache", type=Path, default=Path(".cache/prepared"),
                        help="SynthTalk and its prepared copy (the default is jaxtalk train's)")
    parser.add_argument("--fusions", nargs="+", default=list(FUSIONS), choices=FUSIONS,
                        help="variants to run (split the table over several runs on a slow CPU)")
    parser.add_argument("--out", type=Path, default=Path("experiments/results/freetalk_stm_ablation.json"))
    args = parser.parse_args()
    corpus, prepared = load_data(args.size, args.cache)
    seen = [data.face_mesh(i, k, resolution=args.resolution) for i, k in SEEN]
    held = [data.face_mesh(i, k, resolution=args.resolution) for i, k in HELD_OUT]
    clips = corpus.split("test")[: args.test_clips]
    # The window is the recipe's (rows of the earlier in-memory training, 8-frame windows, are not kept).
    settings = {"size": args.size, "steps": args.steps, "batch": args.batch, "resolution": args.resolution,
                "window": STMWindows.window, "test_clips": args.test_clips}
    # Variants run in several invocations (one budget each) are merged into one table when the
    # settings match; a variant run again replaces its earlier row.
    earlier = json.loads(args.out.read_text()) if args.out.exists() else {}
    kept = [r for r in earlier.get("rows", []) if earlier.get("settings") == settings]
    rows = [r for r in kept if r["fusion"] not in {NAMES[f] for f in args.fusions}]
    for fusion in args.fusions:
        t0 = time.time()
        cfg = dataclasses.replace(STMConfig.small(), fusion=fusion)
        params, means = train_stm(prepared, corpus, cfg, SEEN, args.steps, resolution=args.resolution,
                                  batch_size=args.batch)
        lve = {"seen": [], "held-out": []}
        for i, m in enumerate(seen):
            lve["seen"].append(evaluate_mesh(corpus, cfg, params, m, means[i], clips)["model"]["LVE_mm2"])
        for m in held:  # only the model's LVE is used: the mean-pose column gets a zero placeholder
            lve["held-out"].append(evaluate_mesh(corpus, cfg, params, m, np.zeros_like(m.vertices), clips)["model"]["LVE_mm2"])
        rows.append({"fusion": NAMES[fusion], "LVE_seen_mm2": float(np.mean(lve["seen"])),
                     "LVE_held_out_mm2": float(np.mean(lve["held-out"])), "train_s": time.time() - t0})
        print(rows[-1], flush=True)
    order = list(NAMES.values())
    rows.sort(key=lambda r: order.index(r["fusion"]))
    bm.print_table(rows, f"STM feature combination (SynthTalk {args.size}, {args.steps} steps each, LVE in mm^2)")
    print(f"wrote {bm.write_json(args.out, {'rows': rows, 'settings': settings})}")


if __name__ == "__main__":
    main()
