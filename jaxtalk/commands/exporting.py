"""``jaxtalk export``: head parameters (.npz) or a vertex sequence (.npy) -> binary glTF (.glb) + audio (.wav).

Parameters ``(T, 56)`` (from ``sample``, ``stream``, ``demo`` or any generic npz) are written on the
built-in face, or on a FLAME model with ``--flame``, as morph targets and a jaw/neck skin; a vertex
sequence (FreeTalk's output on a user's mesh, any ``(T, V, 3)`` or ``(T, 3V)`` array) as a principal-
component morph basis within ``--max-error-mm``. The mesh of a vertex sequence is found as ``render``
finds it (a built-in resolution, else ``--faces``). glTF carries no sound, so the audio (``--audio``, or
the audio stored in the npz) is written beside the ``.glb`` with the same name and a ``.wav`` suffix.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from jaxtalk.export import (
    DEFAULT_MAX_ERROR,
    ExportSummary,
    export_face_model,
    export_vertex_sequence,
    write_audio_beside,
)
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

__all__ = ["ExportOptions", "ExportResult", "export_file"]


@dataclasses.dataclass(frozen=True)
class ExportOptions:
    """Settings of :func:`export_file`.

    Attributes:
        input: ``.npz`` with head parameters, or ``.npy`` vertices.
        out: the ``.glb`` to write.
        audio: audio to write beside it (default: the audio stored in the npz, if any).
        faces: triangles for vertices of a mesh that is not built in (``.npy`` or the mesh file).
        flame: a FLAME 2020 model file to write parameters on instead of the built-in face.
        fps: frame rate of a vertex sequence (an npz states its own).
        max_error_mm: the vertex basis's bound, millimetres.
    """

    input: Path
    out: Path
    audio: Path | None = None
    faces: Path | None = None
    flame: Path | None = None
    fps: float = MOTION_FPS
    max_error_mm: float = DEFAULT_MAX_ERROR * 1e3


@dataclasses.dataclass(frozen=True)
class ExportResult:
    """What :func:`export_file` wrote: the ``.glb``'s summary and the audio beside it (or None)."""

    summary: ExportSummary
    audio: Path | None


def export_file(opts: ExportOptions) -> ExportResult:
    """Export ``opts.input`` to ``opts.out`` (and its audio beside it); see the module docstring.

    Raises:
        FileNotFoundError: a missing input, audio, faces or FLAME file.
        ValueError: a bad output path, a params file of the wrong width, NaN, no frames, vertices that
            do not match their mesh, a bad bound or audio.
    """
    from jaxtalk.commands.rendering import face_model, load_motion, read_head_clip
    from jaxtalk.files import check_output_path

    out = check_output_path(opts.out, (".glb",))
    source = Path(opts.input)
    audio = None
    if source.suffix.lower() == ".npz":
        if opts.faces is not None:
            raise ValueError("--faces is for a vertex sequence (.npy); parameters are written on the face model")
        params, audio, fps = read_head_clip(source)
        summary = export_face_model(face_model(opts.flame), params, out, fps=fps, name=source.stem)
    else:
        if opts.flame is not None:
            raise ValueError("--flame is for head parameters (.npz); a vertex sequence carries its own mesh")
        motion = load_motion(source, faces=opts.faces)
        summary = export_vertex_sequence(motion.vertices, motion.faces, out, fps=opts.fps,
                                         max_error=opts.max_error_mm * 1e-3, name=source.stem)
    if opts.audio is not None:
        from jaxtalk.audio import load_audio

        audio = load_audio(opts.audio, allow_silence=True)
    if audio is None:
        return ExportResult(summary, None)
    return ExportResult(summary, write_audio_beside(out, audio, AUDIO_SAMPLE_RATE))
