"""Which of the other models' inference steps convert to ONNX, and with what error.

Each candidate is the traced core the library runs (no host checks), with random weights of a small
configuration, converted by :func:`jaxtalk.export.onnx.write_onnx` (jax2onnx) exactly as TokTalk's stream is, then
run by onnxruntime on the same inputs as JAX:

* ``timar_stream_step``: one turn of TIMAR's streaming engine (:mod:`jaxtalk.models.timar.streaming`, the
  filling mode, 5 DDIM steps with the initial noise given, eta 0, guidance on);
* ``ats_sample``: FreeTalk's landmark diffusion (DDIM, 4 steps, the starting noise given, eta 0) on 100 frames;
* ``ats_denoiser``: one call of ATS's denoising transformer (no sampler);
* ``stm_decode``: Sparse-To-Mesh on the built-in face (low resolution), 10 frames of landmark motion, the
  mesh's precomputed DiffusionNet operators as constants.

For each: converted or not (the converter's first error line), and where converted the largest difference
between onnxruntime's output and JAX's, and the largest value.

Usage: python experiments/onnx_other_models.py [--out experiments/results/onnx_other_models.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk import benchmarking as bm


def timar_stream_step():
    from jaxtalk.models.timar import spec
    from jaxtalk.models.timar.config import TimarConfig
    from jaxtalk.models.timar.streaming import _mode, _step, init_stream

    config = TimarConfig(width=32, num_layers=1, num_heads=2, head_width=32, head_blocks=1, max_turns=2)
    params = spec.SPEC.init_params(config, jax.random.key(0))
    state = init_stream(config, jax.random.key(1), context=1)
    mode = _mode(config, state)
    leaves, tree = jax.tree.flatten(state)
    key_data = jax.random.key_data(leaves[-1])
    f = config.frames_per_turn
    rng = np.random.default_rng(0)
    args = [*[np.asarray(x) for x in leaves[:-1]], np.asarray(key_data),
            rng.standard_normal((1, f, config.speech_dim)).astype(np.float32),
            0.1 * rng.standard_normal((1, f, config.param_dim)).astype(np.float32),
            rng.standard_normal((1, f, config.speech_dim)).astype(np.float32),
            rng.standard_normal((1, f, config.param_dim)).astype(np.float32)]

    def fn(*a):
        st = jax.tree.unflatten(tree, [*a[: len(leaves) - 1], jax.random.wrap_key_data(a[len(leaves) - 1])])
        us, um, as_, initial = a[len(leaves):]
        _, x = _step.__wrapped__(params, config, st, us, um, as_, jnp.float32(1.0), jnp.float32(0.0), jnp.float32(1.0),
                                 5, "ddim", True, mode, initial, None)
        return (x,)

    return fn, args


def _ats():
    """A small ATS with random weights and the condition of 2 s of random features."""
    from jaxtalk.models.freetalk import ats
    from jaxtalk.models.freetalk.config import ATSConfig

    config = ATSConfig(width=32, num_layers=1, num_heads=2, ff_dim=32)
    params = ats.init_params(config, jax.random.key(0))
    rng = np.random.default_rng(0)
    audio = rng.standard_normal((1, 100, config.speech_dim)).astype(np.float32)
    cond = ats.make_condition(config, audio, "neutral", 1.0)
    motion = rng.standard_normal((*cond.mask.shape, config.motion_dim)).astype(np.float32)
    return ats, config, params, cond, motion


def ats_sample():
    ats, config, params, cond, noise = _ats()
    leaves, tree = jax.tree.flatten(cond)

    def fn(*a):
        c = jax.tree.unflatten(tree, list(a[:-1]))
        return (ats.sample(params, config, c, None, noise=a[-1], sample_steps=4),)

    return fn, [*[np.asarray(x) for x in leaves], noise]


def ats_denoiser():
    ats, config, params, cond, x = _ats()
    leaves, tree = jax.tree.flatten(cond)

    def fn(*a):
        c = jax.tree.unflatten(tree, list(a[:-2]))
        return (ats.ats_denoise(params, config, a[-2], a[-1], c),)

    return fn, [*[np.asarray(v) for v in leaves], x, np.full((1,), 500.0, np.float32)]


def stm_decode():
    from jaxtalk.face import builtin_face
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.config import STMConfig

    config = STMConfig.small()
    face = builtin_face(0, resolution="low")
    mesh = stm.prepare_mesh(np.asarray(face.template), np.asarray(face.faces), config)
    params = stm.init_params(config, jax.random.key(0), mesh)
    features = stm.stm_mesh_features(params, config, mesh)
    disp = 0.002 * np.random.default_rng(0).standard_normal((10, config.num_landmarks, 3)).astype(np.float32)

    def fn(d):
        return (stm._decode(params, config, features, d, mesh.ops),)

    return fn, [disp]


CANDIDATES = {"timar_stream_step": timar_stream_step, "ats_sample": ats_sample, "ats_denoiser": ats_denoiser,
              "stm_decode": stm_decode}


def probe(name: str, folder: Path) -> dict:
    import onnxruntime

    from jaxtalk.export.onnx import io_spec, write_onnx

    fn, args = CANDIDATES[name]()
    want = [np.asarray(x) for x in jax.jit(fn)(*args)]
    inputs = [io_spec(f"input{i}", np.shape(a), np.asarray(a).dtype) for i, a in enumerate(args)]
    try:
        write_onnx(fn, inputs, [f"result{i}" for i in range(len(want))], folder / f"{name}.onnx")
    except Exception as error:  # the converter's refusal is the result
        frames = [f for f in traceback.extract_tb(error.__traceback__) if "jaxtalk" in f.filename]
        return {"converted": False, "error": f"{type(error).__name__}: {str(error).splitlines()[0]}",
                "in": f"{frames[-1].filename.split('jaxtalk/')[-1]}:{frames[-1].lineno}" if frames else None}
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    try:
        session = onnxruntime.InferenceSession(str(folder / f"{name}.onnx"), options)
        got = session.run(None, {spec["name"]: np.asarray(a) for spec, a in zip(inputs, args)})
    except Exception as error:
        return {"converted": True, "runs": False, "error": f"{type(error).__name__}: {str(error).splitlines()[0]}"}
    return {"converted": True, "runs": True,
            "max_abs_diff": max(float(np.abs(g - w).max()) for g, w in zip(got, want)),
            "max_abs_value": max(float(np.abs(w).max()) for w in want)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("experiments/results/onnx_other_models.json"))
    args = parser.parse_args()
    from importlib.metadata import version

    import onnxruntime

    results = {}
    with tempfile.TemporaryDirectory() as scratch:
        for name in CANDIDATES:
            results[name] = probe(name, Path(scratch))
            print(name, json.dumps(results[name]))
    bm.print_table([{"core": name, "converts": r["converted"], "runs": r.get("runs"), "max |diff|": r.get("max_abs_diff"),
                     "error": r.get("error", "")[:90]} for name, r in results.items()], "Other models through jax2onnx")
    bm.write_json(args.out, {"jax2onnx": version("jax2onnx"),
                             "onnxruntime": onnxruntime.__version__, "models": results})
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
