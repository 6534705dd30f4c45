"""A positive control for TIMAR's context claim: how much of the agent's motion an OBSERVABLE linear probe
explains from k past turns, on SynthTalk with its dyadic effects at the default and raised strengths.

The ceiling (``timar_context_ceiling.py``) regresses on the generator's true causes; a model sees only
the conversation. This probe sees what TIMAR with ``k`` past turns sees, per frame ``f`` of the agent's
current 1-s turn (window = the current turn plus ``k`` before it):

* the USER's motion of the group at lags 0..``MAX_LAG_S`` s, causal and inside the window (TIMAR reads
  the user's tokens of the current turn and the past ones);
* the AGENT's own motion of the group at those lags, only before the current turn starts and inside
  the window (the current turn's agent tokens are what is being generated);

each averaged in ``BIN_S`` lag bins (zero where not visible), plus the visible fraction of each bin.
Targets are the agent's neck (3) and upper-face channels minus their per-side mean, features centred
the same way (within-conversation regression, as the ceiling) and scaled to unit spread, one ridge
fit pooled over every train side and speaker (penalty chosen on the val sides), R^2 on the test
sides. The gain from k = 0 to 7 is what context can add to a
linear reader of the observable conversation.

The bar: raise :class:`~jaxtalk.data.synthtalk.dyadic.DyadicEffects` until this gain is at least
0.10, then train TIMAR with and without context on that corpus. Motion only (no audio), so a corpus
takes seconds to a minute.

Usage: python experiments/timar_context_control.py [--size small] [--out PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.data.synthtalk import generate
from jaxtalk.data.synthtalk.corpus import SIZES
from jaxtalk.layout import GROUPS, NECK_SLICE

from timar_common import EFFECTS  # noqa: E402

FPS = 25
FRAMES_PER_TURN = 25
BIN_S = 0.2
MAX_LAG_S = 8.0
GROUP_CHANNELS = {"neck": np.arange(NECK_SLICE.start, NECK_SLICE.stop), "upper_face": np.asarray(GROUPS["upper_face"])}


def lag_features(x: np.ndarray, visible_from: np.ndarray, visible_to: np.ndarray) -> np.ndarray:
    """``(T, bins * (C + 1))``: bin means of ``x`` at lags ``0..MAX_LAG_S`` where ``visible_from[f] <= f - lag
    < visible_to[f]`` (zero elsewhere), and each bin's visible fraction."""
    n, c = x.shape
    per_bin = int(round(BIN_S * FPS))
    bins = int(round(MAX_LAG_S / BIN_S))
    f = np.arange(n)
    out = np.zeros((n, bins, c + 1))
    for lag in range(bins * per_bin):
        src = f - lag
        ok = (src >= visible_from) & (src < visible_to) & (src >= 0)
        out[:, lag // per_bin, :c] += np.where(ok[:, None], x[np.clip(src, 0, None)], 0.0)
        out[:, lag // per_bin, c] += ok
    return (out / per_bin).reshape(n, -1)


@functools.lru_cache(maxsize=4096)
def _motion(corpus, clip: int) -> np.ndarray:
    # Every side is read at four contexts and by two probes: generate its motion once.
    return corpus.motion_without_audio(clip)[0]


def side_features(corpus, agent: int, user: int, past_turns: int, observe: str = "both"
                  ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per group, ``(centred features, centred agent target)`` of one agent side (see the module docstring);
    ``observe="user"`` leaves out the agent's own past motion."""
    a, u = _motion(corpus, agent), _motion(corpus, user)
    n = min(len(a), len(u)) // FRAMES_PER_TURN * FRAMES_PER_TURN
    a, u = a[:n].astype(np.float64), u[:n].astype(np.float64)
    turn_start = np.arange(n) // FRAMES_PER_TURN * FRAMES_PER_TURN
    window_start = np.maximum(turn_start - past_turns * FRAMES_PER_TURN, 0)
    out = {}
    for name, ch in GROUP_CHANNELS.items():
        parts = [lag_features(u[:, ch], window_start, np.arange(n) + 1)]
        if observe == "both":
            parts.append(lag_features(a[:, ch], window_start, turn_start))
        x = np.concatenate(parts, axis=1)
        y = a[:, ch]
        out[name] = (x - x.mean(0), y - y.mean(0))
    return out


RIDGES = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)


def _stack(feats: list[dict], name: str) -> tuple[np.ndarray, np.ndarray]:
    return tuple(np.concatenate(p) for p in zip(*[d[name] for d in feats]))


def _r2(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> float:
    return float(1.0 - np.sum((y - x @ w) ** 2) / np.sum(y**2))


def fit_ridge(train: tuple[np.ndarray, np.ndarray], val: tuple[np.ndarray, np.ndarray],
              test: tuple[np.ndarray, np.ndarray]) -> dict[str, float]:
    """The pooled ridge probe of every script here: ``(features, targets)`` per split, features scaled
    to unit spread on train, the penalty (x the number of training frames) chosen among :data:`RIDGES`
    by R^2 on val.

    Returns:
        ``{"val", "test", "train": R^2, "ridge": penalty}``.
    """
    (x, y), (xv, yv), (xt, yt) = train, val, test
    scale = np.where(x.std(0) > 0, x.std(0), 1.0)
    x, xv, xt = x / scale, xv / scale, xt / scale
    gram, rhs = x.T @ x, x.T @ y
    best = None
    for ridge in RIDGES:
        w = np.linalg.solve(gram + ridge * len(x) * np.eye(x.shape[1]), rhs)
        score = _r2(xv, yv, w)
        if best is None or score > best[0]:
            best = (score, ridge, w)
    return {"val": best[0], "test": _r2(xt, yt, best[2]), "train": _r2(x, y, best[2]), "ridge": best[1]}


def probe_r2(corpus, sides: dict[str, list[tuple[int, int]]], past_turns: int, observe: str = "both"
             ) -> dict[str, dict[str, float]]:
    """Per group, :func:`fit_ridge` on the lag features of ``past_turns`` of context (train sides; the
    penalty chosen on the val sides; R^2 on the test sides).

    Returns:
        ``{group: {"val": R^2, "test": R^2, "train": R^2, "ridge": penalty}}``.
    """
    feats = {k: [side_features(corpus, a, u, past_turns, observe) for a, u in v] for k, v in sides.items()}
    return {name: fit_ridge(*(_stack(feats[k], name) for k in ("train", "val", "test"))) for name in GROUP_CHANNELS}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--settings", default=",".join(EFFECTS), help="comma-separated names of timar_common.EFFECTS "
                    "(default strengths, none, and each effect raised: the TIMAR experiments' --effects)")
    ap.add_argument("--observe", default="user,both", help="what the probe reads: user (the partner's motion "
                    "only: what free-running generation can use), both (also the agent's TRUE past motion)")
    ap.add_argument("--out", default="experiments/results/timar_context_control.json")
    args = ap.parse_args()
    labels = args.settings.split(",")
    unknown = [v for v in labels if v not in EFFECTS]
    if unknown:
        ap.error(f"unknown --settings {unknown}; known: {', '.join(EFFECTS)}")
    rows = []
    for label in labels:
        spec = dataclasses.replace(SIZES[args.size], lazy=True, effects=EFFECTS[label])
        corpus = generate(spec, args.seed)
        sides = {s: [p for a, b in corpus.conversations(s) for p in ((a, b), (b, a))] for s in ("train", "val", "test")}
        for observe in args.observe.split(","):
            r2 = {k: probe_r2(corpus, sides, k, observe) for k in (0, 1, 3, 7)}
            for group in GROUP_CHANNELS:
                rows.append({"effects": label, "observe": observe, "group": group,
                             **{f"R2_k{k}": r2[k][group]["test"] for k in r2},
                             "gain_0_to_7": r2[7][group]["test"] - r2[0][group]["test"],
                             "ridges": ",".join(f"{r2[k][group]['ridge']:g}" for k in r2)})
                print(rows[-1], flush=True)
    print_table(rows, f"Observable linear probe of the agent's motion (SynthTalk-{args.size}, seed {args.seed}; "
                      f"lags 0-{MAX_LAG_S:g} s in {BIN_S:g}-s bins)")
    write_json(args.out, {"machine": machine_info(), "args": vars(args),
                          "settings": {k: dataclasses.asdict(v) for k, v in EFFECTS.items()}, "rows": rows})


if __name__ == "__main__":
    main()
