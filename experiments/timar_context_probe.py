"""Where TIMAR loses the context: a linear probe on the head's conditions.

On the mimicry control corpus a ridge probe on the user's past motion explains +0.12 more of the
agent's neck variance with 7 past turns than with none (``timar_context_control.py``), while TIMAR's
own prediction follows the truth with a correlation of 0.05-0.11 (``timar_context_centred.py``). The
information passes two stages: the encoder turns the window into the diffusion head's conditions
``z`` (one ``width``-vector per frame of the current turn), and the head turns ``z`` into motion. This
script reads ``z`` where the stream makes it (:func:`~jaxtalk.models.timar.streaming.stream_condition`,
turn by turn, ``n`` past turns, every agent frame masked as at inference) and fits the same kind of
probe as the control: ridge from ``z`` (centred per side, scaled to unit spread on the train sides,
penalty chosen on the val sides) to the agent's centred neck (and upper face), R^2 on the test sides.

* The probe's gain from ``n = 0`` to ``7`` close to the observable probe's: the encoder extracts the
  context and the head (or its objective) does not use it.
* No gain in ``z`` of the trained model while a freshly initialised encoder of the same shape carries
  some (``--init``: random features of the same window): training removes or ignores it.
* No gain in either: the encoder's inputs reach ``z`` too weakly for a linear reader (architecture).

Usage: python experiments/timar_context_probe.py MODEL.pkl [MODEL.pkl ...] --size full
       --effects mimicry_1.2 --cache-dir DIR [--init] [--out PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from typing import Any

import jax
import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models.timar.data import conversations
from jaxtalk.models.timar.model import init_params
from jaxtalk.models.timar.streaming import init_stream, stream_condition

from timar_common import EFFECTS, load_corpus, load_model, padded_streams  # noqa: E402
from timar_context_control import GROUP_CHANNELS, fit_ridge  # noqa: E402


class FirstConversations:
    """A corpus that lists only the first ``limit`` conversations of each split (the rest unchanged):
    the probe's training sides are a sample, and every conversation costs a speech synthesis."""

    def __init__(self, corpus: Any, limit: int) -> None:
        self._corpus, self._limit = corpus, limit

    def conversations(self, split: str) -> list:
        return self._corpus.conversations(split)[: self._limit]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._corpus, name)


def conditions(config, params, norm, convs, context: int, batch: int = 64) -> list[np.ndarray]:
    """Each side's head conditions ``(frames, width)``, streamed turn by turn with ``context`` past
    turns, no guidance branch; sides batched, each padded at its end and cropped after (the stream is
    turn-causal, so padding after a side's last turn cannot reach it)."""
    f = config.frames_per_turn
    out = []
    for start in range(0, len(convs), batch):
        group = convs[start:start + batch]
        us, um, as_ = padded_streams(group, norm)
        state = init_stream(config, jax.random.key(0), batch=len(group), context=context, guidance=False)
        zs = []
        for i in range(us.shape[1] // f):
            sl = slice(i * f, (i + 1) * f)
            state, z = stream_condition(params, config, state, us[:, sl], um[:, sl], as_[:, sl], guidance=False)
            zs.append(np.asarray(z))
        z = np.concatenate(zs, axis=1)
        out.extend(z[j, : c.num_frames] for j, c in enumerate(group))
    return out


def probe(z: dict[str, list[np.ndarray]], truth: dict[str, list[np.ndarray]], channels: np.ndarray) -> dict[str, float]:
    """:func:`~timar_context_control.fit_ridge` from each side's centred conditions to its centred
    target channels (the control probe's targets)."""

    def stack(split):
        xs, ys = [], []
        for a, t in zip(z[split], truth[split]):
            n = min(len(a), len(t))
            x, y = a[:n].astype(np.float64), t[:n, channels].astype(np.float64)
            xs.append(x - x.mean(0))
            ys.append(y - y.mean(0))
        return np.concatenate(xs), np.concatenate(ys)

    return fit_ridge(stack("train"), stack("val"), stack("test"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", help="TIMAR models saved by timar_common.save_model")
    ap.add_argument("--size", default="full")
    ap.add_argument("--effects", default="mimicry_1.2", choices=sorted(EFFECTS))
    ap.add_argument("--cache-dir", default=".cache/prepared")
    ap.add_argument("--train-conversations", type=int, default=300, help="train conversations the probe is fitted on")
    ap.add_argument("--contexts", default="0,7")
    ap.add_argument("--init", action="store_true", help="also probe a freshly initialised model of the first model's shape")
    ap.add_argument("--init-seed", type=int, default=0)
    ap.add_argument("--out", default="experiments/results/timar_context_probe.json")
    args = ap.parse_args()
    corpus = load_corpus(args)
    t0 = time.perf_counter()
    convs = {"train": conversations(FirstConversations(corpus, args.train_conversations), "train"),
             "val": conversations(corpus, "val"), "test": conversations(corpus, "test")}
    print(f"sides: { {k: len(v) for k, v in convs.items()} } ({time.perf_counter() - t0:.0f} s)", flush=True)
    truth = {k: [c.agent_motion for c in v] for k, v in convs.items()}
    models = [(path, *load_model(path)) for path in args.models]
    if args.init:
        _, config, _, norm = models[0]
        models.append((f"initialised (seed {args.init_seed})", config,
                       jax.device_get(init_params(config, jax.random.key(args.init_seed))), norm))
    rows = []
    for name, config, params, norm in models:
        for n in map(int, args.contexts.split(",")):
            t0 = time.perf_counter()
            z = {k: conditions(config, params, norm, v, n) for k, v in convs.items()}
            for group, ch in GROUP_CHANNELS.items():
                fit = probe(z, truth, ch)
                rows.append({"model": name, "context": n, "group": group, **{f"R2_{k}": v for k, v in fit.items()}})
                print(rows[-1], f"({time.perf_counter() - t0:.0f} s)", flush=True)
    for r in rows:  # the gain from the shortest to the longest context, per model and group
        same = [q for q in rows if q["model"] == r["model"] and q["group"] == r["group"]]
        lo, hi = min(same, key=lambda q: q["context"]), max(same, key=lambda q: q["context"])
        r["test_gain"] = hi["R2_test"] - lo["R2_test"]
    print_table(rows, f"Linear probe of TIMAR's head conditions on SynthTalk-{args.size}, effects {args.effects}")
    write_json(args.out, {"machine": machine_info(), "args": vars(args),
                          "effects": dataclasses.asdict(EFFECTS[args.effects]), "rows": rows})


if __name__ == "__main__":
    main()
