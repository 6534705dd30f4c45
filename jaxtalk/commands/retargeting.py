"""``jaxtalk retarget``: jaxtalk motion -> a blendshape rig's weights, as GLB + Live Link Face CSV + JSON.

MOTION is a parameters ``.npz`` (``sample``, ``stream``, ``demo``, a generic npz: ``(T, 56)`` on the built-in
face, or on ``--flame``) or a ``.npy`` vertex sequence (FreeTalk's output): on a built-in face resolution,
on the rig's own mesh, or on ``--mesh`` (the mesh file it was animated on). RIG is a ``.glb`` / ``.gltf``
with morph targets, a folder of OBJ shapes with a ``neutral.obj``, or ``builtin`` (the built-in ARKit rig).

``--out NAME.glb`` names the outputs: ``NAME.glb`` (the rig's mesh, its morph targets and their weights
over time, the head turning about its pivot), ``NAME.csv`` (a Live Link Face recording), ``NAME.json``,
and the audio beside the ``.glb`` as ``NAME.glb.wav`` (``--audio``, or the audio stored in the npz). An
existing ``NAME.glb`` is replaced; the side files are names the command picks, so an existing file under
one of them is kept unless ``--overwrite`` is given (:mod:`jaxtalk.files`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxtalk.types import MOTION_FPS

__all__ = ["RetargetOptions", "RetargetReport", "retarget_file", "BUILTIN_RIG"]

BUILTIN_RIG = "builtin"
DEFAULT_OUT = Path("retarget.glb")


@dataclasses.dataclass(frozen=True)
class RetargetOptions:
    """Settings of :func:`retarget_file` (module docstring).

    Attributes:
        motion: ``.npz`` parameters or ``.npy`` vertices.
        rig: a rig file or folder, or ``"builtin"``.
        out: the ``.glb`` (None: ``retarget.glb``, which replaces no file without ``overwrite``).
        audio: audio to write beside the ``.glb`` (default: the npz's).
        mesh: the mesh file a vertex sequence was animated on.
        flame: a FLAME 2020 model file that the parameters are posed on.
        units: the unit of a rig or mesh file (None: detected).
        landmarks: the rig file's 68 landmarks (a file :func:`~jaxtalk.models.freetalk.animate.read_landmarks`
            reads: ``(68, 3)`` positions in its units or ``(68,)`` vertex indices), to register it by.
        fps: frame rate of a vertex sequence (an npz states its own).
        smoothness, l1, l2, symmetry: the solver's penalties.
        overwrite: let the names the command picks replace existing files.
    """

    motion: Path
    rig: str | Path = BUILTIN_RIG
    out: Path | None = None
    audio: Path | None = None
    mesh: Path | None = None
    flame: Path | None = None
    units: str | None = None
    landmarks: Path | None = None
    fps: float = MOTION_FPS
    smoothness: float = 0.01
    l1: float = 0.0
    l2: float = 1e-4
    symmetry: float = 0.0
    overwrite: bool = False


@dataclasses.dataclass(frozen=True)
class RetargetReport:
    """What :func:`retarget_file` wrote and measured."""

    glb: Path
    csv: Path
    json: Path
    audio: Path | None
    lines: list[str]


def _outputs(out: Path) -> tuple[Path, Path]:
    return out.with_suffix(".csv"), out.with_suffix(".json")


def retarget_file(opts: RetargetOptions, *, echo: Callable[[str], None] = print) -> RetargetReport:
    """Retarget ``opts.motion`` onto ``opts.rig`` and write the GLB, CSV, JSON and audio.

    Raises:
        FileNotFoundError: a missing input.
        ValueError: a bad motion (shape, NaN), a rig without morph targets, a mesh or rig that does not
            register to the face, a fit error larger than the face (a unit or scale mistake:
            :meth:`~jaxtalk.export.Retargeter.check_fit`), a bad option value or output path.
    """
    from jaxtalk.commands.rendering import face_model, read_head_clip
    from jaxtalk.export import (
        DEFAULT_WINDOW,
        Penalties,
        Retargeter,
        arkit_rig,
        audio_path_for,
        export_rig_animation,
        load_rig,
        write_audio_beside,
        write_live_link_csv,
        write_weights_json,
    )
    from jaxtalk.files import Output, claim_outputs
    from jaxtalk.types import AUDIO_SAMPLE_RATE

    out = Path(opts.out) if opts.out is not None else DEFAULT_OUT
    if out.suffix.lower() != ".glb":
        raise ValueError(f"--out must name a .glb file (the CSV and JSON go beside it), got {str(out)!r}")
    csv, json_path = _outputs(out)
    builtin = str(opts.rig) == BUILTIN_RIG
    rig_path = None if builtin else Path(opts.rig)
    # Only the .glb is a name the user gives; the CSV, the JSON and the audio beside it are names the
    # command derives from it, which replace no existing file without --overwrite.
    claim_outputs([Output(out, named=opts.out is not None, suffixes=(".glb",)), Output(csv), Output(json_path),
                   Output(audio_path_for(out))],
                  inputs=[opts.motion, rig_path, opts.audio, opts.mesh, opts.flame, opts.landmarks],
                  overwrite=opts.overwrite)
    penalties = Penalties(smoothness=opts.smoothness, l1=opts.l1, l2=opts.l2, symmetry=opts.symmetry)
    if not (np.isfinite(opts.fps) and opts.fps > 0):
        raise ValueError(f"--fps must be a positive number, got {opts.fps}")
    motion_path = Path(opts.motion)
    if not motion_path.is_file():
        raise FileNotFoundError(f"motion file not found: {str(motion_path)!r}")
    suffix = motion_path.suffix.lower()
    if suffix not in (".npz", ".npy"):
        raise ValueError(f"{str(motion_path)!r}: expected .npz parameters or .npy vertices, got {suffix or 'no suffix'!r}")
    if builtin:
        if opts.landmarks is not None:
            raise ValueError("--landmarks are the rig file's 68 landmarks; the built-in rig needs none (pass --rig FILE)")
        rig = arkit_rig()
    else:
        rig = load_rig(rig_path)
        if opts.units is not None:
            rig = dataclasses.replace(rig, units=opts.units)
    echo(rig.describe())
    landmarks = None
    if opts.landmarks is not None:
        from jaxtalk.models.freetalk.animate import read_landmarks  # the reader FreeTalk's sample uses

        landmarks = read_landmarks(opts.landmarks, rig.neutral)

    audio = None
    if suffix == ".npz":
        if opts.mesh is not None:
            raise ValueError("--mesh is for a vertex sequence (.npy); parameters are posed on the face model")
        params, audio, fps = read_head_clip(motion_path)
        retargeter = Retargeter.for_face(rig, face_model(opts.flame), penalties, landmarks=landmarks)
        motion = params
    else:
        if opts.flame is not None:
            raise ValueError("--flame is for head parameters (.npz); a vertex sequence carries its own mesh")
        motion, retargeter = _vertex_motion(motion_path, rig, opts, penalties, landmarks)
        fps = float(opts.fps)
    if opts.audio is not None:
        from jaxtalk.audio import load_audio

        audio = load_audio(opts.audio, allow_silence=True)
    echo(retargeter.registration.describe())
    # Solved a window at a time (Retargeter.__call__): memory stays bounded whatever the clip's length.
    result = retargeter(motion)
    windows = "" if result.windows == 1 else f" in {result.windows} windows of {DEFAULT_WINDOW} frames"
    echo(f"solved {result.weights.shape[0]} frames x {rig.num_shapes} shapes{windows} in {result.seconds * 1e3:.0f} "
         f"ms ({result.iterations} iterations): fit error {result.rms_error * 1e3:.3f} mm RMS, weights in "
         f"[{result.weights.min():.3f}, {result.weights.max():.3f}]")
    # A fit error larger than the face is a unit or scale mistake, not a fit: stop before writing anything.
    retargeter.check_fit(result.rms_error, None if suffix == ".npz" else motion[0])
    angles = np.degrees(np.abs(result.head_angles).max(axis=0))
    echo(f"head rotation: up to {angles[0]:.1f} deg yaw, {angles[1]:.1f} deg pitch, {angles[2]:.1f} deg roll")

    wav = audio_path_for(out)
    summary = export_rig_animation(rig, result.weights, out, fps=fps,
                                   head_rotation=retargeter.rig_rotation(result.head_rotation),
                                   pivot=retargeter.head_pivot, name=motion_path.stem,
                                   audio_file=wav.name if audio is not None else None)
    write_live_link_csv(csv, rig.names, result.weights, result.head_angles, fps)
    write_weights_json(json_path, names=rig.names, weights=result.weights, head_angles=result.head_angles, fps=fps,
                       extra={"motion": str(motion_path), "rig": BUILTIN_RIG if builtin else str(rig_path),
                              "penalties": dataclasses.asdict(penalties), "rms_error_m": result.rms_error,
                              "registration": {"method": retargeter.registration.method,
                                               "residual_m": retargeter.registration.residual,
                                               "fitted_vertices": retargeter.registration.fitted,
                                               "reference": retargeter.registration.reference,
                                               "ignored_part_vertices": list(retargeter.registration.ignored)}})
    written = write_audio_beside(out, audio, AUDIO_SAMPLE_RATE) if audio is not None else None
    lines = [f"written {summary.describe()}", f"written {csv} (Live Link Face CSV, 61 curves)",
             f"written {json_path}",
             f"written {written}" if written is not None else "no audio: pass --audio to write it beside the .glb"]
    for line in lines:
        echo(line)
    return RetargetReport(out, csv, json_path, written, lines)


def _vertex_motion(path: Path, rig, opts: RetargetOptions, penalties, landmarks):
    """The vertex sequence and its retargeter: on ``--mesh``, the rig's own mesh, or a built-in face."""
    from jaxtalk.files import load_npy
    from jaxtalk.export import Retargeter
    from jaxtalk.face import builtin_face

    # Mapped, not read: the retargeter reads a window of frames at a time.
    verts = load_npy(path, what="motion file", mmap=True)
    if not np.issubdtype(verts.dtype, np.number):
        raise ValueError(f"{str(path)!r} holds {verts.dtype} values, not vertex positions")
    shape = verts.shape
    if verts.ndim == 2 and verts.shape[1] % 3 == 0 and verts.shape[1] != 3:
        verts = verts.reshape(verts.shape[0], -1, 3)
    if verts.ndim != 3 or verts.shape[2] != 3 or verts.shape[0] < 1:
        raise ValueError(f"{str(path)!r}: vertices must have shape (frames, verts, 3) or (frames, 3 verts), "
                         f"got {shape}")
    for a in range(0, verts.shape[0], 256):  # a chunk at a time: the file is mapped, not read
        finite = np.isfinite(verts[a:a + 256]).reshape(-1, verts.shape[1] * 3).all(axis=1)
        if not finite.all():
            raise ValueError(f"{str(path)!r}: vertices contain NaN or inf (frame {a + int(np.argmin(finite))})")
    if opts.mesh is not None:
        from jaxtalk.geometry.canonical import load_mesh

        neutral, faces = load_mesh(opts.mesh)
        if neutral.shape[0] != verts.shape[1]:
            raise ValueError(f"{str(opts.mesh)!r} has {neutral.shape[0]} vertices but {str(path)!r} animates "
                             f"{verts.shape[1]}: not the mesh these vertices belong to")
        return verts, Retargeter.for_mesh(rig, neutral, faces, units=opts.units, penalties=penalties,
                                          landmarks=landmarks)
    if verts.shape[1] == rig.num_vertices:
        return verts, Retargeter.for_mesh(rig, rig.neutral, rig.faces, units=rig.units, penalties=penalties,
                                          landmarks=landmarks)
    for resolution in ("low", "default", "high"):
        face = builtin_face(0, resolution=resolution)
        if face.num_vertices == verts.shape[1]:
            return verts, Retargeter.for_mesh(rig, np.asarray(face.template), np.asarray(face.faces), template=face,
                                              penalties=penalties, landmarks=landmarks)
    raise ValueError(f"{str(path)!r} animates {verts.shape[1]} vertices: neither the rig's {rig.num_vertices} nor a "
                     "built-in face's; pass --mesh, the mesh file it was animated on")
