"""Retargeted weights as files: a Live Link Face recording (CSV) and JSON.

Live Link Face's CSV (what the app records and Unreal's LiveLinkFaceImporter, the Maya and Blender
importers read): a header ``Timecode,BlendShapeCount,`` then the 61 curves of
:data:`~jaxtalk.export.arkit.LIVE_LINK_CURVES` (the 52 shapes, the head's yaw, pitch and roll, each eye's
yaw, pitch and roll); one row per frame with its timecode ``HH:MM:SS:FF.fff`` (``FF`` the frame within the
second at the clip's rate, ``.fff`` the sub-frame fraction, ``.000`` for frames on the grid), the count 61,
and the 61 values. Shapes the rig lacks are 0; head angles are radians (see
:mod:`jaxtalk.export.retarget`); the eyes' rotations are 0 (jaxtalk moves the lids, not eyeballs).

Both files are written a chunk of frames at a time (atomically, as every jaxtalk file): a clip of any
length holds nothing but its weights and head angles while they are written.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.export.arkit import ARKIT_NAMES, LIVE_LINK_CURVES
from jaxtalk.export.rig import arkit_halves, arkit_shape_name
from jaxtalk.files import atomic_output, check_output_path
from jaxtalk.types import Float

# Frames made into text at a time.
_ROWS = 1024

__all__ = ["live_link_timecode", "arkit_weights", "live_link_curves", "write_live_link_csv", "write_weights_json",
           "read_live_link_csv"]


def live_link_timecode(frame: int, fps: float | int) -> str:
    """``HH:MM:SS:FF.fff`` of frame ``frame`` (from 0) at ``fps``: ``live_link_timecode(26, 25)`` is
    ``00:00:01:01.000``."""
    if frame < 0 or not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"a timecode needs a frame >= 0 and a positive fps, got {frame} at {fps}")
    seconds = math.floor(frame / fps + 1e-9)
    sub = max(frame - seconds * fps, 0.0)  # frames (with a fraction at a non-integer rate) into the second
    whole = int(sub + 1e-9)
    milli = min(round((sub - whole) * 1000), 999)
    hours, rem = divmod(seconds, 3600)
    minutes, secs = divmod(rem, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}:{whole:02d}.{milli:03d}"


def arkit_weights(names: tuple[str, ...] | list[str], weights: Float[np.ndarray, "frames k"]
                  ) -> Float[np.ndarray, "frames 52"]:
    """A rig's weights in ARKit's 52 (Live Link order), matched by name; a shape of both sides that the rig
    splits into halves is their mean (:func:`~jaxtalk.export.rig.arkit_halves`); shapes it lacks are 0."""
    w = np.asarray(weights, np.float64)
    out = np.zeros((w.shape[0], len(ARKIT_NAMES)))
    index = {n: i for i, n in enumerate(ARKIT_NAMES)}
    seen: set[str] = set()
    for k, name in enumerate(names):
        arkit = arkit_shape_name(name)
        if arkit is not None and arkit not in seen:
            out[:, index[arkit]] = w[:, k]
            seen.add(arkit)
    for arkit, (left, right) in arkit_halves(names).items():
        out[:, index[arkit]] = (w[:, left] + w[:, right]) / 2
    return out


def live_link_curves(names: tuple[str, ...] | list[str], weights: Float[np.ndarray, "frames k"],
                     head_angles: Float[np.ndarray, "frames 3"] | None = None) -> Float[np.ndarray, "frames 61"]:
    """The 61 curves of Live Link Face frames, in :data:`LIVE_LINK_CURVES` order: a rig's weights on ARKit's
    52 shapes (matched by name, :func:`arkit_weights`), the head's yaw, pitch and roll in radians (zeros
    without), the eyes' six curves 0. What a Live Link Face recording's rows and UDP packets hold.

    Raises:
        ValueError: head angles of the wrong shape, NaN or inf.
    """
    arkit = arkit_weights(names, weights)
    frames = arkit.shape[0]
    head = np.zeros((frames, 3)) if head_angles is None else np.asarray(head_angles, np.float64)
    if head.shape != (frames, 3):
        raise ValueError(f"head_angles must have shape ({frames}, 3), got {head.shape}")
    values = np.concatenate([arkit, head, np.zeros((frames, 6))], axis=1)
    if not np.all(np.isfinite(values)):
        raise ValueError("weights or head angles hold NaN or inf")
    return values


def write_live_link_csv(path: str | Path, names: tuple[str, ...] | list[str], weights: Float[np.ndarray, "frames k"],
                        head_angles: Float[np.ndarray, "frames 3"] | None, fps: float | int) -> Path:
    """Write a Live Link Face recording (module docstring), atomically.

    Args:
        path: the ``.csv``.
        names: the rig's shape names (matched to ARKit's by :func:`arkit_shape_name`).
        weights: ``(T, K)``.
        head_angles: ``(T, 3)`` yaw, pitch, roll in radians, or None (zeros).
        fps: the frame rate.

    Raises:
        ValueError: mismatched shapes, NaN, a bad path or fps.
    """
    path = check_output_path(path, (".csv",))
    w, head = _checked(names, weights, head_angles)
    live_link_timecode(0, fps)  # checks fps before the file is opened
    with atomic_output(path) as tmp, open(tmp, "w", encoding="utf-8", newline="") as handle:
        handle.write("Timecode,BlendShapeCount," + ",".join(LIVE_LINK_CURVES) + "\n")
        for a in range(0, w.shape[0], _ROWS):
            values = live_link_curves(names, w[a:a + _ROWS], None if head is None else head[a:a + _ROWS])
            handle.write("".join(f"{live_link_timecode(a + t, fps)},{len(LIVE_LINK_CURVES)},"
                                 + ",".join(f"{x:.6f}" for x in row) + "\n" for t, row in enumerate(values)))
    return path


def _checked(names: tuple[str, ...] | list[str], weights: Any, head_angles: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """``(weights (T, K), head angles (T, 3) or None)`` as arrays, their shapes checked before anything is written
    (their values are checked a chunk at a time as they are)."""
    w = np.asarray(weights, np.float64)
    if w.ndim != 2 or w.shape[1] != len(names):
        raise ValueError(f"weights must have shape (frames, {len(names)}) for {len(names)} names, got {w.shape}")
    if head_angles is None:
        return w, None
    head = np.asarray(head_angles, np.float64)
    if head.shape != (w.shape[0], 3):
        raise ValueError(f"head_angles must have shape ({w.shape[0]}, 3), got {head.shape}")
    return w, head


def read_live_link_csv(path: str | Path) -> tuple[list[str], Float[np.ndarray, "frames 61"]]:
    """``(timecodes, values (T, 61))`` of a Live Link Face CSV, columns in :data:`LIVE_LINK_CURVES` order.

    Raises:
        ValueError: a header that is not Live Link Face's, or a malformed row.
    """
    lines = Path(path).read_text().splitlines()
    header = lines[0].split(",") if lines else []
    if header[:2] != ["Timecode", "BlendShapeCount"]:
        raise ValueError(f"{str(path)!r} is not a Live Link Face CSV (header {header[:3]})")
    column = {name: i for i, name in enumerate(header)}
    missing = [c for c in LIVE_LINK_CURVES if c not in column]
    if missing:
        raise ValueError(f"{str(path)!r} lacks the curves {missing[:3]}")
    stamps, rows = [], []
    for n, line in enumerate(lines[1:], start=2):
        cells = line.split(",")
        if len(cells) != len(header):
            raise ValueError(f"{str(path)!r} line {n}: {len(cells)} cells, the header has {len(header)}")
        stamps.append(cells[0])
        rows.append([float(cells[column[c]]) for c in LIVE_LINK_CURVES])
    return stamps, np.asarray(rows, np.float64).reshape(-1, len(LIVE_LINK_CURVES))


def write_weights_json(path: str | Path, *, names: tuple[str, ...] | list[str], weights: Float[np.ndarray, "frames k"],
                       head_angles: Float[np.ndarray, "frames 3"] | None, fps: float | int, extra: dict | None = None) -> Path:
    """Write the weights as JSON: ``fps``, ``frames``, ``names`` (the rig's), ``arkit`` (each name's ARKit
    name or null), ``weights`` (``T`` lists of ``K``), ``head`` (``yaw``/``pitch``/``roll`` lists, radians,
    and their convention), plus ``extra``. Atomically.
    """
    path = check_output_path(path, (".json",))
    w, h = _checked(names, weights, head_angles)
    for what, values in (("weights", w), ("head angles", h)):
        if values is not None and not all(np.isfinite(values[a:a + _ROWS]).all() for a in range(0, len(values), _ROWS)):
            raise ValueError(f"{what} hold NaN or inf, which JSON cannot")
    payload: dict = {
        "fps": float(fps),
        "frames": int(w.shape[0]),
        "names": list(names),
        "arkit": [arkit_shape_name(n) for n in names],
        "weights": _Rows(w),
    }
    if h is not None:
        payload["head"] = {"units": "radians",
                           "convention": "R = Ry(yaw) Rx(pitch) Rz(roll); x: subject's left, y: up, z: out of the face",
                           "yaw": _Rows(h[:, 0]), "pitch": _Rows(h[:, 1]), "roll": _Rows(h[:, 2])}
    payload.update(extra or {})
    with atomic_output(path) as tmp, open(tmp, "w", encoding="utf-8") as handle:
        _dump(payload, handle, 0)
        handle.write("\n")
    return path


class _Rows:
    """A per-frame array in a JSON document, written a chunk of frames at a time (a frame's values on one
    line), each value rounded to 6 decimals as ``np.round(x, 6).tolist()`` gives it."""

    def __init__(self, array: np.ndarray) -> None:
        self.array = array

    def lines(self) -> Iterator[str]:
        for a in range(0, len(self.array), _ROWS):
            chunk = np.round(self.array[a:a + _ROWS], 6).tolist()
            yield ",\n".join(json.dumps(row) for row in chunk) if self.array.ndim > 1 else json.dumps(chunk)[1:-1]


def _dump(value: Any, handle: io.TextIOBase, depth: int) -> None:
    """``json.dump`` (values JSON cannot hold as ``str``, as :func:`jaxtalk.files.atomic_write_json`) with
    :class:`_Rows` written as they are made: objects that hold them one key a line, the rest as JSON writes them."""
    if isinstance(value, _Rows):
        handle.write("[")
        for k, text in enumerate(value.lines()):
            handle.write((",\n" if k else "") + text)
        handle.write("]")
    elif isinstance(value, dict) and any(isinstance(v, (_Rows, dict)) for v in value.values()):
        indent = "\n" + " " * (depth + 1)
        handle.write("{")
        for k, (key, item) in enumerate(value.items()):
            handle.write(("," if k else "") + indent + json.dumps(str(key)) + ": ")
            _dump(item, handle, depth + 1)
        handle.write("\n" + " " * depth + "}")
    else:
        handle.write(json.dumps(value, default=str))
