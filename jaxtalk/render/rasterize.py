"""A vectorised NumPy z-buffer triangle rasteriser (no display, no OpenGL).

All triangles are rasterised at once, with no Python loop over triangles or pixels:

1. each triangle's pixel bounding box is expanded into candidate pixels (a ragged ``np.repeat``);
2. barycentric coordinates of each candidate come from the triangle's affine edge functions
   (precomputed per triangle in float64 relative to its box corner, so float32 suffices per pixel);
3. candidates outside the triangle are dropped; the rest compete in a z-buffer resolved with
   ``np.maximum.at`` on a screen-linear depth key (``1/depth`` for perspective, ``-depth`` for
   orthographic);
4. the winners' barycentrics are made perspective-correct (weights ``lambda_k / depth_k``).

Sampling is at pixel centres; a pixel whose centre lies on an edge shared by two triangles may be
claimed by either (the nearer wins; exact ties go to the later triangle), so there are no cracks.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxtalk.types import Float, Int

__all__ = ["Fragments", "rasterize"]

# Inside-test slack on barycentrics: keeps pixels on shared edges covered despite rounding.
_EDGE_EPS = 1e-5
# Triangles with less than this doubled screen area (pixels^2) cover no pixel centre reliably.
_MIN_AREA2 = 1e-9


@dataclasses.dataclass(frozen=True, eq=False)
class Fragments:
    """The visible surface sample at each covered pixel.

    Attributes:
        pixel: flat pixel index ``row * width + column`` of each covered pixel, ascending, ``(N,)``.
        face: index of the visible triangle at that pixel, ``(N,)`` int32.
        bary: perspective-correct barycentric coordinates in that triangle, ``(N, 3)`` float32
            (non-negative up to rounding, rows sum to 1).
        height: image height.
        width: image width.
    """

    pixel: Int[np.ndarray, "n"]
    face: Int[np.ndarray, "n"]
    bary: Float[np.ndarray, "n 3"]
    height: int
    width: int

    def face_image(self) -> Int[np.ndarray, "height width"]:
        """Visible triangle per pixel, ``(height, width)`` int32, -1 where no triangle covers it."""
        image = np.full(self.height * self.width, -1, np.int32)
        image[self.pixel] = self.face
        return image.reshape(self.height, self.width)


def rasterize(
    xy: Float[np.ndarray, "verts 2"],
    depth: Float[np.ndarray, "verts"],
    faces: Int[np.ndarray, "tris 3"],
    height: int,
    width: int,
    *,
    perspective: bool = True,
) -> Fragments:
    """Rasterise a triangle mesh already projected to pixel coordinates.

    Args:
        xy: pixel coordinates of the vertices (x right, y down; pixel centres at ``+0.5``), ``(V, 2)``.
        depth: distance of each vertex in front of the camera, ``(V,)``; triangles with a vertex at
            or behind the camera (``depth <= 0``) are skipped (no near-plane clipping).
        faces: triangles as vertex indices, ``(F, 3)``; both windings are drawn (two-sided).
        height: image height in pixels.
        width: image width in pixels.
        perspective: interpolate depth and barycentrics perspective-correctly (``False`` for an
            orthographic projection, where screen-space interpolation is exact).

    Returns:
        ``Fragments`` of the nearest triangle at every covered pixel centre.

    Raises:
        ValueError: if the shapes disagree or a face indexes a missing vertex.
    """
    xy = np.asarray(xy)
    depth = np.asarray(depth)
    faces = np.asarray(faces)
    if xy.ndim != 2 or xy.shape[1] != 2 or depth.shape != (xy.shape[0],):
        raise ValueError(f"xy must be (V, 2) and depth (V,), got {xy.shape} and {depth.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= xy.shape[0]):
        raise ValueError(
            f"faces index vertices in [{faces.min()}, {faces.max()}] but there are {xy.shape[0]} vertices"
        )
    empty = Fragments(np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros((0, 3), np.float32), height, width)

    corners = xy.astype(np.float64)[faces]  # (F, 3, 2)
    dz = depth.astype(np.float64)[faces]  # (F, 3)
    x0, y0 = corners[:, 0, 0], corners[:, 0, 1]
    ex1, ey1 = corners[:, 1, 0] - x0, corners[:, 1, 1] - y0
    ex2, ey2 = corners[:, 2, 0] - x0, corners[:, 2, 1] - y0
    area2 = ex1 * ey2 - ex2 * ey1
    # Pixel-centre bounding box: columns j with j + 0.5 in [min x, max x], clipped to the image.
    col0 = np.maximum(np.ceil(corners[..., 0].min(1) - 0.5), 0)
    col1 = np.minimum(np.floor(corners[..., 0].max(1) - 0.5), width - 1)
    row0 = np.maximum(np.ceil(corners[..., 1].min(1) - 0.5), 0)
    row1 = np.minimum(np.floor(corners[..., 1].max(1) - 0.5), height - 1)
    keep = (np.abs(area2) > _MIN_AREA2) & (dz.min(1) > 0) & (col1 >= col0) & (row1 >= row0)
    keep &= np.all(np.isfinite(corners), axis=(1, 2))
    tri = np.flatnonzero(keep)
    if tri.size == 0:
        return empty
    col0, row0 = col0[tri].astype(np.int64), row0[tri].astype(np.int64)
    ncols = col1[tri].astype(np.int64) - col0 + 1
    counts = ncols * (row1[tri].astype(np.int64) - row0 + 1)

    # Barycentrics (l1, l2) are affine in the pixel centre: l = base + a * dcol + b * drow, with the
    # base taken at the box's first pixel centre so the per-pixel float32 terms stay small.
    inv_a = 1.0 / area2[tri]
    px, py = col0 + 0.5 - x0[tri], row0 + 0.5 - y0[tri]
    e1x, e1y, e2x, e2y = ex1[tri], ey1[tri], ex2[tri], ey2[tri]
    table = np.stack(
        [
            (px * e2y - py * e2x) * inv_a,  # l1 at the box origin
            e2y * inv_a,  # d l1 / d col
            -e2x * inv_a,  # d l1 / d row
            (e1x * py - e1y * px) * inv_a,  # l2 at the box origin
            -e1y * inv_a,  # d l2 / d col
            e1x * inv_a,  # d l2 / d row
        ],
        axis=1,
    ).astype(np.float32)

    # Ragged expansion of the boxes into candidate pixels (int32 unless the image is huge).
    total = int(counts.sum())
    itype = np.int32 if total < 2**31 and height * width < 2**31 else np.int64
    owner = np.repeat(np.arange(tri.size, dtype=itype), counts)
    starts = (np.cumsum(counts) - counts).astype(itype)
    local = np.arange(total, dtype=itype) - starts[owner]
    nc = ncols.astype(itype)[owner]
    drow = local // nc
    dcol = local - drow * nc
    coef = table[owner]
    dcol_f, drow_f = dcol.astype(np.float32), drow.astype(np.float32)
    l1 = coef[:, 0] + coef[:, 1] * dcol_f + coef[:, 2] * drow_f
    l2 = coef[:, 3] + coef[:, 4] * dcol_f + coef[:, 5] * drow_f
    l0 = np.float32(1.0) - l1 - l2
    inside = np.flatnonzero((l0 >= -_EDGE_EPS) & (l1 >= -_EDGE_EPS) & (l2 >= -_EDGE_EPS))
    if inside.size == 0:
        return empty
    owner, l0, l1, l2 = owner[inside], l0[inside], l1[inside], l2[inside]
    pixel = (row0.astype(itype)[owner] + drow[inside]) * itype(width) + col0.astype(itype)[owner] + dcol[inside]

    if perspective:
        # 1/depth is affine in screen space; a larger key is nearer.
        corner_key = (1.0 / dz[tri]).astype(np.float32)[owner]  # (N, 3)
        key = l0 * corner_key[:, 0] + l1 * corner_key[:, 1] + l2 * corner_key[:, 2]
    else:
        corner_key = dz[tri].astype(np.float32)[owner]
        key = -(l0 * corner_key[:, 0] + l1 * corner_key[:, 1] + l2 * corner_key[:, 2])

    zbuf = np.full(height * width, -np.inf, np.float32)
    np.maximum.at(zbuf, pixel, key)
    win = np.flatnonzero(key >= zbuf[pixel])
    # Exact depth ties (shared edges/vertices): fancy assignment keeps the last candidate.
    slot = np.full(height * width, -1, itype)
    slot[pixel[win]] = win.astype(itype)
    covered = np.flatnonzero(slot >= 0)
    chosen = slot[covered]
    bary = np.stack([l0[chosen], l1[chosen], l2[chosen]], axis=1)
    if perspective:
        # Perspective-correct weights: screen barycentrics divided by depth, renormalised.
        bary = bary * corner_key[chosen]
        bary /= key[chosen][:, None]
    return Fragments(
        pixel=covered,
        face=tri[owner[chosen]].astype(np.int32),
        bary=np.ascontiguousarray(bary, np.float32),
        height=height,
        width=width,
    )
