"""Meshes a user brings, read and put in the frame a face model was trained in.

STM (FreeTalk's Sparse-To-Mesh) is intrinsic except for its xyz/normal input: it was trained on faces
in metres, centred, looking along +z with +y up (the built-in face's frame). A scan or an artist's
head comes in millimetres or centimetres, anywhere in space, facing anywhere. This module:

* :func:`load_mesh`: OBJ / PLY / GLB / GLTF / OFF / STL with the file's own vertices in the file's order
  (:mod:`jaxtalk.geometry.mesh_io`; a glTF scene is flattened with its node transforms), with clear errors
  for a missing file, a point cloud or a file with no triangles.
* :func:`detect_units`: the unit from the largest bounding-box side, which for a face or a head is
  8-45 cm: one of ``m``, ``dm`` (a captured head that a glTF file, nominally in metres, stores ten
  times too large), ``cm``, ``mm`` (and ``um``, the Basel Face Model's micrometres) fits, or the size
  makes no sense for a face and the error says so.
* :func:`canonicalize`: a similarity transform (scale, rotation, translation) from the user's frame to
  the template's, landmark-free by default (with 68 user landmarks, Umeyama on the landmarks).
* :func:`align_to_face`: :func:`canonicalize` onto a face model's neutral with that face's own
  landmarks, the one way FreeTalk's meshes and the retargeter's rigs are aligned.

The landmark-free alignment fits a *reference face* to the user's surface and carries it over to the
template through the two faces' landmarks. The built-in template is a procedural face whose
forehead, nose bridge and chin lie about 2 cm behind a real face's, so a surface fit of it to a real
face lines up skin instead of features (or lays it upside down on the chin). The reference for real
faces is MediaPipe's canonical face (an average real face, Apache-2.0, ``data/``); the template itself
is the reference for meshes of its own kind (the built-in faces). Both are tried when the template's
landmarks are given, and the one that fits the user's surface better is used.

Separate surfaces inside the face (eyeballs, teeth, gums, a tongue, lashes, a mouth bag: what a face
kit or a captured head adds beside its skin) are left out of the fit (:func:`_inner_parts`): a
connected component (coincident vertices merged) that lies within the convex hull of the rest of the
mesh is one of them; the reference face has none, and they pull the fit onto the wrong reference.
:attr:`Canonicalization.ignored` names them by their vertex counts. For each reference:

1. Its inner face (:class:`_Face`: the front of the face inside an ellipse, the rim left out because a
   cropped mask may not reach it), each point weighted by its relief, is placed on the user's surface
   in candidate poses: the rotations that map the principal axes of the two surfaces onto each other
   (24, each also turned about the user's longest axis, along which a head's crown-to-neck runs, since
   a head's width and depth are alike) and the 24 of the file's own axes, at the reference's size,
   plus :data:`_GRID_ROTATIONS` rotations spread evenly over all of them (:func:`_rotation_grid`):
   a head whose longest axis runs diagonally (from the chin to the back of the skull, as a captured
   head with a short neck has it) has principal axes that point nowhere in particular, and the file's
   own axes only help a head stored upright, so without the grid such a head turned 30 or 60 degrees
   about x or y was refused. Each is put at the front of the user's surface as seen from the
   candidate's forward direction in two ways (:func:`_front_anchors`: the middle of the front, and
   the nose tip).
2. The best distinct candidates (where they start) take a few steps of rigid, trimmed, point-to-plane
   ICP; the best of those by how well they fit both ways (:func:`_pose_score`: the reference onto the
   user's surface, and the user's surface over the reference's inner face back onto it) run to
   convergence, and the best of them is refined with the scale free (within a face's range).
3. A fit whose residual or scale is implausible for a face is an error, never a silent far-off answer.
   The limits and the fits they separate: ``_MAX_FIT_M`` and docs/design-decisions.md.

:class:`Canonicalization` maps positions to the template frame and displacements back into the
user's units and frame (a displacement rotates and scales but does not translate).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.geometry.mesh_io import MESH_SUFFIXES, load_mesh
from jaxtalk.types import Float, Int

__all__ = [
    "UNITS",
    "describe_parts",
    "umeyama",
    "MESH_SUFFIXES",
    "FACE_EXTENT_M",
    "MEDIAPIPE_FACE_FILE",
    "MEDIAPIPE_IBUG",
    "Canonicalization",
    "load_mesh",
    "detect_units",
    "reference_face",
    "canonicalize",
    "face_reference",
    "align_to_face",
]

# Metres per unit.
UNITS: dict[str, float] = {"m": 1.0, "dm": 1e-1, "cm": 1e-2, "mm": 1e-3, "um": 1e-6}
# The largest bounding-box side of a face mask (about 15-20 cm) or a whole head with neck (up to
# about 35 cm), with margin. The ranges of the units do not overlap (the range spans a factor of 5.6,
# neighbouring units a factor of 10), so detection is unambiguous.
FACE_EXTENT_M = (0.08, 0.45)
# The reference face for real faces: MediaPipe's canonical face (468 vertices, centimetres, +y up,
# +z toward the viewer), and the vertex of it at each of these iBUG-68 landmarks: chin 8, brows 17,
# 19, 21 / 22, 24, 26, nasion 27, nose tip 30, subnasale 33, eye corners 36, 39 / 42, 45, mouth
# corners 48 / 54, the middle of the upper and lower lip 51 / 57.
MEDIAPIPE_FACE_FILE = Path(__file__).resolve().parent / "data" / "mediapipe_canonical_face.obj"
MEDIAPIPE_IBUG: dict[int, int] = {8: 152, 17: 70, 19: 105, 21: 107, 22: 336, 24: 334, 26: 300, 27: 168, 30: 4, 33: 2,
                                  36: 33, 39: 133, 42: 362, 45: 263, 48: 61, 54: 291, 51: 0, 57: 17}
# A fitted similarity scale outside this range means the mesh is not a human face at real size.
_SCALE_RANGE = (0.6, 1.6)
# After alignment, the reference's inner face must fit the user's surface within this (metres; the
# relief-weighted, capped mean distance of _fit_score, dominated by nose, eyes, mouth and chin). It lies
# between the fits of real faces and of face-sized shapes that are no face (docs/design-decisions.md).
_MAX_FIT_M = 0.004
# The inner face: an ellipse of these fractions of the face's half-width and of its half-height below
# and above the centre of its bounding box (see _Face).
_CORE = (0.8, 0.9, 0.6)
# Weight of a point of the inner face beyond its relief (see _Face).
_FLAT_WEIGHT = 0.25
# Depth of the front of a face behind the tip of the nose that _front_anchors centres on: the eyes,
# mouth, chin and forehead lie within it, the ears and the neck behind it.
_FRONT_DEPTH_M = 0.05
# Turns (degrees) of each principal-axes candidate about the user's longest axis, and the sizes
# (relative to the reference's) the search starts from.
_TURNS = tuple(range(-75, 91, 15))
_SEARCH_SCALES = (0.7, 0.85, 1.0, 1.2, 1.45)
# Rotations of the even grid every search also starts from (_rotation_grid): any rotation lies within
# 21 degrees of one of them (12 on average), which a few steps of ICP close.
_GRID_ROTATIONS = 1000
# The search fits this many points of the inner face; this many distinct candidates (20 degrees or
# 1 cm apart) take _FIRST_STEPS steps of ICP, and the best _REFINED of them run to convergence.
_PROBE_POINTS = 120
_TRIED = 40
# The grid's candidates are ranked apart (they are many and most lie far off: ranked together with the
# principal-axes ones they crowd out the right start of a head whose axes say where its face is), and
# this many distinct ones of them take the first steps of ICP too.
_GRID_TRIED = 40
_FIRST_STEPS = 6
_REFINED = 6
# ICP leaves out pairs farther apart than _TRIM x the median distance (and than the floor, metres).
_TRIM = 2.5
_TRIM_FLOOR_M = 0.004
# Distances are capped here in the scores (metres).
_SCORE_CAP_M = 0.015
# The largest rotation (radians) one ICP step takes.
_MAX_TURN = 0.1
# Neighbours of a user sample that give its normal.
_NORMAL_NEIGHBOURS = 12
# The principal axes, the front anchors and _overlap look at every this-many user samples.
_COARSE_STRIDE = 4
# The distance field of the user's surface (see _Surface): voxels of this side (or larger, so that
# the grid has at most _FIELD_MAX_VOXELS along a side), distances capped here.
_FIELD_VOXEL_M = 0.003
_FIELD_MAX_VOXELS = 160
_FIELD_CAP_M = 0.025
# A connected component with at least this fraction of its area inside the convex hull of the rest of
# the mesh (within _HULL_TOLERANCE_M) is an inner part (eyeballs, teeth, tongue), left out of the fit;
# only the _MAX_PARTS largest components besides the largest are considered (scan debris is too small
# to matter either way).
_INNER_FRACTION = 0.9
_HULL_TOLERANCE_M = 0.001
_MAX_PARTS = 32
# Samples of each surface (area-weighted).
_FACE_POINTS = 4000
_USER_POINTS = 20000

Pose = tuple[float, np.ndarray, np.ndarray]  # (scale, rotation, translation): x -> scale * rotation @ x + translation


def describe_parts(ignored: tuple[int, ...], shown: int = 6) -> str:
    """The separate parts an alignment left out, for a person: ``"3 separate parts lying inside the rest
    (642, 642, 386 vertices)"``; past ``shown`` parts, the largest and the total (a face kit has dozens).
    Named by size, not by kind: eyeballs and teeth look like this, and so do a scan's loose bits."""
    many = len(ignored) > shown
    counts = ", ".join(str(n) for n in ignored[:shown]) + (", ..." if many else "")
    total = f"; {sum(ignored)} vertices in all" if many else ""
    return (f"{len(ignored)} separate part{'s' if len(ignored) > 1 else ''} lying inside the rest "
            f"({counts} vertices{total})")


@dataclasses.dataclass(frozen=True)
class Canonicalization:
    """``x_template = scale * rotation @ x_user + translation`` (``x_user`` in the user's units).

    Attributes:
        units: the user's unit (a key of :data:`UNITS`).
        scale: template metres per user unit (the unit factor times the fitted similarity scale).
        rotation: ``(3, 3)`` proper rotation.
        translation: ``(3,)`` metres.
        residual: mean distance (metres, template frame) of the reference face's inner face to the
            aligned user surface (the landmarks' mean distance after the fit with ``"landmarks"``).
        method: ``"icp"`` (landmark-free) or ``"landmarks"``.
        reference: the face fitted to the user's surface: ``"mediapipe"`` (MediaPipe's canonical face,
            carried over to the template by the landmarks of both), ``"template"`` or ``"landmarks"``.
        ignored: the vertex counts of the separate parts inside the face (eyeballs, teeth, a tongue)
            left out of the landmark-free fit, largest first; empty when there were none.
    """

    units: str
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residual: float
    method: str
    reference: str = "template"
    ignored: tuple[int, ...] = ()

    @property
    def fitted_scale(self) -> float:
        """The similarity scale beyond the unit conversion (1 = the template's size)."""
        return self.scale / UNITS[self.units]

    def describe(self) -> str:
        """One line for a person: the units, how and through which face it was aligned, the scale, the
        mean distance and the separate parts left out."""
        via = " via MediaPipe's canonical face" if self.reference == "mediapipe" else ""
        line = (f"units {self.units}, aligned to the template by {self.method}{via} (scale {self.fitted_scale:.3f}, "
                f"mean distance {self.residual * 1000:.1f} mm)")
        if self.ignored:
            line += f"; left out {describe_parts(self.ignored)}"
        return line

    def to_template(self, points: Float[np.ndarray, "*n 3"]) -> Float[np.ndarray, "*n 3"]:
        """User positions -> template frame (metres)."""
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation

    def to_user(self, points: Float[np.ndarray, "*n 3"]) -> Float[np.ndarray, "*n 3"]:
        """Template positions (metres) -> the user's units and frame."""
        return (np.asarray(points, np.float64) - self.translation) @ self.rotation / self.scale

    def displacements_to_user(self, displacements: Float[np.ndarray, "*n 3"]) -> Float[np.ndarray, "*n 3"]:
        """Template-frame displacements (metres) -> the user's units and frame (no translation)."""
        return np.asarray(displacements, np.float64) @ self.rotation / self.scale


def _extent(vertices: np.ndarray) -> float:
    return float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))


def detect_units(vertices: Float[np.ndarray, "verts 3"]) -> str:
    """The unit a face mesh is stored in, from its largest bounding-box side.

    Args:
        vertices: ``(V, 3)`` positions.

    Returns:
        ``"m"``, ``"dm"``, ``"cm"``, ``"mm"`` or ``"um"``: the unit in which the largest side lies in
        :data:`FACE_EXTENT_M`.

    Raises:
        ValueError: no unit makes it the size of a face (with the measured size in the message).
    """
    extent = _extent(np.asarray(vertices, np.float64))
    lo, hi = FACE_EXTENT_M
    for name, metres in UNITS.items():
        if lo <= extent * metres <= hi:
            return name
    sizes = ", ".join(f"{extent * m:.3g} m if {u}" for u, m in UNITS.items())
    raise ValueError(
        f"the mesh's largest side is {extent:.4g} units, which is not the size of a face or a head "
        f"({lo * 100:.0f}-{hi * 100:.0f} cm) in any unit ({sizes}); give its units "
        f"(--units {', '.join(list(UNITS)[:-1])} or {list(UNITS)[-1]}) if it really is a face"
    )


@functools.lru_cache(maxsize=1)
def reference_face() -> tuple[Float[np.ndarray, "468 3"], Int[np.ndarray, "898 3"]]:
    """MediaPipe's canonical face in metres (vertices, triangles): the reference for real faces."""
    v, f = load_mesh(MEDIAPIPE_FACE_FILE)
    v = v * UNITS["cm"]
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points spread over the surface by area (deterministic) and the unit normals of their
    triangles: points drawn on triangles chosen with probability proportional to area, which does not
    depend on how densely a region is meshed."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    total = area.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("the mesh has zero surface area (every face is degenerate)")
    rng = np.random.default_rng(seed)
    pick = rng.choice(faces.shape[0], size=count, p=area / total)
    w = rng.dirichlet(np.ones(3), size=count)
    normals = cross[pick] / np.maximum(2.0 * area[pick], np.finfo(float).tiny)[:, None]
    return np.einsum("nk,nkd->nd", w, tri[pick]), normals


def _inner_parts(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """``(kept, ignored)``: which triangles the fit uses, and the vertex counts of the separate parts
    inside the face that it leaves out (largest first).

    A face kit or a captured head brings eyeballs, teeth, gums, a tongue or lashes as surfaces of their
    own beside the skin. The reference faces have none of them, and where they show (an eyeball in an
    open eye, teeth between parted lips) they pull the fit, or make the wrong reference fit better. Such
    a part is a connected component (coincident vertices merged: :func:`face_components`) other than
    the largest, with at least :data:`_INNER_FRACTION` of its area inside the convex hull of the rest of
    the mesh. What lies outside the rest (a skull, a neck, ears, a face beside the back of its head)
    stays, and a mesh of one piece is untouched.
    """
    from scipy.spatial import ConvexHull

    from jaxtalk.geometry.mesh_checks import face_components

    labels = face_components(vertices, faces)
    count = int(labels.max()) + 1 if labels.size else 0
    kept = np.ones(len(faces), bool)
    if count < 2:
        return kept, ()
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    order = np.argsort(-np.bincount(labels, area, minlength=count), kind="stable")
    candidates = order[1:1 + _MAX_PARTS]

    def hull_points(part: int) -> np.ndarray:
        points = vertices[np.unique(faces[labels == part])]
        try:
            return points[ConvexHull(points).vertices]
        except Exception:  # scipy's QhullError: a flat or tiny part is its own hull
            return points

    outline = {int(part): hull_points(int(part)) for part in (order[0], *candidates)}
    rest_of = vertices[np.unique(faces[~np.isin(labels, list(outline))])]  # the parts too small to consider
    ignored = []
    for part in candidates:
        others = np.concatenate([rest_of] + [pts for other, pts in outline.items() if other != part])
        try:
            hull = ConvexHull(others)
        except Exception:  # the rest is flat: nothing lies inside it
            continue
        mine = labels == part
        centres = tri[mine].mean(axis=1)
        inside = np.all(centres @ hull.equations[:, :3].T + hull.equations[:, 3] <= _HULL_TOLERANCE_M, axis=1)
        if area[mine] @ inside >= _INNER_FRACTION * area[mine].sum():
            kept &= ~mine
            ignored.append(int(np.unique(faces[mine]).size))
    return kept, tuple(sorted(ignored, reverse=True))


@dataclasses.dataclass(frozen=True)
class _Face:
    """A face fitted to the user's surface: surface samples in metres in its own frame (+y up, +z out
    of the face).

    Attributes:
        points: ``(P, 3)`` samples of the whole face.
        tree: their KD-tree.
        core: ``(C, 3)`` its inner face, which every face mesh covers: the front-facing samples inside
            an ellipse of :data:`_CORE` (eyes, nose, mouth, cheeks, chin, lower forehead). The outer
            rim, which a cropped mask (a BFM-style mask) may not reach, is left out.
        weights: ``(C,)`` how much each core point counts: its relief, i.e. its height above or below
            the smooth quadric surface that fits the inner face best (normalised to mean 1), plus
            :data:`_FLAT_WEIGHT`. The nose, the eye sockets, the lips and the chin say where a face is;
            the smooth cheeks and forehead would fit the side of a head as well as its face.
        centre, half: ``(3,)`` the centre and half-sides of the face's bounding box.
    """

    points: np.ndarray
    tree: Any
    core: np.ndarray
    weights: np.ndarray
    centre: np.ndarray
    half: np.ndarray

    def in_core(self, points: np.ndarray) -> np.ndarray:
        """``(N,)`` whether points (the face's frame) lie inside the inner face's ellipse, seen from the
        front."""
        fx, below, above = _CORE
        dx, dy = (points[:, :2] - self.centre[:2]).T
        return (dx / (fx * self.half[0])) ** 2 + (dy / (np.where(dy < 0, below, above) * self.half[1])) ** 2 <= 1


def _face(vertices: np.ndarray, faces: np.ndarray) -> _Face:
    from scipy.spatial import cKDTree

    points, normals = _surface_samples(vertices, faces, _FACE_POINTS, seed=1)
    lo, hi = points.min(axis=0), points.max(axis=0)
    face = _Face(points, cKDTree(points), points[:0], np.zeros(0), (lo + hi) / 2, (hi - lo) / 2)
    core = points[face.in_core(points) & (normals[:, 2] > 0.2)]
    x, y, z = (core - face.centre).T
    basis = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    relief = np.abs(z - basis @ np.linalg.lstsq(basis, z, rcond=None)[0])
    return dataclasses.replace(face, core=core, weights=relief / relief.mean() + _FLAT_WEIGHT)


def _principal_frame(points: np.ndarray) -> np.ndarray:
    """``(3, 3)`` the principal axes of ``points`` as columns, by decreasing variance, right-handed."""
    _, vecs = np.linalg.eigh(np.cov((points - points.mean(axis=0)).T))
    axes = vecs[:, ::-1].copy()
    if np.linalg.det(axes) < 0:  # a right-handed frame, so that every candidate rotation is proper
        axes[:, 2] *= -1
    return axes


def _axis_rotations() -> np.ndarray:
    """``(24, 3, 3)`` the proper rotations that map coordinate axes onto coordinate axes (signed
    permutations)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[np.arange(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return np.stack(out)


@functools.lru_cache(maxsize=2)
def _rotation_grid(count: int) -> np.ndarray:
    """``(count, 3, 3)`` rotations spread evenly over all rotations (a super-Fibonacci spiral of unit
    quaternions, Alexa 2022): deterministic, and every rotation lies near one of them (see
    :data:`_GRID_ROTATIONS`)."""
    from scipy.spatial.transform import Rotation

    s = np.arange(count) + 0.5
    near, far = np.sqrt(s / count), np.sqrt(1.0 - s / count)
    a, b = 2.0 * np.pi * s / np.sqrt(2.0), 2.0 * np.pi * s / 1.533751168755204288118041
    grid = Rotation.from_quat(np.stack([near * np.sin(a), near * np.cos(a), far * np.sin(b), far * np.cos(b)], axis=1))
    out = grid.as_matrix()
    out.setflags(write=False)
    return out


def _front_anchors(points: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """``(2, N, 3)``: where a face's front is, seen from each of ``N`` forward directions, in two ways.

    First, the middle of the front: along the direction, the front-most surface (a high quantile, so
    that a stray vertex does not count); across it, the centre of the surface within
    :data:`_FRONT_DEPTH_M` of that front. For a face or a head seen from the front this is the middle
    of the face at the height of the nose tip, whatever lies behind it (ears, neck, the back of the
    head). Second, the front-most point itself (the centre of the samples beyond that quantile): the
    tip of the nose, which stays put when the direction is a little off, while the middle of the
    front slides toward the forehead or the chin."""
    proj = points @ forward.T  # (P, N)
    front = np.quantile(proj, 0.999, axis=0)
    shell = proj >= front - _FRONT_DEPTH_M
    centre = (shell.T @ points) / shell.sum(axis=0)[:, None]
    middle = centre + (front - np.einsum("nd,nd->n", centre, forward))[:, None] * forward
    tip = proj >= front
    return np.stack([middle, (tip.T @ points) / tip.sum(axis=0)[:, None]])


def _candidates(face: _Face, user: _Surface) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(N,)`` scales, ``(N, 3, 3)`` rotations, ``(N, 3)`` translations (face -> user) to start the
    search from, and ``(N,)`` which of them come from the even grid.

    The rotations map the face's principal axes onto the user's (the 24 ways), each also turned about
    the user's longest axis by :data:`_TURNS` (a head is longest from the crown to the neck, while
    its width and depth are alike, so its principal axes across may lie anywhere), plus the 24 of the
    user file's own axes and the even grid of :func:`_rotation_grid` (where the principal axes say
    nothing about the face's pose); each at the scales of :data:`_SEARCH_SCALES` (a face may be some
    way from the reference's size) and placed by the front anchors (:func:`_front_anchors`) in both
    ways."""
    from scipy.spatial.transform import Rotation

    cube = _axis_rotations()
    u_axes = _principal_frame(user.coarse)
    spins = Rotation.from_rotvec(np.radians(np.asarray(_TURNS, np.float64))[:, None] * u_axes[:, 0]).as_matrix()
    aligned = u_axes @ cube @ _principal_frame(face.points).T
    rotations = np.concatenate([(spins[:, None] @ aligned[None]).reshape(-1, 3, 3), cube])
    forward, which = np.unique(rotations[:, :, 2].round(12), axis=0, return_inverse=True)
    user_anchors = _front_anchors(user.coarse, forward)[:, which.reshape(-1)]  # (2, R, 3)
    # The grid's anchors do not depend on the face: the surface holds them for every reference.
    grid = np.r_[np.zeros(len(rotations), bool), np.ones(_GRID_ROTATIONS, bool)]
    rotations = np.concatenate([rotations, _rotation_grid(_GRID_ROTATIONS)])
    user_anchors = np.concatenate([user_anchors, user.grid_anchors], axis=1)
    face_anchors = _front_anchors(face.points, np.array([[0.0, 0.0, 1.0]]))[:, 0]  # (2, 3)
    scales = np.asarray(_SEARCH_SCALES, np.float64)
    # (S, 2, R, 3): scale x anchor x rotation
    translations = user_anchors[None] - scales[:, None, None, None] * np.einsum("rij,aj->ari", rotations, face_anchors)[None]
    count = translations.shape[1] * translations.shape[2]
    return (np.repeat(scales, count), np.tile(rotations, (len(scales) * 2, 1, 1)), translations.reshape(-1, 3),
            np.tile(grid, len(scales) * 2))


def umeyama(src: Float[np.ndarray, "n 3"], dst: Float[np.ndarray, "*frames n 3"],
            weights: Float[np.ndarray, " n"] | None = None, *, scale: bool = False
            ) -> tuple[Any, np.ndarray, np.ndarray]:
    """Weighted least-squares ``dst ~ s * R @ src + t`` (Umeyama 1991): a proper rotation, and a scale
    when ``scale`` (else 1); for each frame of a batch of ``dst`` point sets.

    Args:
        src: ``(N, 3)`` points.
        dst: ``(N, 3)`` or ``(T, N, 3)`` corresponding points.
        weights: ``(N,)`` point weights (default: equal).
        scale: fit a scale too.

    Returns:
        ``(s, R, t)``: a float, ``(3, 3)`` and ``(3,)`` for one point set; ``(T,)``, ``(T, 3, 3)`` and
        ``(T, 3)`` for a batch.
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, np.einsum("n,...nc->...c", w, dst)
    a, b = src - mu_s, dst - mu_d[..., None, :]
    u, sig, vt = np.linalg.svd(np.einsum("...ni,nj->...ij", b * w[:, None], a))
    d = np.ones(sig.shape)
    d[..., 2] = np.where(np.linalg.det(u) * np.linalg.det(vt) < 0, -1.0, 1.0)
    rot = (u * d[..., None, :]) @ vt
    s = (sig * d).sum(axis=-1) / (w @ (a**2).sum(axis=1)) if scale else np.ones(sig.shape[:-1])
    trans = mu_d - s[..., None] * np.einsum("...ij,j->...i", rot, mu_s)
    return (float(s), rot, trans) if dst.ndim == 2 else (s, rot, trans)


def _compose(outer: Pose, inner: Pose) -> Pose:
    """``outer`` after ``inner``."""
    (s1, r1, t1), (s2, r2, t2) = outer, inner
    return s1 * s2, r1 @ r2, s1 * r1 @ t2 + t1


@dataclasses.dataclass(frozen=True)
class _Surface:
    """The user's surface as the fit sees it (metres).

    Attributes:
        points: ``(P, 3)`` area-weighted samples.
        tree: their KD-tree.
        normals: ``(P, 3)`` normals from each sample's neighbours (the principal axis of least
            variance; their sign is arbitrary), which a scanner's noise does not scramble as it does a
            triangle's normal.
        coarse: every :data:`_COARSE_STRIDE`-th sample (the principal axes, the front, the overlap).
        field, origin, spacing: the distance to the nearest sample on a voxel grid (capped at
            :data:`_FIELD_CAP_M`), read by :meth:`distance` to score thousands of candidate poses at
            once; accurate to about a voxel.
        grid_anchors: ``(2, G, 3)`` the front anchors (:func:`_front_anchors`) seen from the forward
            direction of each rotation of :func:`_rotation_grid`, which every reference shares.
    """

    points: np.ndarray
    tree: Any
    normals: np.ndarray
    coarse: np.ndarray
    field: np.ndarray
    origin: np.ndarray
    spacing: float
    grid_anchors: np.ndarray

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (metres, at most :data:`_FIELD_CAP_M`) of each point to the surface, from the field."""
        index = np.floor((points - self.origin) / self.spacing).astype(np.int64)
        inside = np.all((index >= 0) & (index < self.field.shape), axis=-1)
        out = np.full(points.shape[:-1], _FIELD_CAP_M)
        i = index[inside]
        out[inside] = self.field[i[:, 0], i[:, 1], i[:, 2]]
        return out


def _surface(vertices: np.ndarray, faces: np.ndarray) -> _Surface:
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree

    points, _ = _surface_samples(vertices, faces, _USER_POINTS, seed=0)
    tree = cKDTree(points)
    near = points[tree.query(points, k=_NORMAL_NEIGHBOURS)[1]]
    near = near - near.mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", near, near))
    origin = points.min(axis=0) - _FIELD_CAP_M
    spacing = max(_FIELD_VOXEL_M, float(np.max(points.max(axis=0) + _FIELD_CAP_M - origin)) / _FIELD_MAX_VOXELS)
    index = np.floor((points - origin) / spacing).astype(np.int64)
    empty = np.ones(index.max(axis=0) + 1 + int(np.ceil(_FIELD_CAP_M / spacing)), bool)
    empty[index[:, 0], index[:, 1], index[:, 2]] = False
    field = np.minimum(distance_transform_edt(empty) * spacing, _FIELD_CAP_M)
    coarse = points[::_COARSE_STRIDE]
    grid_anchors = _front_anchors(coarse, _rotation_grid(_GRID_ROTATIONS)[:, :, 2])
    return _Surface(points, tree, vecs[:, :, 0], coarse, field, origin, spacing, grid_anchors)


def _icp(points: np.ndarray, weights: np.ndarray, user: _Surface, pose: Pose, iterations: int, scale: bool = False) -> Pose:
    """Trimmed, weighted point-to-plane ICP of face points onto the user's surface: rigid, or a
    similarity with ``scale``. Pairs farther apart than :data:`_TRIM` times the median distance (and
    than :data:`_TRIM_FLOOR_M`) are left out of each step, so that what one mesh has and the other
    lacks (a neck, a cropped forehead, another nose) does not pull. Each step solves the linearised
    problem (rotation vector, translation, and a scale change) about the kept points' centroid."""
    from scipy.spatial.transform import Rotation

    s, rot, t = pose
    for _ in range(iterations):
        moved = s * points @ rot.T + t
        dist, idx = user.tree.query(moved)
        keep = dist <= max(_TRIM * float(np.median(dist)), _TRIM_FLOOR_M * s)
        w = weights[keep]
        centre = w @ moved[keep] / w.sum()
        p, n = moved[keep] - centre, user.normals[idx[keep]]
        columns = [np.cross(p, n), n] + ([np.einsum("nd,nd->n", p, n)[:, None]] if scale else [])
        a = np.concatenate(columns, axis=1)
        b = -np.einsum("nd,nd->n", moved[keep] - user.points[idx[keep]], n)
        lhs = (a * w[:, None]).T @ a
        x = np.linalg.solve(lhs + 1e-9 * np.trace(lhs) * np.eye(len(lhs)), (a * w[:, None]).T @ b)
        # A linearised step is trusted only so far: at most _MAX_TURN radians and 10% of scale.
        omega, shift = x[:3] * min(1.0, _MAX_TURN / (float(np.linalg.norm(x[:3])) + 1e-12)), x[3:6]
        grow = float(np.exp(np.clip(x[6], -0.1, 0.1))) if scale else 1.0
        spin = Rotation.from_rotvec(omega).as_matrix()
        # The scale stays within what a face at real size may need (a fit that would shrink the face
        # onto a patch of something else stops at the bound, where its misfit shows).
        grow = float(np.clip(grow * s, 1 / _SCALE_RANGE[1], 1 / _SCALE_RANGE[0])) / s
        s, rot, t = grow * s, spin @ rot, grow * spin @ (t - centre) + centre + shift
        if np.abs(omega).max() + np.abs(shift).max() / s + abs(grow - 1) < 1e-7:
            break
    return s, rot, t


def _distances(points: np.ndarray, user: _Surface, pose: Pose, cap: float = np.inf) -> np.ndarray:
    """Distance of each posed face point to the user's surface, in the face's metres (inf beyond
    ``cap``, which saves the search when only capped distances matter)."""
    s, rot, t = pose
    return user.tree.query(s * points @ rot.T + t, distance_upper_bound=cap * s)[0] / s


def _fit_score(distances: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The weighted mean of the distances (last axis), each capped at :data:`_SCORE_CAP_M`: a part of
    the face the user's mesh lacks costs the cap, not more."""
    return np.asarray(np.minimum(distances, _SCORE_CAP_M) @ weights / weights.sum())


def _overlap(face: _Face, user: _Surface, pose: Pose) -> float:
    """The other direction of :func:`_fit_score`: the mean distance (capped, the face's metres) to the
    face of the user's surface that lies over its inner face (inside its ellipse seen from the front,
    not behind it). A pose that lays the face on something that is not a face, e.g. upside down on
    the chin and the underside of the jaw, leaves user surface there that the face does not have."""
    s, rot, t = pose
    local = (user.coarse - t) @ rot / s
    over = local[face.in_core(local) & (local[:, 2] > face.centre[2] - face.half[2] - _SCORE_CAP_M)]
    if len(over) == 0:
        return _SCORE_CAP_M
    return float(np.minimum(face.tree.query(over, distance_upper_bound=_SCORE_CAP_M)[0], _SCORE_CAP_M).mean())


def _pose_score(face: _Face, user: _Surface, pose: Pose, core: slice = slice(None)) -> float:
    """How well a pose lays the face on the user's face, both ways: :func:`_fit_score` of its inner
    face onto the user's surface plus :func:`_overlap` back (metres; 0 is a perfect fit)."""
    fit = _fit_score(_distances(face.core[core], user, pose, _SCORE_CAP_M), face.weights[core])
    return float(fit) + _overlap(face, user, pose)


def _distinct(scales: np.ndarray, rotations: np.ndarray, translations: np.ndarray, order: np.ndarray,
              count: int) -> list[int]:
    """The first ``count`` of ``order`` that differ pairwise by more than 20 degrees, 1 cm or 10% of
    scale."""
    chosen: list[int] = []
    for i in order:
        if chosen:
            # The angle between rotations A and B: cos = (trace(A^T B) - 1) / 2.
            cos = (np.einsum("ij,kij->k", rotations[i], rotations[chosen]) - 1) / 2
            near = ((cos >= np.cos(np.radians(20.0))) & (np.linalg.norm(translations[chosen] - translations[i], axis=1) <= 0.01)
                    & (np.abs(np.log(scales[chosen] / scales[i])) <= 0.1))
            if near.any():
                continue
        chosen.append(int(i))
        if len(chosen) == count:
            break
    return chosen


def _fit(face: _Face, user: _Surface) -> Pose:
    """The landmark-free pose of a face on the user's surface (face -> user).

    The candidates of :func:`_candidates` are ranked by :func:`_fit_score` where they start; the
    best :data:`_TRIED` distinct ones of the principal and file axes and the best :data:`_GRID_TRIED`
    of the even grid take a few steps of rigid ICP (a start a little off may look worse than a wrong
    one until it has moved), the best :data:`_REFINED` of those by :func:`_pose_score` run to
    convergence, and the best of them is refined with the scale free."""
    scales, rotations, translations, grid = _candidates(face, user)
    probe = slice(None, None, max(1, len(face.core) // _PROBE_POINTS))
    points, weights = face.core[probe], face.weights[probe]
    moved = scales[:, None, None] * np.einsum("rij,pj->rpi", rotations, points) + translations[:, None]
    score = _fit_score(user.distance(moved) / scales[:, None], weights)
    order = np.argsort(score)
    starts = (_distinct(scales, rotations, translations, order[~grid[order]], _TRIED)
              + _distinct(scales, rotations, translations, order[grid[order]], _GRID_TRIED))
    tried = [_icp(points, weights, user, (scales[i], rotations[i], translations[i]), _FIRST_STEPS) for i in starts]
    tried.sort(key=lambda pose: _pose_score(face, user, pose, probe))
    refined = [_icp(points, weights, user, pose, 30) for pose in tried[:_REFINED]]
    best = min(refined, key=lambda pose: _pose_score(face, user, pose, probe))
    return _icp(face.core, face.weights, user, best, 50, scale=True)


def canonicalize(
    vertices: Float[np.ndarray, "verts 3"],
    faces: Int[np.ndarray, "faces 3"],
    template_vertices: Float[np.ndarray, "tverts 3"],
    template_faces: Int[np.ndarray, "tfaces 3"],
    *,
    units: str | None = None,
    landmarks: Float[np.ndarray, "points 3"] | None = None,
    template_landmarks: Float[np.ndarray, "68 3"] | None = None,
) -> Canonicalization:
    """Fit the similarity transform that puts a user's face mesh onto the template face.

    Args:
        vertices: ``(V, 3)`` the user's mesh, in its own units and pose.
        faces: ``(F, 3)`` its triangles.
        template_vertices: ``(Vt, 3)`` the template face in metres, in the model's frame (+y up, +z
            out of the face).
        template_faces: ``(Ft, 3)`` its triangles.
        units: the user's unit (``m``, ``dm``, ``cm``, ``mm``, ``um``); None: :func:`detect_units`.
        landmarks: optional ``(68, 3)`` positions of the 68 standard landmarks on the user's mesh
            (its units); with them, the similarity that fits them to the template's is the answer.
        template_landmarks: ``(68, 3)`` the template's landmarks (required with ``landmarks``).
            Without user landmarks they carry MediaPipe's canonical face over to the template, so that
            real faces are aligned by a real face (see the module docstring); without them the
            template itself is the only reference.

    Returns:
        A :class:`Canonicalization` (landmark-free: with the separate inner parts it left out, see
        :func:`_inner_parts`).

    Raises:
        ValueError: an unknown unit, a size that is not a face's, landmarks of the wrong shape or
            with NaN, or an alignment whose scale or residual shows that the mesh is not a face.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if units is None:
        units = detect_units(v)
    if units not in UNITS:
        raise ValueError(f"unknown units {units!r}; expected one of {', '.join(UNITS)}")
    unit = UNITS[units]
    size = _extent(v) * unit
    lo, hi = FACE_EXTENT_M
    if not (lo / 2 <= size <= hi * 2):
        raise ValueError(f"in {units} the mesh's largest side is {size * 100:.3g} cm, not the size of a face or a head "
                         f"({lo * 100:.0f}-{hi * 100:.0f} cm); check the units")
    tl = None
    if template_landmarks is not None:
        tl = np.asarray(template_landmarks, np.float64)
        if tl.shape != (68, 3) or not np.all(np.isfinite(tl)):
            raise ValueError(f"template_landmarks must be (68, 3) finite positions, got shape {tl.shape}")
    if landmarks is not None:
        if tl is None:
            raise ValueError("landmarks need template_landmarks (the template's own 68 landmarks)")
        lm = np.asarray(landmarks, np.float64)
        if lm.shape != tl.shape:
            raise ValueError(f"landmarks must have shape {tl.shape}, got {lm.shape}")
        if not np.all(np.isfinite(lm)):
            raise ValueError("landmarks contain NaN or inf")
        # The landmarks say where the features are; a surface fit of another face would pull them off.
        s, rot, trans = umeyama(lm * unit, tl, scale=True)  # user (m) -> template (m)
        residual = float(np.linalg.norm(s * lm * unit @ rot.T + trans - tl, axis=1).mean())
        canon = Canonicalization(units, unit * s, rot, trans, residual, "landmarks", "landmarks")
        return _checked(canon, None, canon.fitted_scale)
    kept, ignored = _inner_parts(v * unit, f)
    user = _surface(v * unit, f[kept])
    references = [("template", _face(np.asarray(template_vertices, np.float64), np.asarray(template_faces, np.int64)),
                   (1.0, np.eye(3), np.zeros(3)))]
    if tl is not None:
        mp_vertices, mp_faces = reference_face()
        ibug, index = zip(*MEDIAPIPE_IBUG.items())
        # template -> MediaPipe's face, by their landmarks
        to_reference = umeyama(tl[list(ibug)], mp_vertices[list(index)], scale=True)
        references.append(("mediapipe", _face(mp_vertices, mp_faces), to_reference))
    best = None
    for name, face, to_reference in references:
        pose = _fit(face, user)  # reference -> user (m)
        distances = _distances(face.core, user, pose)
        fit = float(_fit_score(distances, face.weights))
        if best is None or fit < best[0]:
            best = (fit, name, _compose(pose, to_reference), float(distances.mean()) / to_reference[0], 1 / pose[0])
    fit, name, (s, rot, trans), residual, reference_scale = best  # template (m) -> user (m)
    canon = Canonicalization(units=units, scale=unit / s, rotation=rot.T, translation=-(rot.T @ trans) / s,
                             residual=residual, method="icp", reference=name, ignored=ignored)
    return _checked(canon, fit, reference_scale)


def face_reference(face: Any) -> tuple[Float[np.ndarray, "verts 3"], Int[np.ndarray, "faces 3"],
                                         Float[np.ndarray, "68 3"] | None]:
    """``(vertices, faces, landmarks)`` of a face model's neutral (metres, float64), as
    :func:`canonicalize` takes a template: the landmarks at the zero parameter vector, or None where the
    model has none (a FLAME model loaded without its landmark embedding has NaN landmarks).

    Args:
        face: a :class:`~jaxtalk.face.model.LinearFaceModel` (the built-in face or FLAME).
    """
    from jaxtalk.types import PARAM_DIM

    landmarks = np.asarray(face.landmarks(np.zeros(PARAM_DIM, np.float32)), np.float64)
    return (np.asarray(face.template, np.float64), np.asarray(face.faces, np.int64),
            landmarks if np.all(np.isfinite(landmarks)) else None)


def align_to_face(
    vertices: Float[np.ndarray, "verts 3"],
    faces: Int[np.ndarray, "faces 3"],
    face: Any,
    *,
    units: str | None = None,
    landmarks: Float[np.ndarray, "68 3"] | None = None,
) -> Canonicalization:
    """Align a user's mesh to a face model's neutral with the face's own landmarks (:func:`face_reference`):
    what FreeTalk does to a mesh it animates and the retargeter to a rig, so that both accept the same
    meshes (with the landmarks, real faces are aligned through MediaPipe's canonical face; see the
    module docstring).

    Args:
        vertices: ``(V, 3)`` the user's mesh, in its own units and pose.
        faces: ``(F, 3)`` its triangles.
        face: the :class:`~jaxtalk.face.model.LinearFaceModel` whose frame the mesh is put in.
        units: the mesh's unit (a key of :data:`UNITS`); None: :func:`detect_units`.
        landmarks: optional ``(68, 3)`` positions of the 68 standard landmarks on the mesh (its units).

    Returns:
        A :class:`Canonicalization` into the face's frame.

    Raises:
        ValueError: as :func:`canonicalize`, or user landmarks with a face model that has none.
    """
    tv, tf, tl = face_reference(face)
    if landmarks is not None and tl is None:
        raise ValueError("the face model has no landmarks (a FLAME model loaded without its landmark embedding), so "
                         "the mesh's landmarks cannot be matched to it; load it with one, or leave out the landmarks")
    return canonicalize(vertices, faces, tv, tf, units=units, landmarks=landmarks, template_landmarks=tl)


def _checked(canon: Canonicalization, fit: float | None, scale: float) -> Canonicalization:
    """``canon``, or the error that says why it cannot be a face's alignment (``fit``: the reference's
    :func:`_fit_score`, None with landmarks; ``scale``: the similarity scale that fits the reference,
    or the landmarks, to the mesh, which ICP keeps within :data:`_SCALE_RANGE`: at its bounds the fit
    wanted more). The scale onto the template must lie in the range too."""
    if fit is not None and fit > _MAX_FIT_M:
        raise ValueError(f"the mesh does not look like a face: after the best alignment a face's nose, eyes, mouth "
                         f"and chin lie {fit * 1000:.1f} mm from its surface on average (a face fits within "
                         f"{_MAX_FIT_M * 1000:.0f} mm); pass its 68 landmarks to guide the alignment")
    lo_s, hi_s = _SCALE_RANGE
    if not (lo_s * 1.001 < scale < hi_s * 0.999 and lo_s <= canon.fitted_scale <= hi_s):
        raise ValueError(f"aligning the template face to the mesh needs a scale of {canon.fitted_scale:.2f} "
                         f"(at or beyond {lo_s}-{hi_s}): in {canon.units} this is not a human face at real size; "
                         "check the units")
    return canon
