"""The reference host of an exported stream (``jaxtalk export-model RUN --format onnx``): the whole protocol a
host in another language implements, in Python on ``onnxruntime`` and NumPy alone.

This file imports nothing from jaxtalk; the export copies it into the folder as ``host.py``. Read it beside
the folder's ``manifest.json``:

* **Audio -> tokens** (``frontend.onnx``, when the run has a tokenizer): tokens come in groups of
  ``chunk_tokens``. Group ``n`` reads the ``window_samples`` samples that start at ``n * hop_samples +
  offset_samples`` of the utterance (zeros before its start and past its end) and can run once ``(n + 1) *
  hop_samples + lookahead_samples`` samples have arrived. The graph carries the noise-floor normaliser's
  ``history`` (initially ``+inf``).
* **Tokens -> motion** (``step.onnx``): one call per chunk of ``chunk_tokens`` tokens, giving
  ``chunk_frames`` frames of head parameters ``[exp 50 | jaw 3 | neck 3]`` (axis-angle radians). Its state
  (``tokens``, ``motion``, ``valid``, ``white``) goes back in as the next call's; each call also takes
  ``white_chunk``, fresh standard-normal noise for ``chunk_frames`` frames (any generator: the model only
  needs it independent per frame), and the guidance weight and the noise temperature as scalars.
* **End of an utterance** (:meth:`OnnxStream.finish`): the tokens not emitted yet (``ceil(samples *
  token_rate / sample_rate)`` in all, the audio padded with zeros), the last chunk completed by repeating the
  last token, the frames cropped to ``min(round(tokens * fps / token_rate), round(samples * fps /
  sample_rate))``; then every state starts afresh.
* **Params -> the face** (``morph.onnx``): the morph weights of ``face.glb`` and its jaw and neck rotations
  as glTF quaternions; keep each joint's quaternion on the side of the previous frame's (flip its sign when
  their dot product is negative).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnxruntime

__all__ = ["OnnxStream"]

# White noise of `frames` frames from absolute frame `first` on: (frames, param_dim) standard normal.
WhiteNoise = Callable[[int, int], np.ndarray]


def _initial(spec: dict, white: WhiteNoise | None = None) -> np.ndarray:
    """The first value of a state input, as the manifest's ``init`` says."""
    shape, dtype, init = tuple(spec["shape"]), np.dtype(spec["dtype"]), spec["init"]
    if init == "zeros":
        return np.zeros(shape, dtype)
    if init == "inf":
        return np.full(shape, np.inf, dtype)
    if init == "white":  # (1, frames, dim) from absolute frame spec["first_frame"] on
        return white(spec["first_frame"], shape[1])[None].astype(dtype)
    raise ValueError(f"unknown init {init!r} in the manifest")


class OnnxStream:
    """One stream of an exported model: :meth:`push` audio (or :meth:`push_tokens`), :meth:`finish` an
    utterance.

    Args:
        folder: the exported folder (``manifest.json`` and the graphs).
        white: the white noise of absolute frames (``white(first, frames) -> (frames, param_dim)``); default
            NumPy's generator seeded with ``seed``.
        seed: the default generator's seed.
        cfg_scale, temperature: override the manifest's.
        providers: onnxruntime execution providers (default CPU).
    """

    def __init__(self, folder: str | Path, *, white: WhiteNoise | None = None, seed: int = 0,
                 cfg_scale: float | None = None, temperature: float | None = None,
                 providers: tuple[str, ...] = ("CPUExecutionProvider",)):
        self.folder = Path(folder)
        if not (self.folder / "manifest.json").is_file():
            raise FileNotFoundError(f"{self.folder} holds no manifest.json: not a folder jaxtalk export-model wrote")
        self.manifest = m = json.loads((self.folder / "manifest.json").read_text())
        if m.get("format") != "jaxtalk-onnx-stream" or m.get("version") != 1:
            raise ValueError(f"{self.folder} holds no jaxtalk ONNX stream (format {m.get('format')!r}, "
                             f"version {m.get('version')!r})")
        options = onnxruntime.SessionOptions()
        options.log_severity_level = 3  # errors only, not notes on the graph's unused constants
        session = lambda name: onnxruntime.InferenceSession(str(self.folder / m[name]["file"]), options,  # noqa: E731
                                                            providers=list(providers))
        self.frontend = session("frontend") if m["frontend"] else None
        self.step = session("step")
        self.morph_graph = session("morph") if m["morph"] else None
        if white is None:
            rng = np.random.default_rng(seed)
            white = lambda first, frames: rng.standard_normal((frames, m["param_dim"]), np.float32)  # noqa: E731
        self.white = white
        self.cfg_scale = np.asarray(m["cfg_scale"] if cfg_scale is None else cfg_scale, np.float32)
        self.temperature = np.asarray(m["temperature"] if temperature is None else temperature, np.float32)
        self.reset()

    def reset(self) -> None:
        """Start a new utterance (every state afresh)."""
        m = self.manifest
        self.state = {s["name"]: _initial(s, self.white) for s in m["step"]["inputs"] if "init" in s}
        self.history = ({s["name"]: _initial(s) for s in m["frontend"]["inputs"] if "init" in s}
                        if m["frontend"] else {})
        self.position = 0  # absolute frame of the next chunk
        self.audio = np.zeros(0, np.float32)  # the utterance's audio from sample `self.audio_start` on
        self.audio_start = 0
        self.samples = 0
        self.groups = 0  # token groups emitted
        self.tokens = np.zeros((0, m["token_width"]), np.float32)  # tokens not yet in a chunk
        self.token_count = 0
        self.frames = 0
        self.last_quaternions: dict[int, np.ndarray] = {}

    # ------------------------------------------------------------------ audio -> tokens
    def _group(self, n: int) -> np.ndarray:
        f = self.manifest["frontend"]
        start = n * f["hop_samples"] + f["offset_samples"]
        window = np.zeros(f["window_samples"], np.float32)
        lo = max(start, self.audio_start)
        hi = min(start + f["window_samples"], self.audio_start + self.audio.size)
        if hi > lo:
            window[lo - start:hi - start] = self.audio[lo - self.audio_start:hi - self.audio_start]
        out = dict(zip([o.name for o in self.frontend.get_outputs()],
                       self.frontend.run(None, {"audio": window, **self.history})))
        self.history = {name: out[f"next_{name}"] for name in self.history}
        return out["tokens"]

    def _forget_audio(self) -> None:
        """Drop the samples no later group reads."""
        f = self.manifest["frontend"]
        keep = self.groups * f["hop_samples"] + f["offset_samples"]
        if keep > self.audio_start:
            self.audio = self.audio[keep - self.audio_start:]
            self.audio_start = keep

    def push(self, audio: np.ndarray) -> np.ndarray:
        """Add mono float audio at the manifest's ``sample_rate``; returns the ``(frames, 56)`` head parameters
        of every chunk it completes."""
        if self.frontend is None:
            raise ValueError("this export takes token embeddings (the run has no tokenizer): push_tokens")
        audio = np.asarray(audio, np.float32)
        if audio.ndim != 1:
            raise ValueError(f"audio must be mono, shape (samples,), got {audio.shape}: mix the channels first")
        if not np.all(np.isfinite(audio)):
            raise ValueError("audio contains NaN or inf")
        f = self.manifest["frontend"]
        self.audio = np.concatenate([self.audio, audio])
        self.samples += audio.size
        tokens = []
        while (self.groups + 1) * f["hop_samples"] + f["lookahead_samples"] <= self.samples:
            tokens.append(self._group(self.groups))
            self.groups += 1
        self._forget_audio()
        return self.push_tokens(np.concatenate(tokens)) if tokens else self._no_frames()

    # ------------------------------------------------------------------ tokens -> motion
    def _no_frames(self) -> np.ndarray:
        return np.zeros((0, self.manifest["param_dim"]), np.float32)

    def _chunk(self, chunk_tokens: np.ndarray) -> np.ndarray:
        m = self.manifest
        white = self.white(self.position + m["white_lead_frames"], m["chunk_frames"])[None].astype(np.float32)
        feed = {**self.state, "chunk_tokens": chunk_tokens[None], "white_chunk": white,
                "cfg_scale": self.cfg_scale, "temperature": self.temperature}
        out = dict(zip([o.name for o in self.step.get_outputs()], self.step.run(None, feed)))
        self.state = {name: out[f"next_{name}"] for name in self.state}
        self.position += m["chunk_frames"]
        return out["params"][0]

    def push_tokens(self, tokens: np.ndarray) -> np.ndarray:
        """Add ``(n, token_width)`` token embeddings at the manifest's ``token_rate``; returns the frames of every
        chunk they complete."""
        m = self.manifest
        tokens = np.asarray(tokens, np.float32)
        if tokens.ndim != 2 or tokens.shape[1] != m["token_width"]:
            raise ValueError(f"tokens must have shape (n, {m['token_width']}), got {tokens.shape}")
        self.token_count += tokens.shape[0]
        self.tokens = np.concatenate([self.tokens, tokens])
        ct = m["chunk_tokens"]
        whole = self.tokens.shape[0] // ct * ct
        out = [self._chunk(self.tokens[i:i + ct]) for i in range(0, whole, ct)]
        self.tokens = self.tokens[whole:]
        frames = np.concatenate(out) if out else self._no_frames()
        self.frames += frames.shape[0]
        return frames

    def finish(self) -> np.ndarray:
        """The utterance's last frames (see the module docstring); the stream then starts afresh."""
        m = self.manifest
        samples = self.samples if self.frontend is not None and self.samples else None
        if samples is not None:
            total = math.ceil(samples * m["token_rate"] / m["sample_rate"] - 1e-9)
            emitted = self.groups * m["chunk_tokens"]
            tokens = []
            while emitted < total:
                tokens.append(self._group(self.groups)[: total - emitted])
                self.groups += 1
                emitted += tokens[-1].shape[0]
            if tokens:
                self.token_count += sum(t.shape[0] for t in tokens)
                self.tokens = np.concatenate([self.tokens, *tokens])
        frames = self._no_frames()
        if self.tokens.shape[0]:
            pad = -self.tokens.shape[0] % m["chunk_tokens"]
            tokens = np.concatenate([self.tokens, np.repeat(self.tokens[-1:], pad, axis=0)])
            ct = m["chunk_tokens"]
            frames = np.concatenate([self._chunk(tokens[i:i + ct]) for i in range(0, tokens.shape[0], ct)])
        limit = math.floor(self.token_count * m["fps"] / m["token_rate"] + 0.5)
        if samples is not None:
            limit = min(limit, round(samples / m["sample_rate"] * m["fps"]))
        frames = frames[: max(limit - self.frames, 0)]
        self.reset()
        return frames

    # ------------------------------------------------------------------ params -> the face
    def morph(self, params: np.ndarray) -> np.ndarray:
        """``(frames, 56)`` head parameters -> the ``(frames, channels)`` values that pose ``face.glb``
        (manifest ``morph.channels``), quaternion signs continuous across calls."""
        if self.morph_graph is None:
            raise ValueError("this export has no face (morph.onnx)")
        params = np.asarray(params, np.float32)
        block = self.manifest["morph"]["frames"]  # the graph's fixed frame count: pad the last block, crop
        values = np.zeros((params.shape[0], len(self.manifest["morph"]["channels"])), np.float32)
        for a in range(0, params.shape[0], block):
            rows = params[a:a + block]
            rows = np.concatenate([rows, np.repeat(rows[-1:], block - rows.shape[0], axis=0)])
            values[a:a + block] = self.morph_graph.run(None, {"params": rows})[0][: min(block, params.shape[0] - a)]
        for at in self.manifest["morph"]["quaternions"]:
            for row in values:
                last = self.last_quaternions.get(at)
                if last is not None and np.dot(row[at:at + 4], last) < 0:
                    row[at:at + 4] *= -1
                self.last_quaternions[at] = row[at:at + 4].copy()
        return values
