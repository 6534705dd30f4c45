"""FreeTalk training data from SynthTalk: audio features, landmark and vertex displacement windows.

* :func:`audio_features`: jaxtalk's stand-in for resampled HuBERT features: the 100 Hz log-mel
  spectrogram with each motion frame's four mel frames stacked (80 x 4 = 320 per frame at 25 fps),
  so the features are already on the motion timeline as the paper's resampled HuBERT track is.
* :func:`ats_windows`: fixed-length windows of (audio features, landmark displacements relative to
  the identity's neutral landmarks, emotion id, intensity) for ATS.
* :func:`mesh_motion`: for a face identity and a (re)meshed topology, the landmark displacements and
  the dense vertex displacements of a motion track (the STM supervision).
* :func:`stm_windows`: fixed-length windows of those over several meshes, vertex axes padded to a
  common size, for :func:`jaxtalk.models.freetalk.stm.loss`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

# Shared with ``prepare`` (a lower layer), re-exported here as part of FreeTalk's data API.
from jaxtalk.audio.speech import AUDIO_FEATURE_DIM, MEL_FRAMES_PER_FRAME, audio_features
from jaxtalk.data.batching import window_starts
from jaxtalk.data.standardize import fit_standardizer, standardize, unstandardize
from jaxtalk.face.motion import bucketed_motion, landmark_motion, without_head_pose
from jaxtalk.models.freetalk.emotions import emotion_ids
from jaxtalk.types import PARAM_DIM, Float

__all__ = [
    "FaceMesh",
    "face_mesh",
    "DisplacementStats",
    "MEL_FRAMES_PER_FRAME",
    "AUDIO_FEATURE_DIM",
    "audio_features",
    "neutral_landmarks",
    "ats_windows",
    "landmark_motion",
    "mesh_motion",
    "stm_windows",
    "without_head_pose",
]



@dataclasses.dataclass(frozen=True)
class DisplacementStats:
    """Per-coordinate mean and spread of landmark displacements, to train ATS on standardised data.

    A landmark-shaped view of :mod:`jaxtalk.data.standardize` (which fits and applies the statistics;
    the 3N coordinates are its channels). The diffusion noise is unit-variance per coordinate, so ATS
    learns best on data with zero mean and unit spread; the mean is also the mean-pose baseline. Use
    with ``displacement_scale = 1``.

    Attributes:
        mean: ``(N, 3)`` mean displacement (metres).
        std: ``(N, 3)`` standard deviation, floored at ``floor`` x its average so that nearly
            static landmarks are not blown up into noise.
    """

    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, displacements: Float[np.ndarray, "*batch 68 3"], floor: float = 0.2) -> DisplacementStats:
        """Statistics over every leading axis of ``displacements`` (e.g. windows and frames).

        Raises:
            ValueError: fewer than 2 frames, NaN/inf values, or not ``(..., N, 3)``.
        """
        d = np.asarray(displacements)
        if d.ndim < 3 or d.shape[-1] != 3:
            raise ValueError(f"displacements must have shape (..., frames, N, 3), got {d.shape}")
        try:
            stats = fit_standardizer(d.reshape(-1, d.shape[-2] * 3), floor=floor)
        except ValueError as err:
            raise ValueError(f"cannot fit displacement statistics on shape {d.shape}: {err}") from None
        return cls(mean=stats["mean"].reshape(d.shape[-2:]), std=stats["std"].reshape(d.shape[-2:]))

    def as_standardizer(self) -> dict[str, np.ndarray]:
        """The ``{"mean", "std"}`` dict of :mod:`jaxtalk.data.standardize` (flat ``(3N,)`` channels)."""
        return {"mean": self.mean.reshape(-1), "std": self.std.reshape(-1)}

    def normalize(self, displacements: Any) -> Any:
        """``(d - mean) / std`` (NumPy or JAX, any leading axes; NumPy in, NumPy out)."""
        return self._map(standardize, displacements)

    def denormalize(self, standardized: Any) -> Any:
        """Inverse of :meth:`normalize`."""
        return self._map(unstandardize, standardized)

    def _map(self, fn: Any, x: Any) -> Any:
        # NumPy stays NumPy (the loader's path; see jaxtalk.data.standardize), anything else is JAX.
        xp = np if isinstance(x, np.ndarray) else jnp
        flat = xp.asarray(x, xp.float32).reshape(*np.shape(x)[:-2], -1)
        return fn(self.as_standardizer(), flat).reshape(np.shape(x))


@dataclasses.dataclass(frozen=True, eq=False)
class FaceMesh:
    """A face identity on one mesh topology: the face model, the remeshing (None for the base mesh),
    and the neutral mesh.

    Attributes:
        face: the :class:`jaxtalk.face.LinearFaceModel`.
        variant: a :class:`jaxtalk.geometry.topology.TopologyVariant`, or None.
        vertices: ``(V, 3)`` neutral vertices (metres); faces: ``(F, 3)`` triangles.
        name: e.g. ``"id3/retriangulated"``.
    """

    face: Any
    variant: Any
    vertices: np.ndarray
    faces: np.ndarray
    name: str

    def region(self, name: str) -> np.ndarray:
        """Vertex indices of a named face region on this mesh.

        A remeshed vertex belongs to the region when its nearest base corner does (the corner of the
        base triangle it lies in with the largest barycentric coordinate).

        Raises:
            ValueError: unknown region name.
        """
        if name not in self.face.regions:
            raise ValueError(f"unknown region {name!r}; known: {sorted(self.face.regions)}")
        base = np.asarray(self.face.regions[name])
        if self.variant is None:
            return base
        corners = self.variant.base_faces[self.variant.face_index]  # (V', 3)
        nearest = corners[np.arange(len(corners)), np.argmax(self.variant.barycentric, axis=1)]
        return np.flatnonzero(np.isin(nearest, base))

    def motion(self, motion: Float[np.ndarray, "frames params"]) -> tuple[np.ndarray, np.ndarray]:
        """``(landmark_disp (T, 68, 3), vertex_disp (T, V, 3))`` of a motion track on this mesh."""
        lms, verts, _ = mesh_motion(self.face, motion, self.variant)
        return lms, verts


def face_mesh(identity: int, kind: str = "base", *, resolution: str = "low", seed: int | None = None) -> FaceMesh:
    """The built-in face of an identity on a topology ("base" or a :mod:`jaxtalk.geometry.topology` kind).

    Args:
        identity: built-in face identity (0 = mean face).
        kind: "base", "subdivided", "decimated", "retriangulated" or "shuffled".
        resolution: built-in face resolution ("low", "default", "high").
        seed: remeshing seed (default: the identity).

    Returns:
        A :class:`FaceMesh`.

    Raises:
        ValueError: unknown kind or resolution.
    """
    from jaxtalk.face import builtin_face
    from jaxtalk.geometry.topology import make_variant

    face = builtin_face(identity, resolution=resolution)
    template, tris = np.asarray(face.template, np.float64), np.asarray(face.faces)
    if kind == "base":
        return FaceMesh(face, None, template, tris, f"id{identity}/base")
    variant = make_variant(template, tris, kind, seed=identity if seed is None else seed)
    return FaceMesh(face, variant, np.asarray(variant.vertices), np.asarray(variant.faces), f"id{identity}/{kind}")


def neutral_landmarks(face: Any) -> Float[np.ndarray, "68 3"]:
    """``L_tpl``: the landmarks of a face model at the zero parameter vector (its neutral template)."""
    return np.asarray(face.landmarks(jnp.zeros(PARAM_DIM, jnp.float32)))


def ats_windows(
    corpus: Any,
    clips: Sequence[int],
    *,
    identity: int = 0,
    window: int = 50,
    hop: int = 25,
    head_pose: bool = False,
) -> dict[str, np.ndarray]:
    """ATS training windows from SynthTalk clips.

    Args:
        corpus: a :class:`jaxtalk.data.synthtalk.SynthTalkCorpus`.
        clips: clip indices (e.g. ``corpus.split("train")``).
        identity: face identity whose landmarks are used.
        window: frames per window.
        hop: frames between window starts.
        head_pose: keep the neck rotation in the landmark motion (default: face deformation only,
            see :func:`without_head_pose`).

    Returns:
        ``{"displacements": (N, W, 68, 3), "audio": (N, W, 320), "emotion": (N,) int32,
        "intensity": (N,) float32, "clip": (N,) int32, "start": (N,) int32}``.

    Raises:
        ValueError: no clip is at least ``window`` frames long.
    """
    face = corpus.face(identity)
    out: dict[str, list] = {k: [] for k in ("displacements", "audio", "emotion", "intensity", "clip", "start")}
    for c in clips:
        info = corpus.clips[c]
        motion = corpus.motion(c) if head_pose else without_head_pose(corpus.motion(c))
        disp = landmark_motion(face, motion)
        feats = audio_features(corpus.audio(c), disp.shape[0])
        emo = int(emotion_ids(info.emotion)[0])
        for s in window_starts(disp.shape[0], window, hop, pad_short=False):
            out["displacements"].append(disp[s:s + window])
            out["audio"].append(feats[s:s + window])
            out["emotion"].append(emo)
            out["intensity"].append(float(info.intensity))
            out["clip"].append(c)
            out["start"].append(s)
    if not out["clip"]:
        raise ValueError(f"no clip among {len(clips)} is at least window={window} frames long")
    return {
        "displacements": np.stack(out["displacements"]).astype(np.float32),
        "audio": np.stack(out["audio"]),
        "emotion": np.asarray(out["emotion"], np.int32),
        "intensity": np.asarray(out["intensity"], np.float32),
        "clip": np.asarray(out["clip"], np.int32),
        "start": np.asarray(out["start"], np.int32),
    }


def mesh_motion(
    face: Any, motion: Float[np.ndarray, "frames params"], variant: Any = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Landmark and vertex displacements of a motion track on a face, optionally remeshed.

    Args:
        face: a :class:`jaxtalk.face.LinearFaceModel`.
        motion: ``(T, 56)`` head parameters.
        variant: a :class:`jaxtalk.geometry.topology.TopologyVariant` of ``face``'s template, or None
            for the face's own mesh.

    Returns:
        ``(landmark_disp (T, 68, 3), vertex_disp (T, V', 3), rest_vertices (V', 3))`` float32, metres.

    Raises:
        ValueError: motion not of shape ``(T > 0, 56)``.
    """
    rows, n = bucketed_motion(motion)
    lms_all = np.asarray(face.landmarks_seq(rows))
    verts_all = np.asarray(face.vertices_seq(rows))
    if variant is not None:
        verts_all = np.asarray(variant.transfer(verts_all))
    lms = lms_all[1 : n + 1] - lms_all[:1]
    verts, rest = verts_all[1 : n + 1], verts_all[:1]
    return lms.astype(np.float32), (verts - rest).astype(np.float32), rest[0].astype(np.float32)


def stm_windows(
    tracks: Sequence[tuple[int, np.ndarray, np.ndarray]],
    num_vertices: int,
    *,
    window: int = 16,
    hop: int = 16,
) -> dict[str, np.ndarray]:
    """STM training windows over several meshes, vertex axes zero-padded to ``num_vertices``.

    Args:
        tracks: ``(mesh index, landmark_disp (T, 68, 3), vertex_disp (T, V_m, 3))`` per track.
        num_vertices: common padded vertex count (>= every V_m).
        window: frames per window.
        hop: frames between window starts.

    Returns:
        ``{"mesh": (N,) int32, "landmarks": (N, W, 68, 3), "vertices": (N, W, num_vertices, 3)}``.

    Raises:
        ValueError: a track with more vertices than ``num_vertices`` or no window at all.
    """
    mesh, lms, verts = [], [], []
    for idx, lm, vd in tracks:
        if vd.shape[1] > num_vertices:
            raise ValueError(f"track of mesh {idx} has {vd.shape[1]} vertices > num_vertices={num_vertices}")
        padded = np.pad(vd, ((0, 0), (0, num_vertices - vd.shape[1]), (0, 0)))
        for s in window_starts(lm.shape[0], window, hop, pad_short=False):
            mesh.append(idx)
            lms.append(lm[s:s + window])
            verts.append(padded[s:s + window])
    if not mesh:
        raise ValueError(f"no track is at least window={window} frames long")
    return {
        "mesh": np.asarray(mesh, np.int32),
        "landmarks": np.stack(lms).astype(np.float32),
        "vertices": np.stack(verts).astype(np.float32),
    }
