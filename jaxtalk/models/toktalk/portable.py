"""TokTalk's live stream as ONNX graphs that a host runs without Python (``jaxtalk export-model``).

The stream a :class:`~jaxtalk.models.toktalk.live.LiveModel` runs is cut into three fixed-shape graphs, each
the same JAX computation the live model runs, converted by ``jax2onnx`` (:func:`jaxtalk.export.onnx.write_onnx`):

* ``frontend.onnx`` (runs with a tokenizer): one group of ``chunk_tokens`` tokens from its audio window
  (:func:`jaxtalk.audio.tokenizer.group_tokens`: log-mel, pooling, the noise-floor normaliser with its
  history as state, the nearest centroid and its embedding);
* ``step.onnx``: one chunk of the streaming engine (:func:`~jaxtalk.models.toktalk.streaming.advance_window`:
  the Euler sampler with guidance over the fixed window, the overlap inpainted), the window as explicit
  state. The starting noise is an input: the stream's noise of a frame is white noise smoothed over its
  neighbours (:func:`~jaxtalk.models.toktalk.noise.frame_noise`), so the graph carries the white noise of
  the window and the ``noise_frames``-wide margins (``white``) and takes that of ``chunk_frames`` new frames
  per call (``white_chunk``, for absolute frames ``position + white_lead_frames ..``). Fed the stream key's
  white noise (:func:`~jaxtalk.models.toktalk.noise.frame_white_noise`) it gives exactly
  :func:`~jaxtalk.models.toktalk.streaming.stream`'s frames; fed any standard normal noise, a stream of the
  same model;
* ``morph.onnx``: head parameters -> the values that pose the built-in face's ``face.glb``
  (:func:`jaxtalk.export.face_model_morph`).

``manifest.json`` says everything a host needs (shapes, rates, the window layout, each state's initial
value); :mod:`jaxtalk.export.onnx_host` is the reference host. Not exported: source-space tokens through the
adaptation layer (export the base-token stream and adapt on the host), and the ARKit output (the converter
did not finish converting the retargeting solver's Newton loop: docs/onnx.md).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxtalk.files import atomic_write_json
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.live import LiveModel
from jaxtalk.models.toktalk.noise import noise_kernel, smooth_noise
from jaxtalk.models.toktalk.sampling import default_grid
from jaxtalk.models.toktalk.streaming import advance_window, tokens_per_chunk
from jaxtalk.types import Array, Bool, Float

__all__ = ["PortableLayout", "portable_layout", "portable_step", "export_stream"]

PyTree = Any


@dataclasses.dataclass(frozen=True)
class PortableLayout:
    """The fixed shapes of the exported step (batch 1).

    Attributes:
        window_frames: frames of the window (left context + chunk).
        window_tokens: tokens of the window.
        chunk_tokens: tokens per chunk.
        margin: frames of white noise each side of the window that its smoothing reads.
        white_frames: frames of the carried white noise, ``window_frames + 2 * margin``.
        white_lead_frames: a chunk's new white noise starts this many frames after its first frame.
        white_first_frame: the absolute frame of the carried white noise's first row before chunk 0.
    """

    window_frames: int
    window_tokens: int
    chunk_tokens: int
    margin: int
    white_frames: int
    white_lead_frames: int
    white_first_frame: int


def portable_layout(config: TokTalkConfig) -> PortableLayout:
    """The shapes of ``config``'s exported step.

    Before the chunk starting at frame ``p`` the carried white noise holds frames ``p - context - margin -
    chunk ..`` (one chunk behind); the chunk moves it on by ``chunk_frames`` new frames, ``p + margin ..``."""
    w, c, ctx = config.window_frames, config.chunk_frames, config.context_frames
    r = (noise_kernel(config.noise_frames).shape[0] - 1) // 2
    return PortableLayout(window_frames=w, window_tokens=tokens_per_chunk(config, w),
                          chunk_tokens=tokens_per_chunk(config), margin=r, white_frames=w + 2 * r,
                          white_lead_frames=r, white_first_frame=-ctx - r - c)


def portable_step(
    params: PyTree,
    config: TokTalkConfig,
    style_vec: Float[Array, "1 vector"],
    ts: Float[Array, " grid"],
    tokens: Float[Array, "1 window_tokens token"],
    motion: Float[Array, "1 window param"],
    valid: Bool[Array, "1 window"],
    white: Float[Array, "1 white param"],
    chunk_tokens: Float[Array, "1 chunk_tokens token"],
    white_chunk: Float[Array, "1 chunk param"],
    cfg_scale: Float[Array, ""],
    temperature: Float[Array, ""],
) -> tuple[Float[Array, "1 chunk param"], Float[Array, "1 window_tokens token"], Float[Array, "1 window param"],
           Bool[Array, "1 window"], Float[Array, "1 white param"]]:
    """One chunk of the stream with its noise as an input (what ``step.onnx`` computes; see the module).

    Returns:
        ``(params, tokens, motion, valid, white)``: the chunk's head parameters and the state after it.
    """
    white = jnp.concatenate([white[:, config.chunk_frames:], white_chunk], axis=1)
    noise = temperature * smooth_noise(white, config.noise_frames)
    tokens, motion, valid, out = advance_window(params, config, tokens, motion, valid, chunk_tokens, style_vec, noise,
                                                cfg_scale, ts)
    return out, tokens, motion, valid, white


def _step_graph(model: LiveModel, ts: np.ndarray) -> tuple[Any, list[dict], list[str]]:
    from jaxtalk.export.onnx import io_spec

    config = model.config
    layout = portable_layout(config)
    d, width = config.param_dim, config.speech_dim
    style_vec = jnp.asarray(model.style, jnp.float32)
    inputs = [
        io_spec("tokens", (1, layout.window_tokens, width), np.float32, init="zeros"),
        io_spec("motion", (1, layout.window_frames, d), np.float32, init="zeros"),
        io_spec("valid", (1, layout.window_frames), np.bool_, init="zeros"),
        io_spec("white", (1, layout.white_frames, d), np.float32, init="white", first_frame=layout.white_first_frame),
        io_spec("chunk_tokens", (1, layout.chunk_tokens, width), np.float32),
        io_spec("white_chunk", (1, config.chunk_frames, d), np.float32),
        io_spec("cfg_scale", (), np.float32),
        io_spec("temperature", (), np.float32),
    ]
    outputs = ["params", "next_tokens", "next_motion", "next_valid", "next_white"]

    def fn(tokens, motion, valid, white, chunk_tokens, white_chunk, cfg_scale, temperature):
        return portable_step(model.params, config, style_vec, jnp.asarray(ts, jnp.float32), tokens, motion, valid, white,
                             chunk_tokens, white_chunk, cfg_scale, temperature)

    return fn, inputs, outputs


def _frontend_graph(model: LiveModel) -> tuple[Any, list[dict], list[str], dict]:
    from jaxtalk.audio.tokenizer import group_tokens
    from jaxtalk.export.onnx import io_spec

    tokenizer = model.tokenizer
    layout = tokenizer.stream(tokens_per_chunk(model.config)).layout()
    inputs = [io_spec("audio", (layout.window_samples,), np.float32)]
    outputs = ["ids", "tokens"]
    past = tokenizer.floor_window - 1 if tokenizer.floor_window else 0
    if past:
        inputs.append(io_spec("history", (past, tokenizer.n_mels), np.float32, init="inf"))
        outputs.append("next_history")

    def fn(audio, history=None):
        ids, embeddings, history = group_tokens(tokenizer, layout, audio, history)
        return (ids, embeddings) if history is None else (ids, embeddings, history)

    window = {"window_samples": layout.window_samples, "hop_samples": layout.hop_samples,
              "offset_samples": layout.offset_samples, "lookahead_samples": layout.lookahead_samples}
    return fn, inputs, outputs, window


def export_stream(
    model: LiveModel, out: str | os.PathLike, *, run_name: str = "", face: Any = None,
) -> dict[str, Any]:
    """Write ``model``'s stream as ONNX graphs and ``manifest.json`` into the folder ``out`` (see the module),
    with the reference host (``host.py``) and, for ``face`` (default: the built-in face), ``morph.onnx`` and
    ``face.glb``.

    Args:
        model: the live model (its style vector, guidance weight, time grid and temperature are the export's).
        out: the folder (created; files in it are replaced one by one, each atomically).
        run_name: recorded in the manifest.
        face: the face the morph graph poses (None: the built-in face).

    Returns:
        The manifest.

    Raises:
        ValueError: a model whose chunks are not whole log-mel hops of its tokenizer.
        ImportError: jax2onnx is not installed.
    """
    # The export package (glTF, rigs) loads only when a stream is exported, not with the model.
    import jaxtalk.export
    from jaxtalk.export import export_face_model, face_model_morph, face_model_targets
    from jaxtalk.export.onnx import MANIFEST_FORMAT, io_spec, write_onnx
    from jaxtalk.face import builtin_face

    config = model.config
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    layout = portable_layout(config)
    ts = np.asarray(default_grid(config) if model.ts is None else model.ts, np.float32)
    manifest: dict[str, Any] = {
        "format": MANIFEST_FORMAT[0], "version": MANIFEST_FORMAT[1], "model": "toktalk", "run": run_name,
        "sample_rate": model.sample_rate, "fps": config.fps, "chunk_frames": config.chunk_frames,
        "chunk_samples": model.chunk_samples, "token_rate": float(config.token_rate), "chunk_tokens": layout.chunk_tokens,
        "token_width": config.speech_dim, "param_dim": config.param_dim,
        "params": "[exp 50 | jaw 3 | neck 3]: expression coefficients, then jaw and neck rotations (axis-angle, radians)",
        "sample_steps": int(ts.shape[0] - 1),
        "cfg_scale": float(config.cfg_scale if model.cfg_scale is None else model.cfg_scale),
        "temperature": float(config.temperature if model.temperature is None else model.temperature),
        "white_lead_frames": layout.white_lead_frames,
        "noise": ("white_chunk: standard normal noise of the chunk's new frames, independent per frame and "
                  "channel; the initial 'white' state likewise (frames from first_frame on)"),
    }
    if model.tokenizer is not None:
        fn, inputs, outputs, window = _frontend_graph(model)
        write_onnx(fn, inputs, outputs, out / "frontend.onnx")
        manifest["frontend"] = {"file": "frontend.onnx", **window, "inputs": inputs, "outputs": outputs}
    else:
        manifest["frontend"] = None  # tokens from the run's own encoder, at token_rate
    fn, inputs, outputs = _step_graph(model, ts)
    write_onnx(fn, inputs, outputs, out / "step.onnx")
    manifest["step"] = {"file": "step.onnx", "inputs": inputs, "outputs": outputs}
    face = builtin_face(0) if face is None else face
    channels = [*face_model_targets(face), *(f"{j}.q{c}" for j in ("jaw", "neck") for c in "xyzw")]
    morph_inputs = [io_spec("params", (config.chunk_frames, config.param_dim), np.float32)]
    write_onnx(lambda params: (face_model_morph(face, params),), morph_inputs, ["morph"], out / "morph.onnx")
    export_face_model(face, np.zeros((1, config.param_dim), np.float32), out / "face.glb", name="rest")
    k = len(channels) - 8
    manifest["morph"] = {"file": "morph.onnx", "face": "face.glb", "frames": config.chunk_frames, "channels": channels,
                         "quaternions": [k, k + 4], "joints": ["jaw", "neck"], "inputs": morph_inputs,
                         "outputs": ["morph"]}
    # The reference host (imports onnxruntime, which the export itself does not need): copied as a file.
    shutil.copyfile(Path(jaxtalk.export.__file__).with_name("onnx_host.py"), out / "host.py")
    atomic_write_json(out / "manifest.json", manifest)
    return manifest
