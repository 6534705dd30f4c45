"""Face-model fitting benchmark: recovery errors and timings of ``jaxtalk.fit`` on the built-in face.

For landmarks, full vertices and a decimated topology variant, in the three modes, at several noise
levels: a smooth ground-truth clip in the parameters the observations determine
(``identifiable_params``) is rendered to geometry, noise is added, and the fit is compared with the
truth (parameter max error, geometry RMS against the clean geometry). Timings are of the jitted core
(compile and run separately, median of repeats, ``block_until_ready``) via ``jaxtalk.benchmarking``.

    python experiments/fit_face.py [--frames 25] [--resolution low] [--out experiments/results/fit_face.json]
"""

from __future__ import annotations

import argparse
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.benchmarking import print_table, time_jitted, write_json
from jaxtalk.face import builtin_face
from jaxtalk.fit import FitConfig, fit_landmarks, fit_vertices, identifiable_params
from jaxtalk.fit import face_fit
from jaxtalk.geometry.topology import make_variant


def smooth_clip(num_frames: int, keep: np.ndarray, seed: int) -> np.ndarray:
    """A slow random clip (a few sinusoids per parameter) in the ``keep`` components."""
    rng = np.random.default_rng(seed)
    t = np.arange(num_frames)[:, None] / 25.0
    amp = np.concatenate([0.5 * np.ones(50), 0.08 * np.ones(6)])
    p = amp * sum(np.sin(2 * np.pi * (f * t + rng.uniform(size=56))) / k for k, f in enumerate((0.4, 1.1, 2.3), 1))
    p[:, np.setdiff1d(np.arange(56), keep)] = 0.0
    return p


def core_timing(model, surface, target, weights, config, kind, repeats):
    """Compile and run time of the jitted solve for one input."""
    init = jnp.zeros((target.shape[0], 56), target.dtype)
    fn = functools.partial(face_fit._fit_core, config=config, kind=kind)
    args = (model, surface, target, weights, init, jnp.full(56, 1e-4, target.dtype), jnp.asarray(0.3, target.dtype))
    return time_jitted(fn, *args, repeats=repeats, warmup=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=25)
    parser.add_argument("--resolution", default="low")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="experiments/results/fit_face.json")
    args = parser.parse_args()

    model = builtin_face(0, resolution=args.resolution)
    variant = make_variant(np.asarray(model.template), np.asarray(model.faces), "decimated", seed=0)
    rows = []
    for source in ("landmarks", "vertices", "variant"):
        active = identifiable_params(model, target="landmarks" if source == "landmarks" else "vertices")
        truth = smooth_clip(args.frames, active, seed=0)
        if source == "landmarks":
            clean = np.asarray(model.landmarks_seq(jnp.asarray(truth, jnp.float32)))
        else:
            clean = np.asarray(model.vertices_seq(jnp.asarray(truth, jnp.float32)))
            if source == "variant":
                clean = variant.transfer(clean)
        rng = np.random.default_rng(1)
        noise = rng.normal(size=clean.shape).astype(np.float32)
        for mode in ("independent", "sequential", "joint"):
            config = FitConfig(mode=mode, active=tuple(active))
            for sigma_mm in (0.0, 0.5, 1.0, 2.0):
                smoothness = 0.0 if mode == "independent" else 0.3
                target = clean + 1e-3 * sigma_mm * noise
                kwargs = dict(config=config, smoothness=smoothness, prior=1e-4, on_failure="return")
                if source == "landmarks":
                    fit = fit_landmarks(model, target, **kwargs)
                    pred = model.landmarks_seq(fit.params)
                else:
                    fit = fit_vertices(model, target, variant=variant if source == "variant" else None, **kwargs)
                    pred = model.vertices_seq(fit.params)
                    if source == "variant":
                        pred = variant.transfer(np.asarray(pred))
                rows.append(
                    {
                        "source": source,
                        "mode": mode,
                        "noise_mm": sigma_mm,
                        "smoothness": smoothness,
                        "param_max_err": float(np.max(np.abs(np.asarray(fit.params) - truth))),
                        "geom_rms_mm": 1e3 * float(np.sqrt(np.mean((np.asarray(pred) - clean) ** 2))),
                        "fit_rms_mm": 1e3 * float(np.mean(np.asarray(fit.rms))),
                        "max_steps_taken": int(np.max(np.asarray(fit.steps))),
                        "converged": fit.all_converged,
                    }
                )
    print_table(rows, f"Fit recovery (built-in face '{args.resolution}', {args.frames} frames, float32)")

    timings = []
    for source in ("landmarks", "vertices", "variant"):
        for mode in ("independent", "sequential", "joint"):
            active = identifiable_params(model, target="landmarks" if source == "landmarks" else "vertices")
            truth = jnp.asarray(smooth_clip(args.frames, active, seed=0), jnp.float32)
            surface, kind = None, "vertices"
            if source == "landmarks":
                target, kind = model.landmarks_seq(truth), "landmarks"
            else:
                target = model.vertices_seq(truth)
                if source == "variant":
                    target = variant.transfer(target)
                    corners = variant.base_faces[variant.face_index]
                    surface = (jnp.asarray(corners, jnp.int32), jnp.asarray(variant.barycentric, jnp.float32))
                    kind = "surface"
            count = target.shape[1]
            weights = jnp.full((args.frames, count), 1.0 / np.sqrt(3.0 * count), jnp.float32)
            config = FitConfig(mode=mode, active=tuple(active))
            timing = core_timing(model, surface, target, weights, config, kind, args.repeats)
            timings.append(
                {
                    "source": source,
                    "mode": mode,
                    "frames": args.frames,
                    "points": count,
                    "compile_s": timing.compile_s,
                    "run_median_s": timing.run_median_s,
                    "ms_per_frame": 1e3 * timing.run_median_s / args.frames,
                }
            )
    print_table(timings, "Fit timings (jitted core; compile vs run)")
    path = write_json(args.out, {"recovery": rows, "timings": timings, "args": vars(args)})
    print(f"wrote {path}")


if __name__ == "__main__":
    jax.config.update("jax_numpy_rank_promotion", "raise")
    main()
