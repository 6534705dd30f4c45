"""``jaxtalk export``: head parameters (.npz) or a vertex sequence (.npy) -> binary glTF (.glb) + audio (.wav).

Parameters ``(T, 56)`` (from ``sample``, ``stream``, ``demo`` or any generic npz) are written on the
built-in face, or on a FLAME model with ``--flame``, as morph targets and a jaw/neck skin; a vertex
sequence (FreeTalk's output on a user's mesh, any ``(T, V, 3)`` or ``(T, 3V)`` array) as a principal-
component morph basis within ``--max-error-mm``. The mesh of a vertex sequence is found as ``render``
finds it (a built-in resolution, else ``--faces``). glTF carries no sound, so the audio (``--audio``, or
the audio stored in the npz) is written beside the ``.glb`` as ``NAME.glb.wav`` (never ``NAME.wav``, the
natural name of the recording itself), and the ``.glb`` names it in ``asset.extras.audio``.

Every output is checked before any work (:func:`jaxtalk.files.claim_outputs`): no input is ever
written over; ``--out`` may replace a file; the default ``anim.glb`` and the audio beside the ``.glb``
replace an existing file only with ``--overwrite``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from jaxtalk.export import (
    DEFAULT_MAX_ERROR,
    ExportSummary,
    audio_path_for,
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
        out: the ``.glb`` to write (None: ``anim.glb``, which replaces no existing file without
            ``overwrite``).
        audio: audio to write beside it (default: the audio stored in the npz, if any).
        faces: triangles for vertices of a mesh that is not built in (``.npy`` or the mesh file).
        flame: a FLAME 2020 model file to write parameters on instead of the built-in face.
        fps: frame rate of a vertex sequence (an npz states its own).
        max_error_mm: the vertex basis's bound, millimetres.
        overwrite: let the default output name and the audio beside the ``.glb`` replace existing files.
    """

    input: Path
    out: Path | None = None
    audio: Path | None = None
    faces: Path | None = None
    flame: Path | None = None
    fps: float = MOTION_FPS
    max_error_mm: float = DEFAULT_MAX_ERROR * 1e3
    overwrite: bool = False

DEFAULT_OUT = Path("anim.glb")


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
    from jaxtalk.files import Output, claim_outputs

    out = Path(opts.out) if opts.out is not None else DEFAULT_OUT
    # Checked before any work. The audio beside the .glb is written only when there is audio, but its
    # name is claimed either way: the npz's audio is known only after reading it.
    claim_outputs([Output(out, named=opts.out is not None, suffixes=(".glb",)), Output(audio_path_for(out))],
                  inputs=[opts.input, opts.audio, opts.faces, opts.flame], overwrite=opts.overwrite)
    source = Path(opts.input)
    audio = None
    if opts.audio is not None:
        from jaxtalk.audio import load_audio

        audio = load_audio(opts.audio, allow_silence=True)
    if source.suffix.lower() == ".npz":
        if opts.faces is not None:
            raise ValueError("--faces is for a vertex sequence (.npy); parameters are written on the face model")
        params, stored, fps = read_head_clip(source)
        audio = stored if audio is None else audio
        summary = export_face_model(face_model(opts.flame), params, out, fps=fps, name=source.stem,
                                    audio_file=audio_path_for(out).name if audio is not None else None)
    else:
        if opts.flame is not None:
            raise ValueError("--flame is for head parameters (.npz); a vertex sequence carries its own mesh")
        motion = load_motion(source, faces=opts.faces)
        summary = export_vertex_sequence(motion.vertices, motion.faces, out, fps=opts.fps,
                                         max_error=opts.max_error_mm * 1e-3, name=source.stem,
                                         audio_file=audio_path_for(out).name if audio is not None else None)
    if audio is None:
        return ExportResult(summary, None)
    return ExportResult(summary, write_audio_beside(out, audio, AUDIO_SAMPLE_RATE))
