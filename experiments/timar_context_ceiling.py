"""How much can context help on SynthTalk? The true-event ceiling for TIMAR's context claim.

``jaxtalk.data.synthtalk.ceiling.context_ceiling``: a ridge regression on the generator's TRUE causes of
the agent's within-conversation motion that lie inside a window of the current turn plus k past
turns (the user's head movement at the agent's mimicry lag and the user's turn ends for the neck; the
shared mood as the window's voices determine it for the upper face), scored by held-out R^2 on the
test conversations, both roles of each. The gain from k = 0 to 7 bounds what a model's history of
past turns can add on this corpus. Motion only: no audio is synthesised, so the full corpus takes
about a minute.

``--effects off`` measures the same corpus with its dyadic effects (mimicry, shared mood) turned off:
the control that shows what the ceiling is without them.

Usage: python experiments/timar_context_ceiling.py [--size full] [--effects default|off] [--out PATH]
"""

from __future__ import annotations

import argparse
import dataclasses

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.data.synthtalk import DEFAULT_EFFECTS, generate
from jaxtalk.data.synthtalk.corpus import SIZES
from jaxtalk.data.synthtalk.dyadic import DyadicEffects
from jaxtalk.data.synthtalk.ceiling import context_ceiling


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="full")
    ap.add_argument("--effects", default="default", choices=("default", "off"))
    ap.add_argument("--out", default=None, help="default: experiments/results/timar_context_ceiling[_off].json")
    args = ap.parse_args()
    effects = DEFAULT_EFFECTS if args.effects == "default" else DyadicEffects(mimicry=0.0, mood=0.0)
    out = args.out or f"experiments/results/timar_context_ceiling{'_off' if args.effects == 'off' else ''}.json"
    size = args.size if args.effects == "default" else dataclasses.replace(SIZES[args.size], effects=effects)
    corpus = generate(size, 0) if args.size == "full" else generate(size, 0, cache_dir=".cache/synthtalk")

    def sides(split):
        return [s for a, b in corpus.conversations(split) for s in ((a, b), (b, a))]

    train, test = sides("train"), sides("test")
    rows = []
    for k in (0, 1, 3, 7, 1000):
        r2 = context_ceiling(corpus, train, test, k)
        rows.append({"past_turns": "all" if k == 1000 else k, "neck_R2": r2["neck"], "upper_face_R2": r2["upper_face"]})
    print_table(rows, f"True-event ceiling on the agent's motion (SynthTalk-{args.size}, {len(train)} train / "
                      f"{len(test)} test conversation sides; effects {effects})")
    write_json(out, {"machine": machine_info(), "args": vars(args), "effects": str(effects), "rows": rows})


if __name__ == "__main__":
    main()
