"""A vectorised NumPy z-buffer triangle rasteriser (no display, no OpenGL).

All triangles are rasterised at once, with no Python loop over triangles or pixels:

1. each triangle's bounding box is expanded into pixel rows (a ragged ``np.repeat``), and each
   row's exact span of covered pixel centres is solved from the triangle's affine edge functions
   (float64, one entry per row);
2. the spans are expanded into covered pixels (a second ragged ``np.repeat``); no pixel outside a
   triangle is ever visited, so per-pixel work is a few float32 multiply-adds;
3. the pixels compete in a z-buffer resolved with ``np.maximum.at`` on a screen-linear depth key
   (``1/depth`` for perspective, ``-depth`` for orthographic);
4. the winners' barycentrics are computed and made perspective-correct (weights
   ``lambda_k / depth_k``).

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
    col0, row0 = col0[tri], row0[tri]
    nrows = (row1[tri] - row0 + 1).astype(np.int64)

    # Barycentrics (l1, l2) are affine in the pixel centre: l = base + a * dcol + b * drow, with the
    # base at the box's first pixel centre (col0 + 0.5, row0 + 0.5).
    inv_a = 1.0 / area2[tri]
    px, py = col0 + 0.5 - x0[tri], row0 + 0.5 - y0[tri]
    e1x, e1y, e2x, e2y = ex1[tri], ey1[tri], ex2[tri], ey2[tri]
    base1, a1, b1 = (px * e2y - py * e2x) * inv_a, e2y * inv_a, -e2x * inv_a
    base2, a2, b2 = (e1x * py - e1y * px) * inv_a, -e1y * inv_a, e1x * inv_a
    if perspective:
        zkey = 1.0 / dz[tri]  # 1/depth is affine in screen space; a larger key is nearer
    else:
        zkey = -dz[tri]

    # Level 1: one entry per (triangle, pixel row) of its box; each row's exact covered column span.
    row_tri = np.repeat(np.arange(tri.size), nrows)
    drow = np.arange(row_tri.size) - np.repeat(np.cumsum(nrows) - nrows, nrows)
    c1 = base1[row_tri] + b1[row_tri] * drow  # l1 at the row's first box column
    c2 = base2[row_tri] + b2[row_tri] * drow
    s1, s2 = a1[row_tri], a2[row_tri]
    # l_k(dcol) = c_k + s_k * dcol >= -eps for k = 0, 1, 2 bounds dcol from below (s > 0) or above.
    lo = np.zeros(row_tri.size)
    hi = (col1[tri] - col0)[row_tri]
    for c, slope in ((c1, s1), (c2, s2), (1.0 - c1 - c2, -s1 - s2)):
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = (-_EDGE_EPS - c) / slope
        lo = np.where(slope > 0, np.maximum(lo, bound), lo)
        hi = np.where(slope < 0, np.minimum(hi, bound), hi)
        hi = np.where((slope == 0) & (c < -_EDGE_EPS), -1.0, hi)
    lo, hi = np.ceil(lo), np.floor(hi)
    counts = np.maximum(hi - lo + 1, 0).astype(np.int64)
    total = int(counts.sum())
    if total == 0:
        return empty

    # Level 2: one entry per covered pixel (int32 unless the image is huge).
    itype = np.int32 if total < 2**31 and height * width < 2**31 else np.int64
    row_of = np.repeat(np.arange(row_tri.size, dtype=itype), counts)
    dcol = np.arange(total, dtype=itype) - np.repeat((np.cumsum(counts) - counts).astype(itype), counts)
    # Per-row affine coefficients in float32, taken at the span's first pixel (small offsets).
    zk = zkey[row_tri]
    first1, first2 = c1 + s1 * lo, c2 + s2 * lo
    kslope = s1 * (zk[:, 1] - zk[:, 0]) + s2 * (zk[:, 2] - zk[:, 0])
    kfirst = zk[:, 0] + first1 * (zk[:, 1] - zk[:, 0]) + first2 * (zk[:, 2] - zk[:, 0])
    table = np.stack([first1, s1, first2, s2, kfirst, kslope], axis=1).astype(np.float32)[row_of]
    dcol_f = dcol.astype(np.float32)
    key = table[:, 4] + table[:, 5] * dcol_f
    start = ((row0[row_tri] + drow) * width + col0[row_tri] + lo).astype(itype)
    pixel = start[row_of] + dcol

    zbuf = np.full(height * width, -np.inf, np.float32)
    np.maximum.at(zbuf, pixel, key)
    win = np.flatnonzero(key >= zbuf[pixel])
    # Exact depth ties (shared edges/vertices): fancy assignment keeps the last candidate.
    slot = np.full(height * width, -1, itype)
    slot[pixel[win]] = win.astype(itype)
    covered = np.flatnonzero(slot >= 0)
    chosen = slot[covered]
    t = table[chosen]
    dc = dcol_f[chosen]
    l1 = t[:, 0] + t[:, 1] * dc
    l2 = t[:, 2] + t[:, 3] * dc
    bary = np.stack([np.float32(1.0) - l1 - l2, l1, l2], axis=1)
    tri_of = row_tri[row_of[chosen]]
    if perspective:
        # Perspective-correct weights: screen barycentrics divided by depth, renormalised.
        bary *= zkey.astype(np.float32)[tri_of]
        bary /= key[chosen][:, None]
    return Fragments(
        pixel=covered,
        face=tri[tri_of].astype(np.int32),
        bary=np.ascontiguousarray(bary, np.float32),
        height=height,
        width=width,
    )
