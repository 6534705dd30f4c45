"""Gradients through the samplers, with and without ``jax.checkpoint``, and inversion with optimistix.

Two samplers of ``small`` models briefly trained on SynthTalk with their recipes
(``jaxtalk.models.<model>.recipe``, the training ``jaxtalk train`` runs) on 2-s windows, or parameters
loaded with ``--toktalk-params`` / ``--ats-params``:

* Euler + CFG (TokTalk): the loss is ``jaxtalk.models.toktalk.inversion.style_loss`` (MSE of the sample against a real
  clip) as a function of the style vector, at the encoder's estimate;
* DDIM, eta 0 (FreeTalk ATS): ``jaxtalk.models.freetalk.inversion.intensity_loss`` (MSE against real landmark clips, model
  units) as a function of the per-clip emotion intensity, at points between the integer levels.

For 1, 5, 10, 20 sampler steps (``--steps``) the table gives: the relative error of the gradient's
directional derivative against central finite differences (float32, as run; step ``--fd-eps``), the
gradient norm, wall time of the forward pass and of forward+backward (``value_and_grad``) with and
without ``jax.checkpoint`` on the sampler step (compile timed separately; median of ``--repeats``
runs of the compiled executable, each ending in ``block_until_ready``), and memory: XLA's compiled
memory analysis, ``temp_size_in_bytes`` of the same executables (the scratch a call needs beyond
its arguments and outputs; with the backward pass this is where the saved activations live). The
forward pass is the same program with or without checkpointing, so it is measured once.

Then the inversions, where the truth is known: a target sampled from fixed noise with a known style
vector (the encoder's estimate for a held-out clip) or known intensities is inverted from another
start (Levenberg-Marquardt, and BFGS for the style), reporting recovered vs true, error, loss,
steps and time; the encoder's estimate for the target clip is compared; and real SynthTalk clips are
inverted (style: loss of the encoder's estimate vs the inverted vector; intensity: recovered vs the
clip's labelled level).

    python experiments/sampler_gradients.py [--steps 1 5 10 20] [--toktalk-train-steps 300]
        [--ats-train-steps 600] [--out experiments/results/sampler_gradients.json]
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models.freetalk.inversion import intensity_loss, invert_intensity, sample_ats_from_noise
from jaxtalk.models.toktalk.inversion import invert_style, style_loss
from jaxtalk.models import toktalk as tt
from jaxtalk.models.freetalk import ats, data
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.data.loader import open_data
from jaxtalk.models.freetalk import recipe as freetalk_recipe
from jaxtalk.models.freetalk.fit import FittedATS
from jaxtalk.models.toktalk import recipe as toktalk_recipe
from jaxtalk.runs import RunSettings
from jaxtalk.train import LoopSettings, OptimConfig
from toktalk_common import DATA, _load, _save, load_corpus

Array = jax.Array

RESULTS = Path(__file__).resolve().parent / "results"
WINDOW = 50  # frames (2 s) per clip in every problem
MIB = 2.0**20


# ---- models -----------------------------------------------------------------------------------------


def _last_loss(history: list[dict]) -> float:
    """The last training loss of a loop history (evaluation-only rows have none)."""
    return float([h["loss"] for h in history if "loss" in h][-1])


def toktalk_model(prepared, steps: int, path: str | None, seed: int = 0):
    """TokTalk ``small`` after ``steps`` stage-1 steps of its recipe on the prepared corpus ``prepared``
    (2-s windows, no EMA), or loaded from ``path``."""
    cfg = tt.TokTalkConfig.small()
    like = jax.eval_shape(lambda k: tt.init_params(cfg, k), jax.random.key(0))
    if path and Path(path).is_file():
        return cfg, _load(Path(path), like), {"loaded": path}
    t0 = time.perf_counter()
    optim = OptimConfig(lr=5e-4, warmup_steps=min(50, steps // 5), total_steps=steps, weight_decay=0.0)
    run = RunSettings(steps=steps, batch_size=16, seed=seed, window_frames=WINDOW,
                      loop=LoopSettings(progress=False, log_every=max(1, steps // 5)))
    result = toktalk_recipe.train(cfg, prepared, optim, key=jax.random.key(seed), run=run)
    params = result.state.eval_params
    if path:
        _save(Path(path), params)
    return cfg, params, {"train_steps": steps, "train_s": time.perf_counter() - t0,
                         "final_loss": _last_loss(result.history)}


def ats_model(prepared, steps: int, path: str | None, seed: int = 0) -> tuple[FittedATS, dict]:
    """ATS ``small`` (standardised displacements) after ``steps`` steps of its recipe on the prepared
    corpus (2-s windows), or loaded from ``path``; the standardisation is the recipe's (training split)."""
    cfg = ATSConfig.small(max_frames=WINDOW, displacement_scale=1.0)
    stats = freetalk_recipe.fit_displacement_stats(prepared)
    if path and Path(path).is_file():
        like = jax.eval_shape(lambda k: ats.init_params(cfg, k), jax.random.key(0))
        return FittedATS(cfg, _load(Path(path), like), stats, []), {"loaded": path}
    t0 = time.perf_counter()
    optim = OptimConfig(lr=1e-3, warmup_steps=min(100, steps // 10), total_steps=steps)
    run = RunSettings(steps=steps, batch_size=16, seed=seed, window_frames=WINDOW,
                      loop=LoopSettings(log_every=max(1, steps // 20)))
    result = freetalk_recipe.train_ats(cfg, prepared, optim, key=jax.random.key(seed), run=run)
    fitted = FittedATS(cfg, result.state.eval_params, stats, result.history)
    if path:
        _save(Path(path), fitted.params)
    return fitted, {"train_steps": steps, "train_s": time.perf_counter() - t0,
                    "final_loss": _last_loss(fitted.history)}


# ---- problems ---------------------------------------------------------------------------------------


def held_out_clips(corpus, count: int) -> list[int]:
    clips = [c for c in corpus.split("val") + corpus.split("test") if corpus.clips[c].num_frames >= WINDOW]
    if len(clips) < count:
        clips = [c for c in corpus.split("train") if corpus.clips[c].num_frames >= WINDOW] + clips
    return clips[:count]


def euler_problem(corpus, cfg, params, batch: int, seed: int = 0) -> dict[str, Any]:
    """Tokens, real motion and fixed noise of ``batch`` held-out 2 s clips; the encoder's styles."""
    clips = held_out_clips(corpus, batch)
    per_token = int(cfg.fps / cfg.token_rate)
    tokens = np.stack([np.asarray(corpus.tokens(c, "A").embeddings, np.float32)[: WINDOW // per_token]
                       for c in clips])
    motion = np.stack([np.asarray(corpus.motion(c), np.float32)[:WINDOW] for c in clips])
    noise = np.random.default_rng(seed).normal(size=motion.shape).astype(np.float32)
    return {"clips": clips, "tokens": tokens, "motion": motion, "noise": noise,
            "encoded": np.asarray(tt.encode_style(params, cfg, motion))}


def ddim_problem(corpus, fitted: FittedATS, batch: int, seed: int = 0) -> dict[str, Any]:
    """Audio, labels and standardised real landmark clips of ``batch`` held-out windows; fixed noise."""
    windows = data.ats_windows(corpus, held_out_clips(corpus, batch), window=WINDOW, hop=WINDOW)
    idx = np.arange(min(batch, len(windows["clip"])))
    cond = ats.make_condition(fitted.config, windows["audio"][idx], windows["emotion"][idx], 1.0)
    target = np.asarray(fitted.stats.normalize(windows["displacements"][idx]), np.float32)
    noise = jax.random.normal(jax.random.key(seed), (len(idx), WINDOW, fitted.config.motion_dim))
    return {"cond": cond, "target": target, "noise": noise, "labels": windows["intensity"][idx],
            "emotions": windows["emotion"][idx], "clips": windows["clip"][idx]}


# ---- measurements -----------------------------------------------------------------------------------


def measure(fn: Callable, args: tuple, repeats: int) -> tuple[Any, Any, dict[str, float]]:
    """Compile (timed), read XLA's memory analysis, then time ``repeats`` runs.

    Returns:
        ``(compiled executable, its output on args, numbers)``.
    """
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    memory = compiled.memory_analysis()
    out = jax.block_until_ready(compiled(*args))  # warm-up, and the value we report
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    numbers = {"compile_s": compile_s, "run_s": statistics.median(runs),
               "temp_mib": (memory.temp_size_in_bytes / MIB) if memory is not None else float("nan")}
    return compiled, out, numbers


def gradient_rows(sampler: str, loss_at: Callable[[int, bool], Callable], x0: Array, direction: Array,
                  steps_list: list[int], eps: float, repeats: int) -> list[dict[str, Any]]:
    """One row per step count: FD agreement, gradient norm, time and memory of fwd / fwd+bwd (+-remat)."""
    rows = []
    for n in steps_list:
        loss = loss_at(n, False)
        # The forward program is the same with or without checkpointing: measured once, and its
        # executable also gives the finite differences.
        fwd, _, f_num = measure(loss, (x0,), repeats)
        _, (value, grad), g_num = measure(jax.value_and_grad(loss), (x0,), repeats)
        _, (_, grad_r), r_num = measure(jax.value_and_grad(loss_at(n, True)), (x0,), repeats)
        fd = (float(fwd(x0 + eps * direction)) - float(fwd(x0 - eps * direction))) / (2 * eps)
        dd = float(jnp.sum(grad * direction))
        rows.append({
            "sampler": sampler, "steps": n, "loss": float(value),
            "fd_rel_err": abs(dd - fd) / max(abs(fd), 1e-30),
            "remat_grad_rel_diff": float(jnp.linalg.norm(grad_r - grad) / jnp.linalg.norm(grad)),
            "grad_norm": float(jnp.linalg.norm(grad)),
            "fwd_ms": 1e3 * f_num["run_s"], "fwd_bwd_ms": 1e3 * g_num["run_s"],
            "fwd_bwd_remat_ms": 1e3 * r_num["run_s"],
            "fwd_temp_mib": f_num["temp_mib"], "fwd_bwd_temp_mib": g_num["temp_mib"],
            "fwd_bwd_remat_temp_mib": r_num["temp_mib"],
            "compile_fwd_s": f_num["compile_s"], "compile_fwd_bwd_s": g_num["compile_s"],
            "compile_fwd_bwd_remat_s": r_num["compile_s"],
        })
        print(f"  {sampler} {n:>2} steps done", flush=True)
    return rows


def summary(res) -> str:
    """The distinct optimistix results of a batch of inversions, e.g. ``"successful"``."""
    return ",".join(sorted(set(res.results)))


def timed(fn: Callable, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    jax.block_until_ready(out.value)
    return out, time.perf_counter() - t0


def style_inversion_rows(cfg, params, prob: dict[str, Any], sample_steps: int) -> list[dict[str, Any]]:
    """Known style (encoder estimate of clip i) -> target sample; invert from clip i+1's estimate."""
    tokens, noise, enc = prob["tokens"], prob["noise"], prob["encoded"]
    true_style = enc
    start = np.roll(enc, 1, axis=0)  # another clip's (another speaker's, mostly) estimate
    target = np.asarray(tt.sample(params, cfg, tokens, true_style, noise=noise, sample_steps=sample_steps))
    encoder_on_target = np.asarray(tt.encode_style(params, cfg, target))
    rows = []

    def row(case, res, seconds, truth, note=""):
        value = np.asarray(res.value)
        err = (np.linalg.norm(value - truth, axis=1) / np.linalg.norm(truth, axis=1)) if truth is not None else None
        return {"problem": "style (Euler+CFG)", "case": case, "solver": note, "result": summary(res),
                "steps": int(np.max(res.steps)), "time_s": seconds,
                "rel_err_mean": None if err is None else float(err.mean()),
                "rel_err_max": None if err is None else float(err.max()),
                "start_loss": float(np.mean(res.init_loss)), "final_loss": float(np.mean(res.loss))}

    for solver in ("levenberg_marquardt", "bfgs"):
        # BFGS is capped low: on these ill-conditioned problems it needs many more steps than LM.
        kwargs = dict(init=start, sample_steps=sample_steps, solver=solver, on_failure="return",
                      max_steps=100 if solver == "levenberg_marquardt" else 50)
        res, first = timed(invert_style, params, cfg, tokens, target, noise, **kwargs)
        rows.append(row("sampled target, other clip's style as start", res, first, true_style, solver)
                    | {"time_includes_compile": True})
    enc_err = np.linalg.norm(encoder_on_target - true_style, axis=1) / np.linalg.norm(true_style, axis=1)
    enc_loss = np.asarray(style_loss(params, cfg, tokens, target, noise, encoder_on_target, sample_steps=sample_steps))
    rows.append({"problem": "style (Euler+CFG)", "case": "sampled target: style encoder's estimate",
                 "solver": "encoder", "rel_err_mean": float(enc_err.mean()), "rel_err_max": float(enc_err.max()),
                 "final_loss": float(enc_loss.mean())})
    # Real clips: no true vector; does the inverted style reproduce the clip better than the encoder's?
    res, seconds = timed(invert_style, params, cfg, tokens, prob["motion"], noise, sample_steps=sample_steps,
                         on_failure="return", max_steps=30)
    rows.append(row("real clip, start = encoder", res, seconds, None, "levenberg_marquardt"))
    return rows


def intensity_inversion_rows(fitted: FittedATS, prob: dict[str, Any], sample_steps: int) -> list[dict[str, Any]]:
    cfg, params = fitted.config, fitted.params
    b = prob["target"].shape[0]
    truth = np.linspace(1.0, float(cfg.num_intensities), b).astype(np.float32)
    cond_true = prob["cond"]._replace(intensity=jnp.asarray(truth))
    target = np.asarray(sample_ats_from_noise(params, cfg, cond_true, prob["noise"], sample_steps=sample_steps))
    rows = []
    res, first = timed(invert_intensity, params, cfg, prob["cond"], target, prob["noise"], sample_steps=sample_steps,
                       on_failure="return")
    res, second = timed(invert_intensity, params, cfg, prob["cond"], target, prob["noise"], sample_steps=sample_steps,
                        on_failure="return")
    value = np.asarray(res.value)
    rows.append({"problem": "intensity (DDIM)", "case": "sampled target, segment-midpoint starts",
                 "result": summary(res), "steps": int(np.max(res.steps)), "time_s": second, "first_call_s": first,
                 "true": truth.round(3).tolist(), "recovered": value.round(4).tolist(),
                 "abs_err_max": float(np.max(np.abs(value - truth))),
                 "start_loss": float(np.mean(res.init_loss)), "final_loss": float(np.mean(res.loss))})
    res, seconds = timed(invert_intensity, params, cfg, prob["cond"], prob["target"], prob["noise"],
                         sample_steps=sample_steps, on_failure="return")
    value, labels = np.asarray(res.value), np.asarray(prob["labels"])
    corr = float(np.corrcoef(value, labels)[0, 1]) if np.std(labels) > 0 and np.std(value) > 0 else float("nan")
    rows.append({"problem": "intensity (DDIM)", "case": "real clips vs labelled level", "result": summary(res),
                 "steps": int(np.max(res.steps)), "time_s": seconds, "true": labels.tolist(),
                 "recovered": value.round(3).tolist(), "abs_err_max": float(np.max(np.abs(value - labels))),
                 "abs_err_mean": float(np.mean(np.abs(value - labels))), "pearson_r": corr,
                 "start_loss": float(np.mean(res.init_loss)), "final_loss": float(np.mean(res.loss))})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="tiny", help="SynthTalk corpus size")
    parser.add_argument("--steps", type=int, nargs="*", default=[1, 5, 10, 20],
                        help="sampler step counts of the gradient table (none: skip the table)")
    parser.add_argument("--toktalk-train-steps", type=int, default=300)
    parser.add_argument("--ats-train-steps", type=int, default=600)
    parser.add_argument("--toktalk-params", default=None,
                        help=".npz to load, or to write after training (default: a cache file under results/)")
    parser.add_argument("--ats-params", default=None,
                        help=".npz to load, or to write after training (default: a cache file under results/)")
    parser.add_argument("--batch", type=int, default=2, help="clips per gradient problem")
    parser.add_argument("--inversion-batch", type=int, default=2)
    parser.add_argument("--inversion-euler-steps", type=int, default=5)
    parser.add_argument("--inversion-ddim-steps", type=int, default=10)
    parser.add_argument("--fd-eps", type=float, default=1e-2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-inversion", action="store_true")
    parser.add_argument("--out", default=str(RESULTS / "sampler_gradients.json"))
    args = parser.parse_args()
    t_start = time.perf_counter()

    corpus = load_corpus(args.size)
    # The same corpus prepared for the recipes (features once; the in-memory corpus above gives the
    # held-out problems).
    prepared = open_data(f"synthtalk:{args.size}", cache_dir=DATA)
    cache = RESULTS / "sampler_gradients_cache"
    # The presets' fingerprint is part of the cache name: a changed preset must not load old weights
    # ("recipe": weights of the recipes' training, not of the earlier in-memory windows).
    tag = hashlib.sha1(repr((tt.TokTalkConfig.small(), ATSConfig.small(), "recipe")).encode()).hexdigest()[:8]
    args.toktalk_params = args.toktalk_params or str(
        cache / f"toktalk-small-{args.size}-s{args.toktalk_train_steps}-{tag}.npz")
    args.ats_params = args.ats_params or str(cache / f"ats-small-{args.size}-s{args.ats_train_steps}-{tag}.npz")
    print("training / loading models ...", flush=True)
    tcfg, tparams, tinfo = toktalk_model(prepared, args.toktalk_train_steps, args.toktalk_params)
    fitted, ainfo = ats_model(prepared, args.ats_train_steps, args.ats_params)
    print(f"  TokTalk {tinfo}\n  ATS {ainfo}", flush=True)
    rng = np.random.default_rng(0)

    # Euler + CFG: loss of the style vector at the encoder's estimate for real clips.
    ep = euler_problem(corpus, tcfg, tparams, args.batch)
    s0 = jnp.asarray(ep["encoded"])
    s_dir = jnp.asarray(rng.normal(size=s0.shape).astype(np.float32))
    s_dir = s_dir / jnp.linalg.norm(s_dir)

    def euler_loss(n: int, remat: bool):
        return lambda s: jnp.sum(style_loss(tparams, tcfg, ep["tokens"], ep["motion"], ep["noise"], s,
                                            sample_steps=n, remat=remat))

    # DDIM: loss of the per-clip intensity between the integer levels (the embedding's kinks).
    dp = ddim_problem(corpus, fitted, args.batch)
    i0 = jnp.asarray(np.linspace(1.3, 2.7, dp["target"].shape[0]).astype(np.float32))
    i_dir = jnp.asarray(np.where(np.arange(i0.shape[0]) % 2 == 0, 1.0, -1.0).astype(np.float32))
    i_dir = i_dir / jnp.linalg.norm(i_dir)

    def ddim_loss(n: int, remat: bool):
        return lambda i: jnp.sum(intensity_loss(fitted.params, fitted.config, dp["cond"], dp["target"], dp["noise"],
                                                i, sample_steps=n, remat=remat))

    payload = {
        "machine": machine_info(),
        "args": vars(args),
        "models": {"toktalk": tinfo, "ats": ainfo},
        "memory_measure": "XLA compiled memory_analysis().temp_size_in_bytes (MiB), same executables as timed",
        "fd": f"central differences in float32, eps={args.fd_eps}, unit random direction; relative error of "
              "the directional derivative",
    }
    rows = []
    if args.steps:
        print("gradients ...", flush=True)
        rows = gradient_rows("Euler+CFG (TokTalk small)", euler_loss, s0, s_dir, args.steps, args.fd_eps, args.repeats)
        rows += gradient_rows("DDIM (ATS small)", ddim_loss, i0, i_dir, args.steps, args.fd_eps, args.repeats)
        write_json(args.out, payload | {"gradients": rows})  # kept even if the inversions are cut short
        print_table([{k: r[k] for k in ("sampler", "steps", "fd_rel_err", "remat_grad_rel_diff", "grad_norm", "fwd_ms",
                                    "fwd_bwd_ms", "fwd_bwd_remat_ms", "fwd_temp_mib", "fwd_bwd_temp_mib",
                                    "fwd_bwd_remat_temp_mib")} for r in rows],
                    "Gradients through the samplers (float32; memory = XLA temp bytes of the compiled call)")
        print_table([{k: r[k] for k in ("sampler", "steps", "compile_fwd_s", "compile_fwd_bwd_s",
                                        "compile_fwd_bwd_remat_s")} for r in rows], "Compile times")

    inversion = []
    if not args.skip_inversion:
        print("inversion ...", flush=True)
        ip = euler_problem(corpus, tcfg, tparams, args.inversion_batch, seed=1)
        inversion += style_inversion_rows(tcfg, tparams, ip, args.inversion_euler_steps)
        dq = ddim_problem(corpus, fitted, args.inversion_batch + 1, seed=1)
        inversion += intensity_inversion_rows(fitted, dq, args.inversion_ddim_steps)
        print_table([{k: r.get(k) for k in ("problem", "case", "solver", "result", "steps", "time_s",
                                            "rel_err_mean", "rel_err_max", "abs_err_max", "start_loss", "final_loss")}
                     for r in inversion], "Inversion through the samplers (truth known where an error is given)")
        for r in inversion:
            if "recovered" in r:
                print(f"  {r['case']}: true {r['true']} -> recovered {r['recovered']}")

    payload |= {"gradients": rows, "inversion": inversion, "total_s": time.perf_counter() - t_start}
    path = write_json(args.out, payload)
    print(f"wrote {path} ({payload['total_s']:.0f} s)")


if __name__ == "__main__":
    main()
