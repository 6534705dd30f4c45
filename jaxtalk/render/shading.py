"""Shading of rasterised fragments: smooth vertex normals, Lambert + Blinn-Phong (Gouraud), gamma.

Colours in ``RenderStyle`` and ``vertex_colors`` are display (gamma-encoded) colours; lighting is
computed in linear light and encoded again with ``gamma``.

Lights are fixed in the CAMERA frame (a key light from the front, above and to the viewer's left, a
weaker fill from the other side, and ambient), so a face is lit from the front whatever the camera's
orbit. Lighting uses area-weighted vertex normals and is interpolated over triangles; the
surface is two-sided (an open face mask shows its inside at the mouth and the rim): the normal of a
triangle seen from behind is flipped towards the viewer and its colour darkened.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxtalk.render.rasterize import Fragments
from jaxtalk.types import Float, Int

# Python scalars: beartype (under pytest) does not promote int to float.
Real = int | float

__all__ = ["RenderStyle", "vertex_normals", "cavity_weights", "shade"]


@dataclasses.dataclass(frozen=True)
class RenderStyle:
    """Colours and lighting of rendered frames (all colours linear RGB in ``[0, 1]``).

    Attributes:
        base_color: surface albedo where no per-vertex colours are given (a clay-like skin tone).
        background: background colour.
        key_light: direction TOWARDS the key light in camera coordinates (normalised on use).
        key_intensity: key light strength.
        fill_light: direction towards the fill light in camera coordinates.
        fill_intensity: fill light strength.
        ambient: ambient term.
        specular: Blinn-Phong specular strength of the key light.
        shininess: Blinn-Phong exponent.
        backface_dim: albedo factor for triangles seen from behind (the inside of the mask).
        cavity_color: colour of the mouth cavity drawn over strongly stretched triangles (see
            ``cavity_weights``; only when a rest mesh is given to the frame renderer).
        cavity_stretch: area ratio (posed / rest) at which a triangle starts turning into cavity;
            it is fully cavity at twice this ratio.
        gamma: display gamma applied to the linear result.
        supersample: render at this many times the resolution per axis and average down
            (anti-aliasing; cost grows with its square).
    """

    base_color: tuple[Real, Real, Real] = (0.80, 0.62, 0.52)
    background: tuple[Real, Real, Real] = (0.16, 0.17, 0.20)
    key_light: tuple[Real, Real, Real] = (-0.45, 0.55, 1.0)
    key_intensity: Real = 0.85
    fill_light: tuple[Real, Real, Real] = (0.7, -0.1, 0.6)
    fill_intensity: Real = 0.25
    ambient: Real = 0.12
    specular: Real = 0.12
    shininess: Real = 24.0
    backface_dim: Real = 0.35
    cavity_color: tuple[Real, Real, Real] = (0.22, 0.06, 0.07)
    cavity_stretch: Real = 2.5
    gamma: Real = 2.2
    supersample: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.supersample, bool) or not isinstance(self.supersample, int) or self.supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {self.supersample!r}")
        if self.cavity_stretch <= 1:
            raise ValueError(f"cavity_stretch must be > 1 (an area ratio), got {self.cavity_stretch}")
        if self.gamma <= 0:
            raise ValueError(f"gamma must be positive, got {self.gamma}")
        for name in ("base_color", "background", "cavity_color"):
            color = getattr(self, name)
            if len(color) != 3 or not all(0.0 <= c <= 1.0 for c in color):
                raise ValueError(f"{name} must be 3 values in [0, 1], got {color}")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), np.float32(1e-20))


def face_normals(vertices: Float[np.ndarray, "verts 3"], faces: Int[np.ndarray, "tris 3"]) -> Float[np.ndarray, "tris 3"]:
    """Unnormalised triangle normals (length = twice the area), counter-clockwise = outward."""
    v = vertices[faces]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


def vertex_normals(vertices: Float[np.ndarray, "verts 3"], faces: Int[np.ndarray, "tris 3"]) -> Float[np.ndarray, "verts 3"]:
    """Area-weighted unit vertex normals.

    Args:
        vertices: vertex positions, ``(V, 3)``.
        faces: counter-clockwise triangles, ``(F, 3)``.

    Returns:
        Unit normals, ``(V, 3)`` (zero for vertices in no triangle).
    """
    return _vertex_normals_from(face_normals(vertices, faces), faces, vertices.shape[0])


def _vertex_normals_from(fn: np.ndarray, faces: np.ndarray, num: int) -> np.ndarray:
    flat = faces.reshape(-1)
    # bincount is a fast scatter-add (the area weighting is the cross product's length).
    acc = np.stack([np.bincount(flat, weights=np.repeat(fn[:, c], 3), minlength=num) for c in range(3)], axis=1)
    return _unit(acc).astype(np.float32)


def cavity_weights(
    vertices: Float[np.ndarray, "verts 3"],
    rest_vertices: Float[np.ndarray, "verts 3"],
    faces: Int[np.ndarray, "tris 3"],
    stretch: Real,
) -> Float[np.ndarray, "tris"]:
    """How much each triangle shows the mouth cavity, from its stretch against a rest mesh.

    A face mesh has no mouth interior: an open mouth is the skin between the lips stretched many
    times its rest area (the built-in face's lip-seam triangles grow 10-30x at 0.35 rad of jaw).
    Those triangles are drawn as cavity, blending in from ``stretch`` to ``2 * stretch`` times the
    rest area, so the open mouth reads as dark and a closed one is unchanged.

    Args:
        vertices: posed vertices, ``(V, 3)``.
        rest_vertices: the same mesh at rest (e.g. the template), ``(V, 3)``.
        faces: triangles, ``(F, 3)``.
        stretch: area ratio where the blend starts (> 1).

    Returns:
        Blend weights in ``[0, 1]``, ``(F,)`` float32.
    """
    posed = np.linalg.norm(face_normals(np.asarray(vertices, np.float32), faces), axis=1)
    rest = np.linalg.norm(face_normals(np.asarray(rest_vertices, np.float32), faces), axis=1)
    ratio = posed / np.maximum(rest, np.float32(1e-30))
    return np.clip((ratio - stretch) / stretch, 0.0, 1.0).astype(np.float32)


def shade(
    fragments: Fragments,
    vertices_cam: Float[np.ndarray, "verts 3"],
    faces: Int[np.ndarray, "tris 3"],
    style: RenderStyle,
    *,
    vertex_colors: Float[np.ndarray, "verts 3"] | None = None,
    cavity: Float[np.ndarray, "tris"] | None = None,
    orthographic: bool = False,
) -> Float[np.ndarray, "n 3"]:
    """Colours of the visible fragments of a mesh given in camera coordinates.

    Lighting is evaluated in linear light at the vertices, gamma-encoded there, and the display
    colours are interpolated over the triangles (Gouraud, as fixed-function OpenGL does): at the
    2-8 pixel triangles of a face mesh this looks like per-pixel shading and costs O(V) lighting
    plus one interpolation per pixel. Each vertex gets a front-side and a back-side colour; a
    fragment takes the side its triangle shows to the camera.

    Args:
        fragments: the rasterised visible surface.
        vertices_cam: the mesh's vertices in camera coordinates, ``(V, 3)``.
        faces: its triangles, ``(F, 3)``.
        style: colours and lights.
        vertex_colors: optional per-vertex albedo in ``[0, 1]`` (display colours), ``(V, 3)``.
        cavity: optional per-triangle blend towards ``style.cavity_color`` (``cavity_weights``), ``(F,)``.
        orthographic: the view direction is +z everywhere (else it points to the camera at 0).

    Returns:
        Display colours in ``[0, 255]`` of ``fragments.pixel``, ``(N, 3)`` float32.
    """
    verts = np.asarray(vertices_cam, np.float32)
    fn = face_normals(verts, faces)
    normal = _vertex_normals_from(fn, faces, verts.shape[0])
    view = np.broadcast_to(np.float32([0, 0, 1]), verts.shape) if orthographic else _unit(-verts)
    gamma = np.float32(style.gamma)
    if vertex_colors is None:
        albedo = np.broadcast_to(np.asarray(style.base_color, np.float32) ** gamma, verts.shape)
    else:
        albedo = np.asarray(vertex_colors, np.float32) ** gamma
    front = _lit(normal, view, albedo, style)
    back = _lit(-normal, view, albedo * np.float32(style.backface_dim), style)
    # (2V, 3) display colours; row V + i is vertex i seen from behind.
    table = np.float32(255.0) * np.clip(np.concatenate([front, back]), 0.0, 1.0) ** (np.float32(1.0) / gamma)

    tri = faces[fragments.face]  # (N, 3)
    # Two-sided: a triangle whose geometric normal points away from the viewer is seen from behind.
    centroid_view = np.float32([0, 0, 1]) if orthographic else -verts[faces].mean(1)
    seen_from_back = ((fn * centroid_view).sum(1) < 0)[fragments.face]
    tri = tri + np.int32(verts.shape[0]) * seen_from_back[:, None].astype(np.int32)
    b = fragments.bary
    colors = b[:, 0:1] * table[tri[:, 0]] + b[:, 1:2] * table[tri[:, 1]] + b[:, 2:3] * table[tri[:, 2]]
    if cavity is not None:
        blend = np.asarray(cavity, np.float32)[fragments.face]
        hit = np.flatnonzero(blend > 0)
        if hit.size:
            dark = np.float32(255.0) * np.asarray(style.cavity_color, np.float32)
            colors[hit] += blend[hit, None] * (dark - colors[hit])
    return colors


def _lit(normal: np.ndarray, view: np.ndarray, albedo: np.ndarray, style: RenderStyle) -> np.ndarray:
    """Linear colour of surface points with unit ``normal`` seen along ``view`` (both ``(V, 3)``)."""
    key = _unit(np.asarray(style.key_light, np.float32))
    fill = _unit(np.asarray(style.fill_light, np.float32))
    diffuse = style.key_intensity * np.maximum(normal @ key, 0.0) + style.fill_intensity * np.maximum(normal @ fill, 0.0)
    half = _unit(view + key)
    spec = style.specular * np.maximum((normal * half).sum(1), 0.0) ** np.float32(style.shininess)
    return (albedo * (style.ambient + diffuse)[:, None] + spec[:, None]).astype(np.float32)
