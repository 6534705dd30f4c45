"""The wire protocol of ``jaxtalk serve`` (docs/serve.md): message parsing and validation, and the replies.

A client speaks first with a JSON ``hello`` (text message), then sends its audio as binary messages of
raw PCM, and may send JSON ``end`` (the utterance is over: its last frames come back) or ``stats``. The
server answers every audio message with one JSON ``frames`` message. Anything malformed is answered
with a JSON ``error`` naming a :data:`ERROR_CODES` code, and nothing of that message reaches the stream:
the connection and the stream go on as if it had not been sent.
"""

from __future__ import annotations

import dataclasses
import json
import reprlib
from typing import Any

import numpy as np

__all__ = [
    "ERROR_CODES",
    "FORMATS",
    "PROTOCOL",
    "Hello",
    "ProtocolError",
    "decode_pcm",
    "error_message",
    "parse_hello",
    "parse_message",
]

PROTOCOL = 1
# format name: (NumPy dtype of one sample, full scale).
FORMATS = {"pcm_s16le": ("<i2", 32768.0), "f32le": ("<f4", 1.0)}
# Float samples are full scale at +-1; far beyond is not audio (a wrong format, or garbage bytes).
MAX_FLOAT_AMPLITUDE = 4.0
ERROR_CODES = {
    "bad_json": "a text message that is not a JSON object",
    "unknown_type": "a JSON message of a type the server does not know",
    "bad_hello": "a hello with a missing or ill-typed field, or a number out of its range",
    "bad_rate": "a sample rate other than the server's",
    "bad_format": "a sample format the server does not read",
    "unknown_output": "an output the server does not know",
    "output_unavailable": "an output this server cannot produce",
    "no_hello": "audio or end before a hello was accepted",
    "empty": "an audio message without samples",
    "odd_length": "an audio message whose length is not a whole number of samples",
    "too_large": "an audio message longer than the server's max_chunk_samples",
    "not_finite": "float samples that are NaN or infinite",
    "out_of_range": "float samples far beyond full scale (+-1)",
    "busy": "the server is serving as many clients as it may",
    "internal": "the server failed on this message (its reply says why); the connection goes on",
}


class ProtocolError(ValueError):
    """A malformed message: answered with an ``error`` message (``code``, one of :data:`ERROR_CODES`)."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclasses.dataclass(frozen=True)
class Hello:
    """An accepted hello.

    Attributes:
        sample_rate: samples per second of the client's audio (the server's own).
        format: ``"pcm_s16le"`` or ``"f32le"`` (:data:`FORMATS`).
        outputs: the outputs each frames message carries, in order.
        seed: the stream's noise seed (the same audio and seed give the same motion).
        subject: the Live Link subject name of this client's frames.
    """

    sample_rate: int
    format: str
    outputs: tuple[str, ...]
    seed: int = 0
    subject: str = "jaxtalk"


def parse_message(text: str) -> dict[str, Any]:
    """A text message as a JSON object with a string ``type``.

    Raises:
        ProtocolError: ``bad_json``.
    """
    try:
        message = json.loads(text)
    except (ValueError, RecursionError):  # ValueError: malformed JSON, or an integer over Python's 4300 digits
        message = None
    if not isinstance(message, dict) or not isinstance(message.get("type"), str):
        raise ProtocolError("bad_json", 'text messages are JSON objects with a "type" (hello, end or stats)')
    return message


# The hello's numbers: a sample rate is a positive 32-bit integer, a seed any 64-bit integer (signed or not).
SAMPLE_RATE_RANGE = (1, 2**31 - 1)
SEED_RANGE = (-2**63, 2**64 - 1)


def _integer(message: dict[str, Any], key: str, bounds: tuple[int, int], default: int | None = None) -> int:
    value = message.get(key, default)
    low, high = bounds
    # JSON's true/false are ints to Python; NaN and infinities are floats that are not integers; an int
    # of any size compares exactly with the bounds (converting it to a float first would overflow).
    if (isinstance(value, bool) or not isinstance(value, int | float)
            or (isinstance(value, float) and not value.is_integer()) or not low <= value <= high):
        raise ProtocolError("bad_hello", f"hello.{key} must be an integer in {low}..{high}, got {reprlib.repr(value)}")
    return int(value)


def parse_hello(message: dict[str, Any], *, sample_rate: int, outputs: tuple[str, ...]) -> Hello:
    """Validate a ``hello`` (already :func:`parse_message`'d).

    Args:
        message: ``{"type": "hello", "sample_rate": 16000, "format": "pcm_s16le" | "f32le", "outputs":
            [...], "seed": 0, "subject": "jaxtalk"}`` (``seed``, ``subject`` optional; ``outputs`` default
            ``["params"]``); ``sample_rate`` and ``seed`` are integers in :data:`SAMPLE_RATE_RANGE` and
            :data:`SEED_RANGE` (a float with an integral value counts; NaN, infinities and booleans do not).
        sample_rate: the rate the server takes.
        outputs: the output names the server knows.

    Raises:
        ProtocolError: ``bad_hello``, ``bad_rate``, ``bad_format``, ``unknown_output``.
    """
    rate = _integer(message, "sample_rate", SAMPLE_RATE_RANGE) if "sample_rate" in message else None
    if rate is None:
        raise ProtocolError("bad_hello", f"hello.sample_rate is required (this server takes {sample_rate} Hz)")
    if rate != sample_rate:
        raise ProtocolError("bad_rate", f"sample_rate {rate} Hz: this server takes {sample_rate} Hz mono audio; "
                                        "resample on the client")
    fmt = message.get("format", "pcm_s16le")
    if not isinstance(fmt, str) or fmt not in FORMATS:  # a list or an object is no format (nor hashable)
        raise ProtocolError("bad_format", f"format {reprlib.repr(fmt)}: expected one of {', '.join(FORMATS)}")
    wanted = message.get("outputs", ["params"])
    if (not isinstance(wanted, list) or not wanted or not all(isinstance(o, str) for o in wanted)
            or len(set(wanted)) != len(wanted)):
        raise ProtocolError("bad_hello", "hello.outputs must be a non-empty list of distinct names, got "
                                         f"{reprlib.repr(wanted)}")
    unknown = [o for o in wanted if o not in outputs]
    if unknown:
        raise ProtocolError("unknown_output", f"unknown output {unknown[0]!r}: expected some of {', '.join(outputs)}")
    subject = message.get("subject", "jaxtalk")
    if not isinstance(subject, str) or not 0 < len(subject.encode()) <= 200:
        raise ProtocolError("bad_hello", "hello.subject must be a name of 1 to 200 bytes")
    return Hello(sample_rate=rate, format=fmt, outputs=tuple(wanted),
                 seed=_integer(message, "seed", SEED_RANGE, 0) % 2**32, subject=subject)


def decode_pcm(data: bytes, fmt: str, max_samples: int) -> np.ndarray:
    """One binary audio message as ``(samples,)`` float32 at full scale +-1.

    Raises:
        ProtocolError: ``empty``, ``odd_length``, ``too_large``, ``not_finite``, ``out_of_range``.
    """
    dtype, scale = FORMATS[fmt]
    width = np.dtype(dtype).itemsize
    if not data:
        raise ProtocolError("empty", "an audio message needs at least one sample")
    if len(data) % width:
        raise ProtocolError("odd_length", f"{len(data)} bytes is not a whole number of {width}-byte {fmt} samples")
    if len(data) // width > max_samples:
        raise ProtocolError("too_large", f"{len(data) // width} samples in one message; send at most {max_samples} "
                                         "(split the audio into smaller messages)")
    samples = np.frombuffer(data, dtype)
    if fmt == "f32le":
        finite = np.isfinite(samples)
        if not finite.all():
            raise ProtocolError("not_finite", f"{int((~finite).sum())} NaN/inf samples (first at {int(np.argmin(finite))})")
        peak = float(np.abs(samples).max())
        if peak > MAX_FLOAT_AMPLITUDE:
            raise ProtocolError("out_of_range", f"float samples are full scale at +-1; a peak of {peak:.3g} is not "
                                                "audio (16-bit samples sent as f32le?)")
    return (samples.astype(np.float32) / np.float32(scale)).astype(np.float32)


def error_message(code: str, message: str, **extra: Any) -> dict[str, Any]:
    """The ``error`` reply."""
    return {"type": "error", "code": code, "message": message, **extra}
