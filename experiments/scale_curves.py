"""Each paper claim that did not hold at CPU scale, as a gap against scale, with its verdict.

Reads the result files the claim's own experiment wrote (nothing is retrained here) and plots, per
claim, the gap in the direction the paper claims (positive = the claim holds) against the training
budget, one point per training seed. The verdict compares the gap with its spread:

* ``holds at the largest scale``: there every seed's gap is positive and their mean exceeds twice the
  noise (the seed spread averaged over scales, or ``--floor`` where no scale has two seeds);
* ``does not hold``: otherwise (``reversed`` where the mean gap is below minus twice the noise);
* and whether the mean gap moves toward the claim, away from it, or not beyond the noise from the
  smallest to the largest scale. A verdict resting on one seed says so.

Claims and their files (all under ``experiments/results/``):

* TokTalk, more Euler steps is better: ``toktalk_degradation.json`` (the held-out runs' validation every
  500 steps, 20 val clips, 1 and 10 steps): gap = LVE(1 step) - LVE(10 steps), and the same for jitter.
* FreeTalk, intensity grows through the chain: ``freetalk_intensity_scale/*.json``
  (``freetalk_emotion.py`` at several ATS budgets): gap = the intensity gain along the true direction
  over the generator's own (``gain_ratio``; 1 = as the generator, 0 = none).
* TIMAR, more context helps: ``timar_context_centred_full*_cfg1.json`` and
  ``timar_context_scale/*.json`` (``timar_context_centred.py`` on the mimicry-1.2 control corpus,
  ``full``): gap = centred neck R^2 at 7 past turns minus at 0, test conversations; and the same for
  its correlation part alone (``R2 = 2 a rho - a^2``: a model can gain R^2 by moving less, without
  following the truth any better).
* TIMAR beats the DualTalk-style baseline, the diffusion head beats the MLP head, encoder-only beats the
  MAE-style encoder-decoder: ``timar_tables/*.json`` (``timar_tables.py eval`` at each budget and size):
  gap = the share of the other model's FD that TIMAR's default removes, averaged over expression, jaw
  and pose (test, n = 7 past turns; for the baseline also out of distribution), paired seed by seed;
  against the budget (64 x 2 models) and, for the baseline, against the parameter count (every size
  at 500 steps, as TIMAR's Fig. 6).

    python experiments/scale_curves.py --out experiments/results/scale_curves.json \
        --figure experiments/results/scale_curves.png
"""

from __future__ import annotations

import argparse
import glob
import json
import textwrap
from pathlib import Path

import numpy as np

from jaxtalk.benchmarking import print_table, write_json

RESULTS = Path("experiments/results")


def toktalk_steps(metric: str) -> list[dict]:
    """(training steps, seed, gap) of TokTalk's 1- vs 10-step ``metric`` on the 20 val clips."""
    runs = json.loads((RESULTS / "toktalk_degradation.json").read_text())["sessions"]["2026-12-04-s19"]["runs"]
    return [{"scale": e["step"], "seed": run["seed"], "gap": e[f"{metric}_1step"] - e[f"{metric}_10step"]}
            for run in runs.values() for e in run["evals_val_20_clips"]]


def freetalk_intensity() -> list[dict]:
    """(ATS training steps, seed, intensity gain ratio) from ``freetalk_emotion.py`` runs."""
    points = []
    for path in sorted(glob.glob(str(RESULTS / "freetalk_intensity_scale" / "*.json"))):
        report = json.loads(Path(path).read_text())
        points.append({"scale": int(report["args"]["steps"]), "seed": int(report["args"].get("train_seed", 0)),
                       "gap": report["verdict"]["gain_ratio"]})
    return points


def timar_context(split: str = "test", metric: str = "R2_neck") -> list[dict]:
    """(training steps, seed, gain of ``metric`` from 0 to 7 turns) of TIMAR 64x2's diffusion head on
    the mimicry-1.2 control corpus (``full``): the centred neck R^2, or its correlation part alone."""
    files = [RESULTS / "timar_context_centred_full_cfg1.json", RESULTS / "timar_context_centred_full_1500_cfg1.json",
             *map(Path, sorted(glob.glob(str(RESULTS / "timar_context_scale" / "*.json"))))]
    points = []
    for path in files:
        if not path.is_file():
            continue
        report = json.loads(path.read_text())
        meta = report["scale"]  # the run's budget and seed, added beside timar_context_centred.py's output
        r2 = {r["context"]: r[metric] for r in report["rows"] if r["split"] == split}
        points.append({"scale": meta["steps"], "seed": meta["seed"], "gap": r2[max(r2)] - r2[min(r2)]})
    return points


TIMAR_TABLES = RESULTS / "timar_tables"
FD_GROUPS = ("FD_exp", "FD_jaw", "FD_pose")


def _fd_rows(model: dict, table: str, split: str = "test") -> dict:
    """One model's metrics at n = 7: Table 1's row on ``split`` (TIMAR sampled, the baseline's
    regression) or the mean of its Table 2 rows (test; one per noise seed for a variant trained once)."""
    if table == "table1":
        (row,) = [v for k, v in model["table1"][split].items() if k.endswith(("sample n=7", "regression n=7"))]
        return row
    return {g: float(np.mean([r[g] for r in model["table2"]])) for g in FD_GROUPS}


def timar_tables(baseline: str, axis: str = "steps", split: str = "test") -> list[dict]:
    """(scale, seed, gap) of TIMAR's default against ``baseline`` (``dualtalk``, ``mlp``, ``mae``) from
    ``timar_tables.py`` eval JSONs in ``timar_tables/``: the gap is the share of the baseline's FD that
    TIMAR removes, averaged over the expression, jaw and pose (n = 7; ``split`` test or ood for the
    baseline, test for the variants), seed by seed. ``axis``: ``steps`` (the 64 x 2 models at each
    training budget) or ``params`` (every size at 500 steps)."""
    points = []
    for path in sorted(glob.glob(str(TIMAR_TABLES / "*.json"))):
        models = json.loads(Path(path).read_text())["models"]
        for model in models.values():
            run = model["run"]
            other = models.get(f"{baseline}_s{run['seed']}")
            if run["name"] != "timar" or other is None:
                continue
            if axis == "steps" and (run["width"], run["layers"]) != (64, 2):
                continue
            if axis == "params" and run["steps"] != 500:
                continue
            table = "table1" if baseline == "dualtalk" else "table2"
            ours, theirs = _fd_rows(model, table, split), _fd_rows(other, table, split)
            gap = float(np.mean([(theirs[g] - ours[g]) / theirs[g] for g in FD_GROUPS]))
            points.append({"scale": run["steps"] if axis == "steps" else run["num_params"], "seed": run["seed"],
                           "gap": gap})
    return points


CLAIMS = {
    "TokTalk: 10 Euler steps beat 1 on lip error (LVE, mm^2)": (lambda: toktalk_steps("LVE_mm2"), "TokTalk steps"),
    "TokTalk: 10 Euler steps are smoother than 1 (jitter, mm/frame^2)": (lambda: toktalk_steps("jitter_mm"), "TokTalk steps"),
    "FreeTalk: intensity grows along the emotion (gain / generator's gain)": (freetalk_intensity, "ATS steps"),
    "TIMAR: 7 past turns beat 0 (centred neck R^2, test, control corpus)": (timar_context, "TIMAR 64x2 steps"),
    "TIMAR: 7 past turns beat 0 (its correlation part alone, test, control corpus)": (
        lambda: timar_context(metric="corr_neck"), "TIMAR 64x2 steps"),
    "TIMAR beats the DualTalk-style baseline (share of its FD removed, test, n = 7)": (
        lambda: timar_tables("dualtalk"), "TIMAR 64x2 steps"),
    "... on the out-of-distribution conversations (share of its FD removed, n = 7)": (
        lambda: timar_tables("dualtalk", split="ood"), "TIMAR 64x2 steps"),
    "... against model size, both at the same size (share of FD removed, test)": (
        lambda: timar_tables("dualtalk", axis="params"), "TIMAR parameters (500 steps)"),
    "TIMAR: the diffusion head beats the MLP head (share of FD removed)": (
        lambda: timar_tables("mlp"), "TIMAR 64x2 steps"),
    "TIMAR: encoder-only beats the MAE-style encoder-decoder (share of FD removed)": (
        lambda: timar_tables("mae"), "TIMAR 64x2 steps"),
}


def verdict(points: list[dict], floor: float) -> dict:
    """The verdict of one claim from its (scale, seed, gap) points; ``floor``: the noise level assumed
    where one seed gives no spread."""
    scales = sorted({p["scale"] for p in points})
    by = {s: np.array([p["gap"] for p in points if p["scale"] == s]) for s in scales}
    mean = {s: float(v.mean()) for s, v in by.items()}
    spread = {s: float(v.std(ddof=1)) if len(v) > 1 else float("nan") for s, v in by.items()}
    seeds_spread = [v for v in spread.values() if np.isfinite(v)]
    noise = max(float(np.mean(seeds_spread)) if seeds_spread else 0.0, floor)
    top, bottom = scales[-1], scales[0]
    change = mean[top] - mean[bottom]
    trend = ("moves toward the claim" if change > 2 * noise else "moves away from the claim" if change < -2 * noise
             else "does not change beyond the spread")
    if mean[top] > 2 * noise and (by[top] > 0).all():
        text = "holds at the largest scale"
    else:
        text = "does not hold" + (", reversed" if mean[top] < -2 * noise else "")
    text += f"; from the smallest to the largest scale the gap {trend}"
    if len(by[top]) < 2:
        text += f" (one seed at the largest scale: noise taken as {noise:.3g})"
    # The same rule at each scale, and how many single evaluations (a seed at a scale) fall on each side.
    at_scale = ["holds" if mean[s] > 2 * noise and (by[s] > 0).all() else "reversed" if mean[s] < -2 * noise
                else "within twice the noise" for s in scales]
    gaps = np.concatenate([by[s] for s in scales])
    return {"verdict": text, "scales": scales, "mean_gap": [mean[s] for s in scales],
            "seed_spread": [spread[s] for s in scales], "seeds": [len(by[s]) for s in scales], "noise": noise,
            "verdict_at_scale": at_scale, "evaluations": int(gaps.size),
            "evaluations_for_claim": int((gaps > 0).sum()), "evaluations_against_claim": int((gaps < 0).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=RESULTS / "scale_curves.json")
    ap.add_argument("--figure", type=Path, default=RESULTS / "scale_curves.png")
    ap.add_argument("--floor", type=float, default=0.0,
                    help="noise level assumed for a claim measured with one seed per scale (default 0: say so)")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, NullFormatter

    results, rows = {}, []
    panels = [(name, load(), xlabel) for name, (load, xlabel) in CLAIMS.items()]
    panels = [p for p in panels if p[1]]
    cols = 2 if len(panels) == 4 else min(len(panels), 3)  # 4 panels: 2 x 2; 5 or more: rows of 3
    rows_ = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows_, cols, figsize=(5.2 * cols, 4.4 * rows_), squeeze=False)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    for ax, (name, points, xlabel) in zip(axes.flat, panels):
        v = verdict(points, args.floor)
        results[name] = {"points": points, **v}
        rows.append({"claim": name, "verdict": v["verdict"], "scales": "/".join(map(str, v["scales"])),
                     "mean_gap": " / ".join(f"{g:.3g}" for g in v["mean_gap"]), "seeds": "/".join(map(str, v["seeds"]))})
        for seed in sorted({p["seed"] for p in points}):
            xs = [p["scale"] for p in points if p["seed"] == seed]
            ax.plot(xs, [p["gap"] for p in points if p["seed"] == seed], "o", alpha=0.6, label=f"seed {seed}")
        ax.plot(v["scales"], v["mean_gap"], "k-", lw=1.5, label="mean")
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks(v["scales"] if len(v["scales"]) <= 5 else v["scales"][::3])
        ax.set_xlabel(xlabel)
        ax.set_ylabel("gap (> 0: the claim holds)")
        ax.set_title(textwrap.fill(name, 48) + "\n" + textwrap.fill(v["verdict"], 60), fontsize=7.5)
        ax.legend(fontsize=7)
    fig.tight_layout()
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.figure, dpi=120)
    print_table(rows, "Paper claims against scale")
    write_json(args.out, {"claims": results})
    print(f"wrote {args.out} and {args.figure}")


if __name__ == "__main__":
    main()
