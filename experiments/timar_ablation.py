"""TIMAR Table 2 / Table 5 / Fig. 5 on SynthTalk: diffusion vs MLP head, turn-causal vs bidirectional
attention, encoder-only vs the MAE-style encoder-decoder, the diffusion head's depth K and width d_m,
and a CFG-scale sweep (FD and P-FD vs omega; omega is traced, so every scale reuses one compiled
streaming step).

Variants (``--variants``) are each trained with TIMAR's recipe (``timar_common.train_model``) with the
same data, steps and seed (the default model is
retrained with them, so the rows compare equal budgets), then streamed with n = 7 turns of context on
the test split. The bidirectional variant is evaluated by recomputing the window every turn (it cannot
be cached), which is what the paper's "w/ Bi-Attention" row measures. The ``mae`` variant
(``architecture="encoder_decoder"``, Table 2's "w/ Asym. EncDec") keeps the default's total depth: its
encoder has ``L - L // 2`` blocks and its decoder ``L // 2`` (2 + 2 at the default L = 4), so the
two differ only by the decoder's input projection, positional table and final norm (+10% parameters
at the ``small`` sizes; each row records its parameter count). The head rows (Table 5) change K
(``head_blocks``, default 3) or d_m (``head_width``, default ``--head-width``) alone. The CFG sweep runs on
``--load-model`` (the context experiment's model) when given, else on the retrained default. Results
of separate invocations (e.g. one variant each, to keep every run short) are merged into ``--out``.

Usage: ``python experiments/timar_ablation.py [--size small] [--steps 2000] [--variants default,mlp]
[--load-model experiments/results/timar_context_model.pkl] [--out ...]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models.timar import TimarConfig
from jaxtalk.models.timar.data import conversations

from timar_common import (  # noqa: E402  (sibling script)
    KEYS, add_training_args, load_corpus, load_model, metrics, model_config, predict, train_model,
)

def _split_depth(config: TimarConfig) -> dict:
    """The encoder-decoder at the default's total depth: L - L // 2 encoder and L // 2 decoder blocks
    (at least one each)."""
    dec = max(1, config.num_layers // 2)
    return {"architecture": "encoder_decoder", "num_layers": max(1, config.num_layers - dec), "decoder_layers": dec}


# name -> (row label, config overrides: a dict, or a function of the base config)
VARIANTS = {
    "default": ("diffusion head + TLCA (default)", {}),
    "mlp": ("MLP head", {"head": "mlp"}),
    "bidirectional": ("bidirectional attention", {"attention": "bidirectional"}),
    "paper_mask": ("paper mask ratio (r ~ TN[0.7, 1])", {"mask_ratio_min": 0.7}),
    "mae": ("MAE-style asym. encoder-decoder (same total depth)", _split_depth),
    "head_k1": ("diffusion head K = 1", {"head_blocks": 1}),
    "head_k6": ("diffusion head K = 6", {"head_blocks": 6}),
    "head_k9": ("diffusion head K = 9", {"head_blocks": 9}),
    "head_w64": ("diffusion head d_m = 64", {"head_width": 64}),
    "head_w256": ("diffusion head d_m = 256", {"head_width": 256}),
}


def variant_config(name: str, config: TimarConfig) -> TimarConfig:
    """The base config with variant ``name``'s overrides."""
    overrides = VARIANTS[name][1]
    return dataclasses.replace(config, **(overrides(config) if callable(overrides) else overrides))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_training_args(ap)
    ap.add_argument("--context", type=int, default=7)
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated subset of {list(VARIANTS)} ('' = none)")
    ap.add_argument("--scales", default="0,0.5,1,1.5,2,3", help="CFG sweep in the paper's omega (= 1 + cfg_scale; '' = no sweep)")
    ap.add_argument("--sampler", default="ddim", help="ddim (5-step samples, the paper) or mean (the guided posterior mean)")
    ap.add_argument("--load-model", default=None, help="model for the CFG sweep (default: the retrained default variant)")
    ap.add_argument("--eval-convs", type=int, default=None, help="evaluate on the first N test conversations only")
    ap.add_argument("--out", default="experiments/results/timar_ablation.json")
    args = ap.parse_args()
    names = [v for v in args.variants.split(",") if v]
    unknown = [v for v in names if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; choose from {list(VARIANTS)}")

    corpus = load_corpus(args)
    test_convs = conversations(corpus, "test")[: args.eval_convs]
    out = Path(args.out)
    record = json.loads(out.read_text()) if out.is_file() else {}
    record.setdefault("variants", {})
    record.setdefault("runs", [])
    trained = {}
    if names:
        config = model_config(args)
        for name in names:
            label = VARIANTS[name][0]
            cfg = variant_config(name, config)
            t0 = time.perf_counter()
            res, norm, _ = train_model(args, cfg, seed=args.seed)
            train_s = time.perf_counter() - t0
            trained[name] = (cfg, res.state.eval_params, norm)
            m = metrics(predict(cfg, res.state.eval_params, norm, test_convs, context=args.context, cfg_scale=0.5,
                                sampler=args.sampler), test_convs, corpus)
            n_params = sum(int(x.size) for x in jax.tree.leaves(res.state.eval_params))
            record["variants"][label] = {**m, "steps": args.steps, "train_s": train_s,
                                         "final_loss": [h["loss"] for h in res.history if "loss" in h][-1],
                                         "sampler": args.sampler, "params": n_params,
                                         "layers": [cfg.num_layers,
                                                    cfg.decoder_layers if cfg.architecture == "encoder_decoder" else 0],
                                         "head": [cfg.head_blocks, cfg.head_width]}
    rows = [{"variant": k, "steps": v.get("steps"), "params": v.get("params"), **{key: v.get(key) for key in KEYS}}
            for k, v in record["variants"].items()]
    if rows:
        print_table(rows, f"TIMAR ablations on SynthTalk-{args.size} test (n={args.context}, published scaling)")

    scales = [float(v) for v in args.scales.split(",") if v]
    if scales:
        if args.load_model:
            cfg, params, norm = load_model(args.load_model)
        elif "default" in trained:
            cfg, params, norm = trained["default"]
        else:
            raise SystemExit("the CFG sweep needs --load-model or the default variant in --variants")
        sweep = []
        for w in scales:
            m = metrics(predict(cfg, params, norm, test_convs, context=min(args.context, cfg.max_turns - 1), cfg_scale=w - 1.0,
                                sampler=args.sampler), test_convs, corpus)
            sweep.append({"omega": w, "FD_exp": m["FD_exp"], "P-FD_exp": m["P-FD_exp"], "FD_jaw": m["FD_jaw"],
                          "P-FD_jaw": m["P-FD_jaw"], "FD_pose": m["FD_pose"], "P-FD_pose": m["P-FD_pose"],
                          "MSE_exp": m["MSE_exp"], "MSE_mouth_spk": m["MSE_mouth_spk"]})
        print_table(sweep, "CFG scale sweep (paper's omega: 0 = unconditional, 1 = conditional)")
        best = min(sweep, key=lambda r: r["FD_exp"])
        print(f"best omega by FD_exp: {best['omega']} (paper: guidance above 1 improves FD and P-FD)")
        record["cfg_sweep"] = sweep
        record["cfg_sweep_model"] = args.load_model or "retrained default"
        record["best_omega_fd_exp"] = best["omega"]
    record["runs"].append({"machine": machine_info(), "args": vars(args)})
    write_json(args.out, record)


if __name__ == "__main__":
    main()
