"""Small helpers several test modules share (import as ``from helpers import ...``)."""

from __future__ import annotations

import functools

import jax


@functools.partial(jax.jit, static_argnames="scale")
def perturbed(params, key, scale: float = 0.05):
    """``params`` plus ``scale`` x standard-normal noise on every leaf.

    Zero-initialised layers (adaLN modulations, output projections) make a fresh model's output exactly
    0 or its input; tests of what a layer computes perturb them first so that comparisons see signal.
    """
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(tree, [x + scale * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])


def timar_streams(batch: int, frames: int, seed: int = 0, speech_dim: int = 8) -> dict:
    """Random float32 TIMAR inputs, ``(batch, frames, .)``: both speakers' speech and motion."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return {
        "user_speech": rng.normal(size=(batch, frames, speech_dim)).astype(np.float32),
        "user_motion": rng.normal(size=(batch, frames, 56)).astype(np.float32),
        "agent_speech": rng.normal(size=(batch, frames, speech_dim)).astype(np.float32),
        "agent_motion": rng.normal(size=(batch, frames, 56)).astype(np.float32),
    }


def read_event_file(path):
    """Every TensorBoard ``Event`` of one file, read with tensorboardX's protobufs and the TFRecord
    framing, each record's length and payload checksums verified (independent of jaxtalk's code)."""
    import struct

    from tensorboardX.proto.event_pb2 import Event
    from tensorboardX.record_writer import masked_crc32c

    data, offset, events = path.read_bytes(), 0, []
    while offset < len(data):
        header = data[offset:offset + 8]
        (length,) = struct.unpack("<Q", header)
        assert struct.unpack("<I", data[offset + 8:offset + 12])[0] == masked_crc32c(header)
        payload = data[offset + 12:offset + 12 + length]
        assert len(payload) == length, f"torn record in {path}"
        assert struct.unpack("<I", data[offset + 12 + length:offset + 16 + length])[0] == masked_crc32c(payload)
        events.append(Event.FromString(payload))
        offset += 16 + length
    return events


def event_files(run_dir):
    """A run folder's TensorBoard event files, in name (creation) order."""
    return sorted(p for p in run_dir.glob("events.out.tfevents.*") if not p.name.startswith("."))


def scalars(run_dir):
    """``tag -> [(step, value), ...]`` over all event files of a run folder, in file order."""
    out: dict[str, list[tuple[int, float]]] = {}
    for path in event_files(run_dir):
        for event in read_event_file(path):
            for value in event.summary.value:
                out.setdefault(value.tag, []).append((event.step, value.simple_value))
    return out
