"""``jaxtalk render``: head parameters (.npz) or vertices (.npy) -> mp4 (with audio) or GIF.

Parameters ``(T, 56)`` are posed on the built-in face (or your FLAME model file); a vertex sequence
``(T, V, 3)`` or ``(T, 3V)`` is drawn on the built-in face's triangles when ``V`` matches one of its
resolutions, else on ``--faces``. A second file renders beside the first (same camera, cropped to the
shorter clip), e.g. ground truth next to a prediction.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.face.model import LinearFaceModel
from jaxtalk.types import PARAM_DIM, Float

__all__ = ["RenderOptions", "Motion", "face_model", "read_params", "read_head_clip", "load_motion", "render_file"]

_RESOLUTIONS = ("low", "default", "high")


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """Settings of :func:`render_file`.

    Attributes:
        input: ``.npz`` with ``params`` (or the demo's ``params56``), or ``.npy`` vertices.
        out: ``.mp4`` or ``.gif`` (None: ``render.mp4``, which replaces no existing file without
            ``overwrite``); an input is never written over.
        audio: audio track for an mp4 (default: the audio stored in the input npz, if any).
        compare: a second input rendered beside the first.
        faces: ``(F, 3)`` int ``.npy`` triangles for vertices of another mesh.
        flame: a FLAME 2020 model file to pose parameters on instead of the built-in face.
        size: panel size in pixels.
        captions: caption each panel with its file stem.
        overwrite: let the default output name replace an existing file.
    """

    input: Path
    out: Path | None = None
    audio: Path | None = None
    compare: Path | None = None
    faces: Path | None = None
    flame: Path | None = None
    size: int = 256
    captions: bool = True
    overwrite: bool = False


@dataclasses.dataclass
class Motion:
    """One clip ready to draw.

    Attributes:
        vertices: ``(T, V, 3)``.
        faces: ``(F, 3)``.
        rest: ``(V, 3)`` neutral mesh (for the cavity shading), or None.
        audio: 16 kHz audio stored with the clip, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    rest: np.ndarray | None
    audio: np.ndarray | None


def _require(path: Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"file not found: {str(path)!r}")
    return path


def read_params(path: str | Path) -> Float[np.ndarray, "frames 56"]:
    """``(T, 56)`` head parameters from a generic npz (``params``) or a demo output (``params56``).

    Raises:
        FileNotFoundError: missing file.
        ValueError: not an npz, no parameters in it, wrong width, NaN.
    """
    return read_head_clip(path)[0]


def read_head_clip(path: str | Path) -> tuple[Float[np.ndarray, "frames 56"], Float[np.ndarray, " samples"] | None, float]:
    """``(params, audio, fps)`` of a parameters ``.npz`` (audio: 16 kHz, or None; a demo output is 25 fps).

    Raises:
        As :func:`read_params`.
    """
    from jaxtalk.data.formats import read_npz
    from jaxtalk.files import load_npz
    from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

    path = _require(Path(path))
    data = load_npz(path, what="motion file")
    if "params56" in data:  # `jaxtalk demo`'s prediction.npz
        params, audio, fps = np.asarray(data["params56"], np.float32), None, float(MOTION_FPS)
    else:
        clip = read_npz(path, load_audio=True)
        if clip.params is None:
            raise ValueError(f"{str(path)!r} holds no 'params' ({PARAM_DIM}-d) array; found {sorted(data)}")
        params = np.asarray(clip.params, np.float32)
        audio = None if clip.audio is None else np.asarray(clip.audio, np.float32)
        if audio is not None and clip.sample_rate != AUDIO_SAMPLE_RATE:
            from jaxtalk.audio import resample_audio

            audio = resample_audio(audio, clip.sample_rate, AUDIO_SAMPLE_RATE)
        fps = float(clip.fps)
    if params.ndim != 2 or params.shape[1] != PARAM_DIM or params.shape[0] < 1:
        raise ValueError(f"{str(path)!r}: params must have shape (frames, {PARAM_DIM}), got {params.shape}")
    if not np.all(np.isfinite(params)):
        raise ValueError(f"{str(path)!r}: params contain NaN or inf")
    return params, audio, fps


def face_model(flame: str | Path | None = None) -> LinearFaceModel:
    """The face model parameters are posed on: the FLAME model file ``flame``, else the built-in face.

    Raises:
        FileNotFoundError: a missing FLAME file.
    """
    if flame is not None:
        from jaxtalk.face import load_flame

        return load_flame(_require(Path(flame)))
    from jaxtalk.face import builtin_face

    return builtin_face(0)


def _builtin_faces(num_vertices: int) -> tuple[np.ndarray, np.ndarray] | None:
    from jaxtalk.face import builtin_face

    for resolution in _RESOLUTIONS:
        face = builtin_face(0, resolution=resolution)
        if face.num_vertices == num_vertices:
            return np.asarray(face.faces), np.asarray(face.template)
    return None


def load_motion(path: str | Path, *, faces: str | Path | None = None, flame: str | Path | None = None) -> Motion:
    """Read one clip to render (see the module docstring).

    Args:
        path: ``.npz`` parameters or ``.npy`` vertices.
        faces: triangles for vertices that are not on the built-in face: an ``(F, 3)`` ``.npy``, or
            the mesh file they were animated on (OBJ, PLY, GLB/GLTF, OFF, STL).
        flame: FLAME model file to pose parameters on.

    Returns:
        :class:`Motion`.

    Raises:
        FileNotFoundError: missing file.
        ValueError: unknown suffix, bad shapes, NaN, vertices of an unknown mesh without ``faces``.
    """
    path = _require(Path(path))
    suffix = path.suffix.lower()
    if suffix == ".npz":
        params, audio, _ = read_head_clip(path)
        face = face_model(flame)
        verts = np.asarray(face.vertices_seq(params), np.float32)
        return Motion(verts, np.asarray(face.faces), np.asarray(face.template, np.float32), audio)
    if suffix != ".npy":
        raise ValueError(f"{str(path)!r}: expected .npz parameters or .npy vertices, got {suffix or 'no suffix'!r}")
    from jaxtalk.files import load_npy

    verts = load_npy(path, what="vertex sequence")
    if not np.issubdtype(verts.dtype, np.number):
        raise ValueError(f"{str(path)!r} holds {verts.dtype} values, not vertex positions")
    if verts.ndim == 2 and verts.shape[1] == 3:  # (points, 3): one mesh's positions, not frames of 1 vertex
        raise ValueError(f"{str(path)!r} holds a {verts.shape} array: one set of 3-D points, not a (frames, vertices, 3) "
                         "animation; save the frames stacked as (frames, vertices, 3)")
    if verts.ndim == 2 and verts.shape[1] % 3 == 0:
        verts = verts.reshape(verts.shape[0], -1, 3)
    if verts.ndim != 3 or verts.shape[2] != 3 or verts.shape[0] < 1:
        raise ValueError(f"{str(path)!r}: vertices must have shape (frames, verts, 3) or (frames, 3 verts), "
                         f"got {verts.shape}")
    if not np.all(np.isfinite(verts)):
        raise ValueError(f"{str(path)!r}: vertices contain NaN or inf")
    if faces is not None:
        faces_path = _require(Path(faces))
        if faces_path.suffix.lower() == ".npy":
            tri = load_npy(faces_path, what="faces file")
        else:  # the mesh file the vertices were animated on (FreeTalk's output keeps its vertex order)
            from jaxtalk.geometry.canonical import load_mesh

            mesh_vertices, tri = load_mesh(faces_path)
            if mesh_vertices.shape[0] != verts.shape[1]:
                raise ValueError(f"{str(faces_path)!r} has {mesh_vertices.shape[0]} vertices but {str(path)!r} "
                                 f"animates {verts.shape[1]}: not the mesh these vertices belong to")
        return Motion(verts.astype(np.float32), np.asarray(tri), None, None)
    found = _builtin_faces(verts.shape[1])
    if found is None:
        raise ValueError(f"{str(path)!r} has {verts.shape[1]} vertices, not a built-in face mesh: pass --faces")
    return Motion(verts.astype(np.float32), found[0], found[1], None)


def render_file(opts: RenderOptions) -> Path:
    """Render ``opts.input`` (and ``opts.compare`` beside it) to ``opts.out``.

    Returns:
        The written file.

    Raises:
        FileNotFoundError: a missing input, audio, faces or FLAME file.
        ValueError: a bad output suffix, bad inputs (see :func:`load_motion`), bad audio.
    """
    from jaxtalk.files import Output, claim_outputs
    from jaxtalk.render import render_clip

    (out,) = claim_outputs([Output(Path(opts.out or "render.mp4"), named=opts.out is not None, suffixes=(".mp4", ".gif"))],
                           [opts.input, opts.audio, opts.compare, opts.faces, opts.flame], overwrite=opts.overwrite)
    if opts.size < 16:
        raise ValueError(f"--size must be at least 16 pixels, got {opts.size}")
    clips = [load_motion(opts.input, faces=opts.faces, flame=opts.flame)]
    names = [Path(opts.input).stem]
    if opts.compare is not None:
        clips.append(load_motion(opts.compare, faces=opts.faces, flame=opts.flame))
        names.append(Path(opts.compare).stem)
    frames = min(c.vertices.shape[0] for c in clips)
    audio: Any = None
    if out.suffix.lower() == ".mp4":
        if opts.audio is not None:
            from jaxtalk.audio import load_audio

            audio = load_audio(opts.audio, allow_silence=True)
        else:
            audio = next((c.audio for c in clips if c.audio is not None), None)
    elif opts.audio is not None:
        raise ValueError("a GIF has no audio track: write an .mp4 to use --audio")
    return render_clip(out, [c.vertices[:frames] for c in clips], [c.faces for c in clips], audio=audio,
                       captions=names if opts.captions else None, size=opts.size,
                       rest_vertices=[c.rest for c in clips])
