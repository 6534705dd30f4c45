"""How much can context help on SynthTalk? The true-event ceiling for TIMAR's context claim.

``jaxtalk.data.synthtalk.ceiling.context_ceiling``: a ridge regression on the generator's TRUE causes of
the agent's within-conversation motion that lie inside a window of the current turn plus k past
turns (the user's head movement at the agent's mimicry lag and the user's turn ends for the neck; the
shared mood as the window's voices determine it for the upper face), scored by held-out R^2 on the
test conversations, both roles of each. The gain from k = 0 to 7 bounds what a model's history of
past turns can add on this corpus. Motion only: no audio is synthesised, so the full corpus takes
about a minute.

Usage: python experiments/timar_context_ceiling.py [--size full] [--out PATH]
"""

from __future__ import annotations

import argparse

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.data.synthtalk import DEFAULT_EFFECTS, generate
from jaxtalk.data.synthtalk.ceiling import context_ceiling


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="full")
    ap.add_argument("--out", default="experiments/results/timar_context_ceiling.json")
    args = ap.parse_args()
    corpus = generate(args.size, 0) if args.size == "full" else generate(args.size, 0, cache_dir=".cache/synthtalk")

    def sides(split):
        return [s for a, b in corpus.conversations(split) for s in ((a, b), (b, a))]

    train, test = sides("train"), sides("test")
    rows = []
    for k in (0, 1, 3, 7, 1000):
        r2 = context_ceiling(corpus, train, test, k)
        rows.append({"past_turns": "all" if k == 1000 else k, "neck_R2": r2["neck"], "upper_face_R2": r2["upper_face"]})
    print_table(rows, f"True-event ceiling on the agent's motion (SynthTalk-{args.size}, {len(train)} train / "
                      f"{len(test)} test conversation sides; effects {DEFAULT_EFFECTS})")
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "effects": str(DEFAULT_EFFECTS), "rows": rows})


if __name__ == "__main__":
    main()
