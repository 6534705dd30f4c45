"""TIMAR's Tables 1 and 2 on SynthTalk-full, with training seeds and their spread.

Table 1 (context): TIMAR and the DualTalk-style baseline (``jaxtalk.models.dualtalk``), each trained
with ``--seeds`` training seeds, evaluated at n = 0 / 1 / 3 / 7 turns of context on the test and
out-of-distribution conversations (both roles of each) with the DualTalk metrics per group (FD, P-FD,
MSE, SID, rPCC, published scaling), beside the mean pose (the training mean, every frame) and the
oracle (the generator's expectation). TIMAR streams turn by turn (its config's sampler: 5-step DDIM
samples for ``small``; ``mean`` rows, on the test split at n = 0 and 7, give its guided posterior
mean); the baseline reads the window of turns ``[t - n, t]`` whole, as DualTalk reads a clip.

Table 2 (variants at equal steps, n = 7, test): TIMAR's default against the MLP head, bidirectional
attention, the MAE-style encoder-decoder and the diffusion head's depth K and width d_m (Table 5),
each trained once per seed in ``--variant-seeds``; a variant with one training seed is evaluated with
three noise seeds instead.

Every model trains through its recipe on ``synthtalk:full`` (8-turn windows, the ``small`` preset's
optimiser ``PRESET_DEFAULTS["small"]``) at ``--width`` x ``--layers`` (the diffusion head as wide as the
encoder) with ``--batch`` windows for ``--steps`` steps, and is saved under ``--runs``; ``eval`` reads
whatever is there. The defaults (64 wide, 2 layers, batch 8, 500 steps) fit a 2-core CPU: the ``small``
preset (128 x 4, batch 16) costs about 8 s per step on 8-turn windows there. Train one model per call
so long runs can be spread out:

    python experiments/timar_tables.py train timar --seed 0
    python experiments/timar_tables.py train dualtalk --seed 0
    python experiments/timar_tables.py train mae --seed 0
    python experiments/timar_tables.py eval --out experiments/results/timar_tables.json
    python experiments/timar_tables.py report --out experiments/results/timar_tables.json

Each run keeps its curves (every step's training loss, every evaluation's validation loss and streamed
val metrics) and its parameter count, so ``figures`` draws the paper's Fig. 6 (test FD and P-FD of the
expression against the parameter count, TIMAR and the baseline trained at several ``--width`` x
``--layers`` for one budget, one ``--runs`` folder and eval JSON per size) and Fig. 7 (the diffusion and
MLP heads' curves under the same settings):

    python experiments/timar_tables.py figures --fig6 W32.json W64.json W128.json --fig7 W64_1500.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import time
from pathlib import Path

import jax
import numpy as np

from jaxtalk.benchmarking import machine_info, write_json
from jaxtalk.models.timar import TimarConfig
from jaxtalk.models.timar.data import Normalizer, conversations

from timar_ablation import VARIANTS, variant_config  # noqa: E402  (sibling script)
from timar_common import metrics, padded_streams  # noqa: E402

SIZE = "full"
CACHE = ".cache/prepared"
CONTEXTS = (0, 1, 3, 7)
GROUP_KEYS = ("FD_exp", "FD_jaw", "FD_pose", "P-FD_exp", "P-FD_jaw", "P-FD_pose", "MSE_exp", "MSE_jaw", "MSE_pose",
              "SID_fit_gt_exp", "SID_fit_gt_jaw", "SID_fit_gt_pose", "rPCC_exp", "rPCC_jaw", "rPCC_pose")
CFG_SCALE = 0.5  # jaxtalk's guidance weight: the paper's omega = 1.5


def model_config(name: str, width: int, layers: int):
    """The config of a Table 1/2 model: the ``small`` preset at ``width`` x ``layers``, 8-turn windows."""
    heads = max(1, width // 32)
    if name == "dualtalk":
        from jaxtalk.models.dualtalk import DualTalkConfig

        return DualTalkConfig.small(max_turns=8, width=width, num_layers=layers, num_heads=heads)
    base = TimarConfig.small(max_turns=8, width=width, num_layers=layers, num_heads=heads, head_width=width)
    return variant_config("default" if name == "timar" else name, base)


def run_path(runs: Path, name: str, seed: int) -> Path:
    return runs / f"{name}_s{seed}.pkl"


def train(args) -> None:
    from jaxtalk.data.loader import open_data
    from jaxtalk.models.timar.recipe import PRESET_DEFAULTS

    if args.model == "dualtalk":
        from jaxtalk.models.dualtalk.recipe import train as train_fn
    else:
        from jaxtalk.models.timar.recipe import train as train_fn
    config = model_config(args.model, args.width, args.layers)
    data = open_data(f"synthtalk:{SIZE}", cache_dir=CACHE)
    settings = dataclasses.replace(PRESET_DEFAULTS["small"], batch_size=args.batch)
    t0 = time.perf_counter()
    from jaxtalk.runs import RunSettings

    result = train_fn(config, data, settings.optim(args.steps), key=jax.random.key(args.seed),
                      run=RunSettings(steps=args.steps, batch_size=settings.batch_size, seed=args.seed,
                                      eval_every=args.eval_every))
    train_s = time.perf_counter() - t0
    losses = [float(h["loss"]) for h in result.history if "loss" in h]
    evals = [h["eval"]["val_loss"] for h in result.history if "eval" in h and "val_loss" in h["eval"]]
    # The curves (Fig. 7): every step's training loss, and every evaluation (the validation loss and the
    # streamed val sides' metrics, as the recipe selects its best checkpoint by them).
    curves = {"loss_step": [int(h["step"]) for h in result.history if "loss" in h], "loss": losses,
              "evals": [{"step": int(h["step"]), **{k: float(v) for k, v in h["eval"].items()}}
                        for h in result.history if "eval" in h]}
    num_params = int(sum(np.size(x) for x in jax.tree_util.tree_leaves(result.state.eval_params)))
    out = run_path(Path(args.runs), args.model, args.seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump({"name": args.model, "seed": args.seed, "steps": args.steps, "train_s": train_s,
                     "config": dataclasses.asdict(config), "params": jax.device_get(result.state.eval_params),
                     "normalizer": result.extra["normalizer"], "final_loss": float(np.mean(losses[-20:])),
                     "val_loss": evals[-1] if evals else None, "windows": result.windows, "curves": curves,
                     "num_params": num_params, "width": args.width, "layers": args.layers, "batch": args.batch}, f)
    tmp.replace(out)
    print(f"{args.model} seed {args.seed}: {args.steps} steps in {train_s:.0f} s, loss {np.mean(losses[-20:]):.4f}, "
          f"val {evals[-1] if evals else None}; saved {out}")


def load(path: Path):
    with open(path, "rb") as f:
        d = pickle.load(f)
    if d["name"] == "dualtalk":
        from jaxtalk.models.dualtalk import DualTalkConfig

        config = DualTalkConfig(**d["config"])
    else:
        config = TimarConfig(**d["config"])
    return d, config, Normalizer.from_dict(d["normalizer"])


def predictions(d, config, norm, convs, context: int, mode: str, noise_seed: int):
    """Every side's raw agent motion, all sides in ONE batch: each padded at its end to the longest
    side's turns and cropped after. Exact for both models: TIMAR is turn-causal, and the baseline's
    window for a real turn holds only real turns."""
    from jaxtalk.models.dualtalk import predict_turns
    from jaxtalk.models.timar.streaming import stream

    us, um, as_ = padded_streams(convs, norm)
    if d["name"] == "dualtalk":
        x = predict_turns(d["params"], config, us, um, as_, context=context)
    else:
        sampler = "mean" if mode == "mean" else config.sampler
        x = stream(d["params"], config, us, um, as_, jax.random.key(1000 * noise_seed), context=context,
                                cfg_scale=CFG_SCALE, sampler=sampler)
    x = np.asarray(x)
    return [norm.unmotion(x[i, : c.num_frames]) for i, c in enumerate(convs)]


def summarise(values: list[dict]) -> dict:
    """Mean, standard deviation (ddof 1) and count of every metric over seeds."""
    keys = [k for k in values[0] if all(k in v for v in values)]
    out = {}
    for k in keys:
        x = np.asarray([v[k] for v in values], np.float64)
        out[k] = {"mean": float(x.mean()), "std": float(x.std(ddof=1)) if len(x) > 1 else None, "n": len(x)}
    return out


def evaluate_model(path: Path, corpus, convs_by_split: dict, variants_trained_once: bool) -> dict:
    """One saved model's rows: Table 1 (TIMAR / the baseline) and Table 2 (variants at n = 7, test)."""
    d, config, norm = load(path)
    keys = ("name", "seed", "steps", "train_s", "final_loss", "val_loss", "windows",
            "num_params", "width", "layers", "batch", "curves")  # the last five: absent from older runs
    out: dict = {"run": {k: d[k] for k in keys if k in d},
                 "table1": {}, "table2": []}
    if d["name"] in ("timar", "dualtalk"):
        modes = ("sample", "mean") if d["name"] == "timar" else ("regression",)
        for split, convs in convs_by_split.items():
            for mode in modes:
                if mode == "mean" and split != "test":
                    continue  # evaluation time: the point estimate on the test split only,
                # and only at the two ends of the context range.
                for n in CONTEXTS if mode != "mean" else (CONTEXTS[0], CONTEXTS[-1]):
                    t0 = time.perf_counter()
                    m = metrics(predictions(d, config, norm, convs, n, mode, d["seed"]), convs, corpus)
                    out["table1"].setdefault(split, {})[f"{d['name']} {mode} n={n}"] = m
                    print(f"{path.stem} {split} {mode} n={n}: FD_exp {m['FD_exp']:.3f} MSE_exp {m['MSE_exp']:.3f} "
                          f"FD_pose {m['FD_pose']:.3f} MSE_pose {m['MSE_pose']:.3f} ({time.perf_counter() - t0:.0f} s)")
    if d["name"] != "dualtalk":
        convs = convs_by_split["test"]
        for s in (0, 1, 2) if variants_trained_once else (d["seed"],):
            out["table2"].append(metrics(predictions(d, config, norm, convs, 7, "sample", s), convs, corpus))
    return out


def evaluate(args) -> None:
    """Evaluate every saved model not evaluated yet (results kept per model), then aggregate."""
    from jaxtalk.data.synthtalk import generate

    runs = Path(args.runs)
    corpus = generate(SIZE, 0, cache_dir=Path(CACHE) / "synthtalk")
    found: dict[str, list[Path]] = {}
    for p in sorted(runs.glob("*_s*.pkl")):
        found.setdefault(p.stem.rsplit("_s", 1)[0], []).append(p)
    print("models:", {k: len(v) for k, v in found.items()})
    convs_by_split = {s: conversations(corpus, s)[: args.convs] for s in ("test", "ood")}
    cache = runs / ("eval" if args.convs is None else f"eval_convs{args.convs}")
    cache.mkdir(parents=True, exist_ok=True)
    results: dict[str, list[dict]] = {}
    for name, paths in found.items():
        for path in paths:
            done = cache / f"{path.stem}.json"
            if not done.is_file():
                write_json(done, evaluate_model(path, corpus, convs_by_split, len(paths) == 1 and name != "timar"))
            results.setdefault(name, []).append(json.loads(done.read_text()))
    record: dict = {"machine": machine_info(), "args": vars(args), "table1": {}, "table2": {},
                    "runs": [r["run"] for rs in results.values() for r in rs],
                    # every model's own rows, by run (name_sSEED): what pairs models seed by seed
                    "models": {f"{r['run']['name']}_s{r['run']['seed']}": r for rs in results.values() for r in rs}}
    # Reference rows (every model is trained on the same data, so one normaliser's mean pose serves all).
    _, _, norm = load(next(iter(found.values()))[0])
    for split, convs in convs_by_split.items():
        gts = [c.agent_motion for c in convs]
        record["table1"][split] = {
            "mean pose": metrics([np.broadcast_to(norm.motion_mean, g.shape).astype(np.float32) for g in gts], convs, corpus),
            "oracle": metrics([c.agent_oracle for c in convs], convs, corpus)}
        for name in ("timar", "dualtalk"):
            rows = [r["table1"].get(split, {}) for r in results.get(name, [])]
            for key in [k for k in (rows[0] if rows else {}) if all(k in r for r in rows)]:
                per_seed = [r[key] for r in rows]
                record["table1"][split][key] = {"per_seed": per_seed, "summary": summarise(per_seed)}
    for name, rs in results.items():
        rows = [m for r in rs for m in r["table2"]]
        if rows:
            record["table2"][name] = {"seeds": "training" if len(rs) > 1 else "noise", "per_seed": rows,
                                      "summary": summarise(rows)}
    write_json(args.out, record)
    print(f"wrote {args.out}")


def report(args) -> None:
    """Markdown tables (mean ± std over seeds) from an ``eval`` JSON."""
    rec = json.loads(Path(args.out).read_text())

    def cell(entry, key):
        if "summary" not in entry:
            return f"{entry[key]:.3f}"
        s = entry["summary"][key]
        return f"{s['mean']:.3f}" + (f" ± {s['std']:.3f}" if s["std"] is not None else "")

    for split, rows in rec["table1"].items():
        print(f"\nTable 1, {split}\n\n| method | " + " | ".join(GROUP_KEYS) + " |\n|" + "---|" * (len(GROUP_KEYS) + 1))
        for name, entry in rows.items():
            print(f"| {name} | " + " | ".join(cell(entry, k) for k in GROUP_KEYS) + " |")
    print("\nTable 2, test, n = 7\n\n| variant | seeds | " + " | ".join(GROUP_KEYS) + " |\n|" + "---|" * (len(GROUP_KEYS) + 2))
    for name, entry in rec["table2"].items():
        n = entry["summary"]["FD_exp"]["n"]
        print(f"| {name} | {n} {entry['seeds']} | " + " | ".join(cell(entry, k) for k in GROUP_KEYS) + " |")


TABLE1_N7 = {"timar": "timar sample n=7", "dualtalk": "dualtalk regression n=7"}


def figure6_rows(records: list[dict]) -> list[dict]:
    """Fig. 6's points: every TIMAR and baseline model's size and its test FD / P-FD of the expression
    at n = 7 past turns (TIMAR sampled as users run it), from ``eval`` JSONs of one training budget."""
    rows = []
    for rec in records:
        for model in rec["models"].values():
            run = model["run"]
            if run["name"] not in TABLE1_N7 or "num_params" not in run:
                continue
            m = model["table1"]["test"][TABLE1_N7[run["name"]]]
            rows.append({"model": run["name"], "size": f"{run['width']}x{run['layers']}", "params": run["num_params"],
                         "steps": run["steps"], "seed": run["seed"], "FD_exp": m["FD_exp"], "P-FD_exp": m["P-FD_exp"],
                         "FD_pose": m["FD_pose"], "MSE_exp": m["MSE_exp"]})
    return sorted(rows, key=lambda r: (r["model"], r["params"], r["seed"]))


def smooth(values: list[float], width: int) -> np.ndarray:
    """The trailing moving average of ``values`` over ``width`` steps (shorter at the start)."""
    x = np.asarray(values, np.float64)
    c = np.concatenate([[0.0], np.cumsum(x)])
    i = np.arange(1, len(x) + 1)
    return (c[i] - c[np.maximum(i - width, 0)]) / np.minimum(i, width)


def figures(args) -> None:
    """Fig. 6 (test FD and P-FD of the expression against the parameter count, TIMAR and the baseline at
    one budget) from ``--fig6`` eval JSONs, and Fig. 7 (the diffusion and MLP heads' training and
    validation curves, same settings) from the ``--fig7`` eval JSON."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxtalk.benchmarking import print_table

    records = [json.loads(Path(f).read_text()) for f in args.fig6]
    rows = figure6_rows(records)
    still = records[0]["table1"]["test"]["mean pose"]  # the same test sides and metrics in every file
    if len({r["steps"] for r in rows}) > 1:
        raise SystemExit(f"--fig6 mixes training budgets {sorted({r['steps'] for r in rows})}: give one budget's files")
    print_table(rows, "Fig. 6: test, n = 7")
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.8))
    for ax, key in zip(axes, ("FD_exp", "P-FD_exp")):
        for name, label, colour in (("timar", "TIMAR", "C0"), ("dualtalk", "DualTalk-style", "C3")):
            pts = [r for r in rows if r["model"] == name]
            sizes = sorted({r["params"] for r in pts})
            ax.plot([r["params"] for r in pts], [r[key] for r in pts], "o", color=colour, alpha=0.5)
            ax.plot(sizes, [np.mean([r[key] for r in pts if r["params"] == n]) for n in sizes], "-", color=colour,
                    label=label)
        ax.axhline(still[key], color="grey", ls="--", lw=1, label="mean pose")
        ax.set_xscale("log")
        ax.set_xlabel("parameters")
        ax.set_ylabel(f"{key} (test, n = 7; lower is better)")
        ax.legend(fontsize=8)
    fig.suptitle(f"Model size at {rows[0]['steps']} training steps (SynthTalk full; points: training seeds)", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.fig6_out, dpi=120)
    print(f"wrote {args.fig6_out}")

    rec = json.loads(Path(args.fig7).read_text())
    runs = {stem: m["run"] for stem, m in rec["models"].items() if m["run"]["name"] in ("timar", "mlp") and "curves" in m["run"]}
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for stem, run in sorted(runs.items()):
        colour = "C0" if run["name"] == "timar" else "C1"
        label = ("diffusion head" if run["name"] == "timar" else "MLP head") + f", seed {run['seed']}"
        style = "-" if run["seed"] == 0 else "--"
        c = run["curves"]
        axes[0].plot(c["loss_step"], c["loss"], color=colour, alpha=0.15, lw=0.5)
        axes[0].plot(c["loss_step"], smooth(c["loss"], 25), style, color=colour, label=label)
        steps = [e["step"] for e in c["evals"]]
        axes[1].plot(steps, [e["val_loss"] for e in c["evals"]], style + "o", color=colour, ms=3, label=label)
        axes[2].plot(steps, [e["FD_exp"] for e in c["evals"]], style + "o", color=colour, ms=3, label=label)
    for ax, title in zip(axes, ("training loss (each step; line: 25-step mean)", "validation loss",
                                "val sides streamed: FD_exp (lower is better)")):
        ax.set_xlabel("training step")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.fig7_out, dpi=120)
    print(f"wrote {args.fig7_out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train one model with one seed")
    t.add_argument("model", choices=["timar", "dualtalk", *[v for v in VARIANTS if v != "default"]])
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--steps", type=int, default=500)
    t.add_argument("--width", type=int, default=64)
    t.add_argument("--layers", type=int, default=2)
    t.add_argument("--batch", type=int, default=8)
    t.add_argument("--eval-every", type=int, default=None, help="validation period in steps (default: five per run)")
    t.add_argument("--runs", default="runs/timar_tables")
    e = sub.add_parser("eval", help="evaluate every saved model")
    e.add_argument("--runs", default="runs/timar_tables")
    e.add_argument("--out", default="experiments/results/timar_tables.json")
    e.add_argument("--convs", type=int, default=None, help="only the first N conversation sides per split (a smoke run)")
    r = sub.add_parser("report", help="print the tables of an eval JSON")
    r.add_argument("--out", default="experiments/results/timar_tables.json")
    f = sub.add_parser("figures", help="draw Figs. 6 and 7 from eval JSONs")
    f.add_argument("--fig6", nargs="+", required=True, help="eval JSONs of one training budget at several sizes")
    f.add_argument("--fig7", required=True, help="the eval JSON whose TIMAR and MLP-head runs' curves to draw")
    f.add_argument("--fig6-out", default="experiments/results/timar_fig6.png")
    f.add_argument("--fig7-out", default="experiments/results/timar_fig7.png")
    args = ap.parse_args()
    {"train": train, "eval": evaluate, "report": report, "figures": figures}[args.command](args)


if __name__ == "__main__":
    main()
