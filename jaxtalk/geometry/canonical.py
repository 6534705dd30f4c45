"""Meshes a user brings, read and put in the frame a face model was trained in.

STM (FreeTalk's Sparse-To-Mesh) is intrinsic except for its xyz/normal input: it was trained on faces
in metres, centred, looking along +z with +y up (the built-in face's frame). A scan or an artist's
head comes in millimetres or centimetres, anywhere in space, facing anywhere. This module:

* :func:`load_mesh`: OBJ / PLY / GLB / GLTF / OFF / STL through trimesh (a scene is flattened with its
  node transforms), vertices in file order, with clear errors for a missing file, a point cloud or a
  file with no triangles.
* :func:`detect_units`: the unit from the largest bounding-box side, which for a face or a head is
  8-45 cm: one of ``m``, ``cm``, ``mm`` (and ``um``, the Basel Face Model's micrometres) fits, or the
  size makes no sense for a face and the error says so.
* :func:`canonicalize`: a similarity transform (scale, rotation, translation) from the user's frame to
  the template's. Landmark-free by default: both meshes' principal axes (area-weighted) give the 24
  axis-aligned candidate rotations, each refined by ICP of the template onto the user's surface
  (``trimesh.registration.icp``), and the candidate whose template lies closest to the surface wins.
  With 68 user landmarks, Procrustes on the landmarks replaces the search (then ICP refines). A fit
  whose scale or residual is implausible for a face is an error, never a silent far-off answer.

:class:`Canonicalization` maps positions to the template frame and displacements back into the
user's units and frame (a displacement rotates and scales but does not translate).
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from pathlib import Path

import numpy as np

from jaxtalk.types import Float, Int

__all__ = [
    "UNITS",
    "MESH_SUFFIXES",
    "FACE_EXTENT_M",
    "Canonicalization",
    "load_mesh",
    "detect_units",
    "canonicalize",
]

# Metres per unit.
UNITS: dict[str, float] = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6}
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
# The largest bounding-box side of a face mask (about 15-20 cm) or a whole head with neck (up to
# about 35 cm), with margin. The ranges of the units do not overlap, so detection is unambiguous.
FACE_EXTENT_M = (0.08, 0.45)
# A fitted similarity scale outside this range means the mesh is not a human face at real size.
_SCALE_RANGE = (0.6, 1.6)
# After alignment, the template's points must lie on average within this fraction of the template's
# largest side (6 mm on the built-in face) from the user's surface. Measured: other identities of the
# built-in face 1.1-1.2 mm, a real head scan (menpo3d's james.obj, with neck and ears) 4.0 mm; a
# sphere, a box or a cylinder of a head's size 7.0-8.4 mm.
_MAX_RESIDUAL = 0.03
# Points used for the alignment (area-weighted samples of each surface): enough for a rigid fit,
# few enough that the 24-candidate search stays well under a second.
_SEARCH_POINTS = 600
_FINAL_POINTS = 3000
_USER_POINTS = 20000


@dataclasses.dataclass(frozen=True)
class Canonicalization:
    """``x_template = scale * rotation @ x_user + translation`` (``x_user`` in the user's units).

    Attributes:
        units: the user's unit (a key of :data:`UNITS`).
        scale: template metres per user unit (the unit factor times the fitted similarity scale).
        rotation: ``(3, 3)`` proper rotation.
        translation: ``(3,)`` metres.
        residual: mean distance (metres, template frame) of the template's points to the aligned
            user surface.
        method: ``"icp"`` (landmark-free) or ``"landmarks"``.
    """

    units: str
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residual: float
    method: str

    @property
    def fitted_scale(self) -> float:
        """The similarity scale beyond the unit conversion (1 = the template's size)."""
        return self.scale / UNITS[self.units]

    def to_template(self, points: Float[np.ndarray, "*n 3"]) -> Float[np.ndarray, "*n 3"]:
        """User positions -> template frame (metres)."""
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation

    def to_user(self, points: Float[np.ndarray, "*n 3"]) -> Float[np.ndarray, "*n 3"]:
        """Template positions (metres) -> the user's units and frame."""
        return (np.asarray(points, np.float64) - self.translation) @ self.rotation / self.scale

    def displacements_to_user(self, displacements: Float[np.ndarray, "*n 3"]) -> Float[np.ndarray, "*n 3"]:
        """Template-frame displacements (metres) -> the user's units and frame (no translation)."""
        return np.asarray(displacements, np.float64) @ self.rotation / self.scale


def load_mesh(path: str | os.PathLike[str]) -> tuple[Float[np.ndarray, "verts 3"], Int[np.ndarray, "faces 3"]]:
    """Read a triangle mesh (OBJ, PLY, GLB/GLTF, OFF, STL) with trimesh, vertices in file order.

    Quads and polygons are triangulated by trimesh; a GLB/GLTF scene's meshes are concatenated with
    their node transforms applied. Vertices are not merged or reordered (``process=False``), so an
    output vertex sequence lines up with the file the user has.

    Args:
        path: the mesh file.

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int64)`` as stored (the file's units).

    Raises:
        FileNotFoundError: no such file.
        ValueError: an unsupported suffix, an unreadable file, a point cloud or a mesh without
            triangles.
    """
    import trimesh  # local: importing trimesh is not free

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"mesh file not found: {str(p)!r}")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{str(p)!r}: expected a mesh file ({', '.join(MESH_SUFFIXES)}), got {p.suffix or 'no suffix'!r}")
    try:
        loaded = trimesh.load(p, process=False, maintain_order=True)
    except Exception as err:  # trimesh raises many types for a broken file
        raise ValueError(f"{str(p)!r} could not be read as a mesh: {err}") from None
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        if not meshes:
            kinds = sorted({type(g).__name__ for g in loaded.geometry.values()}) or ["nothing"]
            raise ValueError(f"{str(p)!r} holds no triangle mesh (found: {', '.join(kinds)})")
        loaded = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
    if isinstance(loaded, trimesh.PointCloud):
        raise ValueError(f"{str(p)!r} is a point cloud ({len(loaded.vertices)} points, no faces); "
                         "a mesh with triangles is needed")
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(f"{str(p)!r} is a {type(loaded).__name__}, not a triangle mesh")
    vertices = np.asarray(loaded.vertices, np.float64)
    faces = np.asarray(loaded.faces, np.int64).reshape(-1, 3)
    if faces.shape[0] == 0:
        raise ValueError(f"{str(p)!r} has {vertices.shape[0]} vertices but no faces; a mesh with triangles is needed")
    return vertices, faces


def _extent(vertices: np.ndarray) -> float:
    return float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))


def detect_units(vertices: Float[np.ndarray, "verts 3"]) -> str:
    """The unit a face mesh is stored in, from its largest bounding-box side.

    Args:
        vertices: ``(V, 3)`` positions.

    Returns:
        ``"m"``, ``"cm"``, ``"mm"`` or ``"um"``: the unit in which the largest side lies in
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
        "(--units m, cm, mm or um) if it really is a face"
    )


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int) -> np.ndarray:
    """``count`` points spread over the surface by area (deterministic): face centroids drawn with
    probability proportional to area, which does not depend on how densely a region is meshed."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = area.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("the mesh has zero surface area (every face is degenerate)")
    rng = np.random.default_rng(seed)
    pick = rng.choice(faces.shape[0], size=count, p=area / total)
    w = rng.dirichlet(np.ones(3), size=count)
    return np.einsum("nk,nkd->nd", w, tri[pick])


def _principal_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centre = points.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((points - centre).T))
    axes = vecs[:, ::-1].copy()  # columns by decreasing variance
    if np.linalg.det(axes) < 0:  # a right-handed frame, so that every candidate rotation is proper
        axes[:, 2] *= -1
    return centre, axes


def _candidate_rotations() -> list[np.ndarray]:
    """The 24 proper rotations that map coordinate axes onto coordinate axes (signed permutations)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[np.arange(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return out


def _similarity(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = scale * rotation
    m[:3, 3] = translation
    return m


def _split(matrix: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    linear = matrix[:3, :3]
    scale = float(np.cbrt(np.linalg.det(linear)))
    return scale, linear / scale, matrix[:3, 3].copy()


def _icp(template_pts: np.ndarray, user_pts: np.ndarray, user_tree, initial: np.ndarray,
         iterations: int) -> tuple[np.ndarray, float]:
    """ICP of the template points onto the user points (the template -> user similarity) and the mean
    distance of the moved template points to their nearest user points (in the user's frame);
    ``user_tree`` is the KD-tree of ``user_pts``, built once for every candidate."""
    from trimesh.registration import icp

    matrix, moved, _ = icp(template_pts, user_pts, initial=initial, max_iterations=iterations, threshold=1e-10,
                           reflection=False, scale=True)
    dist, _ = user_tree.query(moved)
    return matrix, float(dist.mean())


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
        template_vertices: ``(Vt, 3)`` the template face in metres, in the model's frame.
        template_faces: ``(Ft, 3)`` its triangles.
        units: the user's unit (``m``, ``cm``, ``mm``, ``um``); None: :func:`detect_units`.
        landmarks: optional ``(68, 3)`` positions of the 68 standard landmarks on the user's mesh
            (its units); with them, Procrustes on the landmarks gives the starting pose.
        template_landmarks: ``(68, 3)`` the template's landmarks (required with ``landmarks``).

    Returns:
        A :class:`Canonicalization`.

    Raises:
        ValueError: an unknown unit, a size that is not a face's, landmarks of the wrong shape or
            with NaN, or an alignment whose scale or residual shows that the mesh is not a face.
    """
    from scipy.spatial import cKDTree
    from trimesh.registration import procrustes

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tv = np.asarray(template_vertices, np.float64)
    tf = np.asarray(template_faces, np.int64)
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
    metres = v * unit
    user_pts = _surface_samples(metres, f, min(_USER_POINTS, max(4 * v.shape[0], 2000)), seed=0)
    user_tree = cKDTree(user_pts)
    tpl_search = _surface_samples(tv, tf, _SEARCH_POINTS, seed=1)
    tpl_final = _surface_samples(tv, tf, _FINAL_POINTS, seed=2)
    if landmarks is not None:
        if template_landmarks is None:
            raise ValueError("landmarks need template_landmarks (the template's own 68 landmarks)")
        lm = np.asarray(landmarks, np.float64)
        tl = np.asarray(template_landmarks, np.float64)
        if lm.shape != tl.shape or lm.ndim != 2 or lm.shape[1] != 3:
            raise ValueError(f"landmarks must have shape {tl.shape}, got {lm.shape}")
        if not np.all(np.isfinite(lm)):
            raise ValueError("landmarks contain NaN or inf")
        start, _, _ = procrustes(tl, lm * unit, reflection=False, scale=True)
        matrix, residual = _icp(tpl_final, user_pts, user_tree, start, 30)
        method = "landmarks"
    else:
        t_centre, t_axes = _principal_frame(tpl_search)
        u_centre, u_axes = _principal_frame(user_pts)
        best = None
        for r in _candidate_rotations():
            rotation = u_axes @ r @ t_axes.T  # template axes -> user axes
            start = _similarity(1.0, rotation, u_centre - rotation @ t_centre)
            matrix, residual = _icp(tpl_search, user_pts, user_tree, start, 15)
            if best is None or residual < best[1]:
                best = (matrix, residual)
        matrix, residual = _icp(tpl_final, user_pts, user_tree, best[0], 40)
        method = "icp"
    s, rot, trans = _split(matrix)  # template (m) -> user (m)
    # Invert: user metres -> template metres; fold the unit factor into the scale.
    inv_scale = 1.0 / s
    canon = Canonicalization(units=units, scale=unit * inv_scale, rotation=rot.T,
                             translation=-(rot.T @ trans) * inv_scale, residual=residual * inv_scale,
                             method=method)
    lo_s, hi_s = _SCALE_RANGE
    if not (lo_s <= canon.fitted_scale <= hi_s):
        raise ValueError(f"aligning the template face to the mesh needs a scale of {canon.fitted_scale:.2f} "
                         f"(beyond {lo_s}-{hi_s}): in {units} this is not a human face at real size; check the units")
    limit = _MAX_RESIDUAL * _extent(tv)
    if canon.residual > limit:
        raise ValueError(f"the mesh does not look like a face: after the best alignment the template face lies "
                         f"{canon.residual * 1000:.1f} mm from its surface on average (a face fits within "
                         f"{limit * 1000:.0f} mm)" + ("" if landmarks is not None else "; pass its 68 landmarks to "
                                                      "guide the alignment"))
    return canon
