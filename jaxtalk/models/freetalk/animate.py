"""FreeTalk end to end: speech + an emotion label -> 68 landmark displacements (ATS) -> any mesh (STM).

:func:`animate` is the whole chain on a mesh a user brings (a scan in millimetres, an artist's head
in centimetres, a remeshed face):

1. :func:`prepare_user_mesh` (once per mesh): check and clean the mesh (merge duplicate vertices,
   drop zero-area faces and isolated vertices: :func:`jaxtalk.geometry.mesh_checks.clean_mesh`), find
   its units and the similarity transform into the frame STM was trained in
   (:func:`jaxtalk.geometry.canonical.align_to_face`, as the retargeter aligns a rig), then
   precompute STM's mesh operators (the robust intrinsic Laplacian where the cotangent one is unsafe:
   non-manifold edges, duplicates, degenerate
   faces) and its static per-vertex features.
2. ATS samples the landmark displacements with DDIM from the audio features its run was trained on.
   Audio longer than the ATS training window is cut into windows that overlap by a quarter window,
   sampled as ONE batch, and cross-faded linearly over the overlaps.
3. STM maps them to per-vertex displacements on the canonical mesh (fixed-size chunks of frames, so
   one compiled program serves every clip length).
4. The displacements are rotated and scaled back into the user's frame and units and added to the
   user's own vertices, in the user's own vertex order (an isolated vertex, which no face uses, stays
   still).

STM was trained on face masks, so on the parts of a scan that lie beyond the template face (neck,
shoulders, the back of a head) its output is an extrapolation: on menpo3d's head scan it moved
neck vertices 5 cm below the chin by up to 3 cm. Displacements therefore fade linearly to zero
between :data:`FADE_START_M` and :data:`FADE_END_M` from the aligned template surface (1 and 3 cm):
the face moves as STM says, what lies well outside it stays still.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from jaxtalk.data.batching import window_starts
from jaxtalk.geometry.canonical import Canonicalization, align_to_face, load_mesh
from jaxtalk.geometry.mesh_checks import CleanedMesh, clean_mesh, validate_mesh
from jaxtalk.models.freetalk.fit import FittedATS, FittedSTM, sample_displacements
from jaxtalk.models.freetalk.stm import STMMesh, prepare_mesh, stm_decode, stm_mesh_features
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS, NUM_LANDMARKS, Float, PRNGKeyArray

__all__ = ["UserMesh", "prepare_user_mesh", "landmark_track", "animate", "displace", "read_landmarks", "STM_CHUNK",
           "FADE_START_M", "FADE_END_M"]

# Frames STM decodes per call: the last chunk is padded, so clips of any length share one program.
STM_CHUNK = 25
# Distance from the aligned template face (metres, template frame) over which displacements fade out.
FADE_START_M = 0.01
FADE_END_M = 0.03
_SAMPLES_PER_FRAME = AUDIO_SAMPLE_RATE // MOTION_FPS


@dataclasses.dataclass(frozen=True, eq=False)
class UserMesh:
    """A user's mesh ready for STM (see :func:`prepare_user_mesh`).

    Attributes:
        vertices: ``(V, 3)`` the mesh as given (its units and frame).
        faces: ``(F, 3)`` as given.
        cleaned: the cleaned mesh STM runs on and the map from the input's vertices to it.
        canonical: the transform into the template frame (units, scale, rotation, translation).
        stm_mesh: STM's operators on the canonical cleaned mesh.
        features: ``(V', mesh_feature_dim)`` STM's static features of it.
        weights: ``(V',)`` in [0, 1], how much of STM's displacement each cleaned vertex takes (1 on
            the face, fading to 0 beyond it; see the module docstring).
    """

    vertices: np.ndarray
    faces: np.ndarray
    cleaned: CleanedMesh
    canonical: Canonicalization
    stm_mesh: STMMesh
    features: Any
    weights: np.ndarray

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])


def read_landmarks(path: str | os.PathLike[str], vertices: np.ndarray) -> Float[np.ndarray, "68 3"]:
    """A landmark file: ``.npy`` or whitespace ``.txt`` of ``(68, 3)`` positions in the mesh's units,
    or of ``(68,)`` integer vertex indices into ``vertices`` (the 68 standard points, iBUG order).

    Raises:
        FileNotFoundError: no such file.
        ValueError: another shape, NaN, or an index outside the mesh.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"landmark file not found: {str(p)!r}")
    if p.suffix.lower() == ".npy":
        from jaxtalk.files import load_npy

        arr = load_npy(p, what="landmark file")
    else:
        try:
            arr = np.loadtxt(p)
        except ValueError as err:
            raise ValueError(f"{str(p)!r}: cannot read landmarks ({err})") from None
    arr = np.asarray(arr)
    if arr.shape == (NUM_LANDMARKS,) and np.all(np.mod(arr, 1) == 0):
        idx = arr.astype(np.int64)
        if idx.min() < 0 or idx.max() >= vertices.shape[0]:
            raise ValueError(f"{str(p)!r}: landmark vertex indices must lie in [0, {vertices.shape[0] - 1}]")
        return np.asarray(vertices, np.float64)[idx]
    if arr.shape != (NUM_LANDMARKS, 3):
        raise ValueError(f"{str(p)!r}: landmarks must be ({NUM_LANDMARKS}, 3) positions or ({NUM_LANDMARKS},) "
                         f"vertex indices, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{str(p)!r}: landmarks contain NaN or inf")
    return arr.astype(np.float64)


def prepare_user_mesh(
    stm: FittedSTM,
    mesh: str | os.PathLike[str] | tuple[Any, Any],
    *,
    units: str | None = None,
    landmarks: Float[np.ndarray, "points 3"] | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
) -> UserMesh:
    """Clean, canonicalise and precompute a user's mesh for :func:`animate` (host side, once per mesh).

    Args:
        stm: the trained STM (its template face sets the canonical frame).
        mesh: a mesh file (OBJ, PLY, GLB/GLTF, OFF, STL) or ``(vertices (V, 3), faces (F, 3))``.
        units: the mesh's unit (``m``, ``dm``, ``cm``, ``mm``, ``um``); None: detected from its size.
        landmarks: optional ``(68, 3)`` landmark positions on the mesh (its units) to guide the
            alignment (see :func:`read_landmarks`).
        cache_dir: disk cache for the mesh operators.

    Returns:
        A :class:`UserMesh`.

    Raises:
        FileNotFoundError: a missing mesh file.
        ValueError: an unreadable file, a point cloud, NaN vertices, bad face indices, too few
            vertices for STM's eigenbasis, a size or shape that is not a face's.
    """
    if isinstance(mesh, (str, os.PathLike)):
        vertices, faces = load_mesh(mesh)
    else:
        vertices, faces = mesh
    v, f = validate_mesh(vertices, faces)
    if f.shape[0] == 0:
        raise ValueError(f"the mesh has {v.shape[0]} vertices and no faces (a point cloud); "
                         "FreeTalk animates a triangle mesh")
    cleaned = clean_mesh(v, f)
    k = stm.config.num_eigenpairs
    if cleaned.vertices.shape[0] <= k:
        raise ValueError(f"the mesh has {cleaned.vertices.shape[0]} usable vertices (of {v.shape[0]}); this STM "
                         f"needs more than its {k} Laplacian eigenpairs, i.e. a face mesh of at least {k + 1} vertices")
    face = stm.face()
    # The same alignment as a retargeted rig's (one code path): the template's landmarks carry MediaPipe's
    # canonical face over, so that real faces are aligned by a real face.
    canon = align_to_face(cleaned.vertices, cleaned.faces, face, units=units, landmarks=landmarks)
    tv = np.asarray(face.template, np.float64)
    placed = canon.to_template(cleaned.vertices)
    stm_mesh = prepare_mesh(placed, cleaned.faces, stm.config, cache_dir=cache_dir)
    features = stm_mesh_features(stm.params, stm.config, stm_mesh)
    distance, _ = cKDTree(tv).query(placed)
    weights = np.clip((FADE_END_M - distance) / (FADE_END_M - FADE_START_M), 0.0, 1.0)
    return UserMesh(vertices=v, faces=f, cleaned=cleaned, canonical=canon, stm_mesh=stm_mesh, features=features,
                    weights=weights)


def _ramp(w: int, starts: list[int], length: int) -> np.ndarray:
    """``(length,)`` unnormalised weight of window ``w``'s frames: a linear ramp over the overlap where
    it meets a neighbour, flat elsewhere."""
    ramp = np.ones(length)
    if w > 0:  # fade in over the overlap with the previous window
        over = starts[w - 1] + length - starts[w]
        ramp[:over] = np.minimum(ramp[:over], (np.arange(over) + 1) / (over + 1))
    if w < len(starts) - 1:  # fade out over the overlap with the next window
        over = starts[w] + length - starts[w + 1]
        ramp[length - over:] = np.minimum(ramp[length - over:], (over - np.arange(over)) / (over + 1))
    return ramp


def _crossfade(num_frames: int, window: int, starts: list[int]) -> np.ndarray:
    """``(W, frames)`` weights of each window's frames, summing to 1 at every output frame (the ramps
    of :func:`_ramp`, normalised): the whole-clip form of what :func:`landmark_track` accumulates
    window by window."""
    length = min(window, num_frames)
    weights = np.zeros((len(starts), num_frames))
    for w, s in enumerate(starts):
        weights[w, s:s + length] = _ramp(w, starts, length)
    return weights / weights.sum(axis=0, keepdims=True)


# Windows ATS samples per call: a long clip is sampled this many windows at a time (bounded memory),
# each window with its own noise, so the result does not depend on how the windows are grouped.
ATS_WINDOWS_PER_CALL = 8


def landmark_track(
    ats: FittedATS,
    audio: Float[np.ndarray, " samples"],
    emotion: str | int,
    intensity: float,
    key: PRNGKeyArray,
    *,
    sample_steps: int | None = None,
    windows_per_call: int = ATS_WINDOWS_PER_CALL,
) -> Float[np.ndarray, "frames 68 3"]:
    """ATS's landmark displacements (metres, template frame) for a whole 16 kHz utterance of any length.

    Windows of the run's training length overlap by a quarter window, are sampled ``windows_per_call``
    at a time (each batch padded to a power of two, so lengths share compiled programs; memory bounded
    whatever the length) and cross-faded. Window ``w`` starts from its own noise (see
    :func:`_window_noise`), so the grouping changes nothing but rounding.

    Raises:
        ValueError: bad audio (empty, NaN, silent), an emotion outside the model's vocabulary or an
            intensity outside ``[1, num_intensities]``.
    """
    from jaxtalk.audio.io import check_audio

    x = np.asarray(audio, np.float32)
    check_audio(x, AUDIO_SAMPLE_RATE)
    frames = max(1, int(round(x.shape[0] / _SAMPLES_PER_FRAME)))
    feats = ats.audio_features(x, frames)
    window = ats.window_frames
    starts = window_starts(frames, window, max(window - window // 4, 1))  # a quarter overlap, cross-faded
    length = min(window, frames)
    out = np.zeros((frames, ats.config.num_landmarks, 3), np.float64)
    total = np.zeros(frames)
    for first in range(0, len(starts), windows_per_call):
        group = list(range(first, min(first + windows_per_call, len(starts))))
        # Padded to a power of two (at most windows_per_call), so lengths share compiled programs.
        batch = 1 << (len(group) - 1).bit_length()
        group += [group[-1]] * (batch - len(group))
        noise = np.stack([_window_noise(key, w, length, ats.config.motion_dim) for w in group])
        chunks = np.stack([feats[starts[w]:starts[w] + length] for w in group])
        disp = sample_displacements(ats, chunks, emotion, intensity, key, sample_steps=sample_steps, noise=noise)
        for w, d in zip(dict.fromkeys(group), disp):
            ramp = _ramp(w, starts, length)
            out[starts[w]:starts[w] + length] += ramp[:, None, None] * d
            total[starts[w]:starts[w] + length] += ramp
    return (out / total[:, None, None]).astype(np.float32)


def _window_noise(key: PRNGKeyArray, w: int, length: int, dim: int) -> np.ndarray:
    """Window ``w``'s DDIM starting noise: what ``ats.sample`` draws from ``key`` for a batch of one
    (window 0), from ``fold_in(key, w)`` for the others."""
    import jax

    k = key if w == 0 else jax.random.fold_in(key, w)
    return np.asarray(jax.random.normal(jax.random.split(k)[0], (1, length, dim)))[0]


def animate(
    ats: FittedATS,
    stm: FittedSTM,
    audio: Float[np.ndarray, " samples"] | str | os.PathLike[str],
    emotion: str | int,
    intensity: float,
    mesh: UserMesh | str | os.PathLike[str] | tuple[Any, Any],
    *,
    key: PRNGKeyArray,
    sample_steps: int | None = None,
    units: str | None = None,
    landmarks: Float[np.ndarray, "points 3"] | None = None,
) -> Float[np.ndarray, "frames verts 3"]:
    """Animate any face mesh from speech and an emotion label: ATS, then STM, then the user's frame.

    Args:
        ats: the trained ATS (:meth:`FittedATS.from_run`).
        stm: the trained STM (:meth:`FittedSTM.from_run`).
        audio: 16 kHz mono samples, or an audio file (any rate; resampled).
        emotion: a name of the ATS model's vocabulary (``ats.config.emotions``) or its id.
        intensity: emotion intensity, continuous in ``[1, num_intensities]``.
        mesh: a :class:`UserMesh` (prepared once, reused), a mesh file, or ``(vertices, faces)``.
        key: PRNG key of the DDIM starting noise.
        sample_steps: DDIM steps (default the ATS config's).
        units, landmarks: for a mesh that is not prepared yet (see :func:`prepare_user_mesh`).

    Returns:
        ``(T, V, 3)`` float32 vertex positions at 25 fps in the mesh's own units, frame and vertex
        order (``T`` = audio duration x 25).

    Raises:
        FileNotFoundError: a missing audio or mesh file.
        ValueError: bad audio, an unknown emotion, an intensity out of range, or a mesh that cannot be
            animated (see :func:`prepare_user_mesh`).
    """
    if not isinstance(mesh, UserMesh):
        mesh = prepare_user_mesh(stm, mesh, units=units, landmarks=landmarks)
    if isinstance(audio, (str, os.PathLike)):
        from jaxtalk.audio import load_audio

        audio = load_audio(audio)
    track = landmark_track(ats, audio, emotion, intensity, key, sample_steps=sample_steps)
    return displace(stm, mesh, track)


def displace(
    stm: FittedSTM, mesh: UserMesh, landmark_disp: Float[np.ndarray, "frames 68 3"]
) -> Float[np.ndarray, "frames verts 3"]:
    """STM on a prepared user mesh: template-frame landmark displacements (metres) -> the user's
    vertex positions ``(T, V, 3)`` in its units and frame.

    Raises:
        ValueError: landmark displacements of the wrong shape or with NaN/inf.
    """
    from jaxtalk.models.freetalk.stm import check_landmark_motion

    disp = np.asarray(check_landmark_motion(landmark_disp, stm.config.num_landmarks))
    if disp.ndim != 3:
        raise ValueError(f"landmark displacements must be one sequence (frames, {stm.config.num_landmarks}, 3), "
                         f"got {disp.shape}")
    frames = disp.shape[0]
    vmap = mesh.cleaned.vertex_map
    kept = vmap >= 0
    # Filled STM_CHUNK frames at a time: the only whole-clip array is the float32 result.
    out = np.empty((frames, mesh.num_vertices, 3), np.float32)
    for s in range(0, frames, STM_CHUNK):
        chunk = disp[s:s + STM_CHUNK]
        n = chunk.shape[0]
        padded = np.concatenate([chunk, np.repeat(chunk[-1:], STM_CHUNK - n, axis=0)])  # one program for all
        canon = np.asarray(stm_decode(stm.params, stm.config, mesh.features, padded, mesh.stm_mesh))[:n]
        user = mesh.canonical.displacements_to_user(canon * mesh.weights[None, :, None])  # metres, template frame
        moved = np.zeros((n, mesh.num_vertices, 3), np.float64)
        moved[:, kept] = user[:, vmap[kept]]
        out[s:s + n] = mesh.vertices[None] + moved
    return out
