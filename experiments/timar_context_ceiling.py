"""How much can context help on SynthTalk? An oracle-feature ceiling for TIMAR's context claim.

SynthTalk's listener nods a lag after the OTHER speaker's phrase ends (``../shared/design/SYNTHTALK.md``). This
probe gives a ridge regression the generator's TRUE phrase-end times of the user (not anything a model
could only estimate) and asks how much of the agent's within-conversation neck pitch they explain on
held-out conversations, when only phrase ends inside the model's window are visible: the current
turn plus ``k`` past turns, k in {0, 1, 3, 7} (and "all"). Features: one indicator per 0.1-s lag bin
(0-3 s) since a visible phrase end, plus a bias; the target is the agent's neck pitch minus its
per-conversation mean (the resting pose is not what context can explain).

If the R^2 barely grows with k, the corpus gives a model little to gain from past turns, whatever it
learns: an upper bound for the TIMAR context table (``timar_context.py``).

Usage: python experiments/timar_context_ceiling.py [--size full] [--cache-dir DIR] [--out PATH]
"""

from __future__ import annotations

import argparse

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.data.synthtalk import generate
from jaxtalk.layout import group_indices
from jaxtalk.models.timar.data import conversations

LAG_BIN_S = 0.1
MAX_LAG_S = 3.0
# First neck channel: axis-angle about the x axis (pitch, i.e. nodding), as the jaw's JAW_OPEN_INDEX.
NECK_PITCH = int(group_indices("neck")[0])


def lag_features(corpus, conv, past_turns: int, frames_per_turn: int = 25, fps: float = 25.0):
    """(T, bins + 1) lag indicators of the visible user phrase ends, and the centred neck pitch (T,)."""
    timeline = corpus.clips[conv.user_clip].timeline
    ends = timeline.phrase_ends[~timeline.backchannel]
    frames = conv.num_frames // frames_per_turn * frames_per_turn
    t = np.arange(frames) / fps
    window_start = (np.arange(frames) // frames_per_turn - past_turns) * frames_per_turn / fps
    bins = int(round(MAX_LAG_S / LAG_BIN_S))
    x = np.zeros((frames, bins + 1))
    x[:, -1] = 1.0
    for end in ends:
        lag = t - end
        visible = (lag >= 0) & (lag < MAX_LAG_S) & (end >= window_start)
        x[visible, (lag[visible] / LAG_BIN_S).astype(int)] = 1.0
    y = conv.agent_motion[:frames, NECK_PITCH]
    return x, y - y.mean()


def ridge_r2(corpus, train, test, past_turns: int, alpha: float = 1.0) -> float:
    """Held-out R^2 of a ridge fit of the centred neck pitch on the lag features."""
    x, y = (np.concatenate(a) for a in zip(*[lag_features(corpus, c, past_turns) for c in train]))
    xt, yt = (np.concatenate(a) for a in zip(*[lag_features(corpus, c, past_turns) for c in test]))
    w = np.linalg.solve(x.T @ x + alpha * np.eye(x.shape[1]), x.T @ y)
    return float(1.0 - np.sum((yt - xt @ w) ** 2) / np.sum(yt**2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="full")
    ap.add_argument("--cache-dir", default=None)
    ap.add_argument("--out", default="experiments/results/timar_context_ceiling.json")
    args = ap.parse_args()
    corpus = generate(args.size, 0, cache_dir=args.cache_dir)
    train, test = conversations(corpus, "train"), conversations(corpus, "test")
    rows = [{"past_turns": k, "neck_pitch_R2_test": ridge_r2(corpus, train, test, k)} for k in (0, 1, 3, 7, 1000)]
    rows[-1]["past_turns"] = "all"
    print_table(rows, f"Oracle ceiling: agent neck pitch from TRUE user phrase ends (SynthTalk-{args.size}, "
                      f"{len(train)} train / {len(test)} test conversation sides)")
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "rows": rows})


if __name__ == "__main__":
    main()
