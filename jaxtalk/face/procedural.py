"""The built-in procedural face: a face-mask mesh, its named expression basis, regions and landmarks.

Everything is made in code, deterministically, from a parametric domain ``(u, v)``: ``u`` runs from
the subject's right (-1) to left (+1) ear, ``v`` from the chin (-1) to the top of the forehead (+1),
and one unit of either is about 0.1 m on the face. The surface is the front of an ellipsoid-like shell
plus Gaussian bumps and dents (brow ridge, eye sockets and eyeballs, nose, cheeks, lips with a seam
groove, mentolabial sulcus, chin) in FLAME's frame and units: metres, x to the subject's left, y up,
z out of the face; about 0.2 m from chin to hairline and 0.14 m wide.

The mesh is a regular grid over ``(s, v)``, with ``u = s * halfwidth(v)`` so the outline is an oval
(narrower at the chin): one connected, manifold disk with a single boundary loop. Rows are denser
around the mouth and the eyes, one row runs exactly along the lip seam, and the grid is mirror
symmetric (odd column count, mirrored diagonals), so left/right components mirror exactly.

Expression components are displacement fields ``(du, dv, dn)`` over the domain (``du``, ``dv`` in
domain units, ``dn`` in metres along the outward normal) pushed onto the surface through its Jacobian:
small tangential slides of skin plus bulges. Units are chosen like FLAME's: one unit of a component
moves skin by about 1-3 mm at its peak, except ``blink_l``/``blink_r``, where 1.0 means a fully
closed lid (the lids meet a quarter of the way up the 7-8 mm eye opening) so a rule-based driver
can write blinks as 0-1 pulses. The jaw rotates about a joint behind the face (x-axis pitch; positive opens), with
weights that switch sharply across the lip seam (the lower lip follows the jaw, the upper does not)
and smoothly over the chin and lower cheeks; 0.3 rad drops the lower lip by about 2.5 cm.
"""

from __future__ import annotations

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np

from jaxtalk.face.model import LinearFaceModel
from jaxtalk.layout import EXP_NAMES

__all__ = ["builtin_face", "RESOLUTIONS", "FaceGrid", "face_grid", "surface_displacement"]

# Grid sizes (columns, rows); odd column counts put a column on the symmetry plane.
RESOLUTIONS: dict[str, tuple[int, int]] = {
    "low": (29, 33),  # ~1k vertices: quick tests and previews
    "default": (57, 65),  # ~3.7k vertices
    "high": (71, 83),  # ~5.9k vertices
}

# Feature placement in the (u, v) domain.
V_EYE, U_EYE, EYE_HW, EYE_HH = 0.22, 0.36, 0.14, 0.045
V_BROW = 0.42
V_NOSE_TIP = -0.08
V_MOUTH, MOUTH_HW = -0.42, 0.25
V_CHIN = -0.8
# Lower lid height as a fraction of the upper lid's height above the eye line.
_LOWER_LID = 0.7
# Joints of the built-in face (metres): FLAME's neck -> jaw chain. FLAME's global joint (no weight
# on the face) and eyes are left out: every joint costs a term in the skinning sum.
_JOINTS = np.array([[0.0, -0.17, -0.03], [0.0, -0.01, 0.0]])
_PARENTS = (-1, 0)


def _halfwidth(v: np.ndarray) -> np.ndarray:
    """Half-width in u of the row at height v: an oval, narrower under the chin than at the top."""
    c = np.where(v < 0.0, 0.68, 0.45)
    return np.asarray(np.sqrt(1.0 - c * v**2))


def _gauss(u, v, cu, cv, su, sv):
    return np.exp(-(((u - cu) / su) ** 2) - ((v - cv) / sv) ** 2)


def _height(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Facial relief (metres, added to z): sum of Gaussian bumps and dents."""
    h = np.zeros_like(u)
    for side in (-1.0, 1.0):
        h += 0.007 * _gauss(u, v, side * 0.33, V_BROW - 0.02, 0.22, 0.07)  # brow ridge
        h -= 0.014 * _gauss(u, v, side * U_EYE, V_EYE + 0.01, 0.17, 0.11)  # eye socket
        h += 0.008 * _gauss(u, v, side * U_EYE, V_EYE, 0.11, 0.06)  # eyeball under the lids
        h += 0.007 * _gauss(u, v, side * 0.1, V_NOSE_TIP - 0.06, 0.06, 0.05)  # nostril wings
        h += 0.010 * _gauss(u, v, side * 0.45, -0.08, 0.18, 0.2)  # cheeks
    h += 0.004 * _gauss(u, v, 0.0, V_BROW - 0.04, 0.1, 0.08)  # glabella
    # Nose: a ridge that grows from the bridge to the tip, then falls off under the tip.
    ramp = np.clip((0.32 - v) / (0.32 - V_NOSE_TIP), 0.0, 1.0) ** 1.3
    below = np.exp(-(((np.minimum(v - V_NOSE_TIP, 0.0)) / 0.06) ** 2))
    width = 0.055 + 0.035 * ramp
    h += 0.022 * ramp * below * np.exp(-((u / width) ** 2))
    # Lips: upper and lower vermilion with a groove along the seam; sulcus and chin below.
    h += 0.008 * _gauss(u, v, 0.0, V_MOUTH + 0.05, 0.23, 0.05)
    h += 0.007 * _gauss(u, v, 0.0, V_MOUTH - 0.06, 0.2, 0.05)
    h -= 0.004 * _gauss(u, v, 0.0, V_MOUTH, 0.24, 0.012)
    h -= 0.004 * _gauss(u, v, 0.0, -0.62, 0.2, 0.05)
    h += 0.010 * _gauss(u, v, 0.0, V_CHIN, 0.2, 0.1)
    return h


def _embed(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Surface point (metres) of domain point (u, v), shape ``(..., 3)``."""
    theta = 1.25 * u
    x = 0.075 * np.sin(theta)
    y = 0.1 * v
    z = 0.085 * np.cos(theta) - 0.03 * v**2 - 0.02 * np.maximum(v - 0.3, 0.0) ** 2 + _height(u, v)
    return np.stack([x, y, z], axis=-1)


def _surface_frame(u: np.ndarray, v: np.ndarray):
    """Jacobian columns dX/du, dX/dv (metres per domain unit) and the unit outward normal."""
    eps = 1e-5
    xu = (_embed(u + eps, v) - _embed(u - eps, v)) / (2 * eps)
    xv = (_embed(u, v + eps) - _embed(u, v - eps)) / (2 * eps)
    n = np.cross(xu, xv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return xu, xv, n


def _row_heights(num_rows: int) -> np.ndarray:
    """Row heights v in [-1, 1], denser near the mouth and eyes, one row exactly on the lip seam."""
    fine = np.linspace(-1.0, 1.0, 8001)
    density = 1.0 + 1.4 * np.exp(-(((fine - V_MOUTH) / 0.1) ** 2)) + 0.6 * np.exp(-(((fine - V_EYE) / 0.1) ** 2))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(fine))])
    rows = np.interp(np.linspace(0.0, 1.0, num_rows), cdf / cdf[-1], fine)
    rows[np.argmin(np.abs(rows - V_MOUTH))] = V_MOUTH
    return rows


@dataclasses.dataclass(frozen=True, eq=False)
class FaceGrid:
    """The built-in face's parametric grid (NumPy): domain coordinates and connectivity.

    Attributes:
        s: normalised column coordinate per column, ``(cols,)`` in [-1, 1].
        rows: v per row, ``(rows,)`` increasing (chin to forehead).
        u: u per vertex, ``(V,)``; v: v per vertex, ``(V,)`` (vertex index = row * cols + col).
        faces: triangles ``(F, 3)`` int32, counter-clockwise seen from +z.
        seam_row: index of the row on the lip seam.
    """

    s: np.ndarray
    rows: np.ndarray
    u: np.ndarray
    v: np.ndarray
    faces: np.ndarray
    seam_row: int

    @property
    def num_cols(self) -> int:
        return len(self.s)

    def index(self, row: int | np.ndarray, col: int | np.ndarray) -> np.ndarray:
        """Vertex index of grid node (row, col)."""
        return np.asarray(row) * self.num_cols + np.asarray(col)

    def locate(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Triangle corners and barycentric coordinates of domain points (u, v).

        Args:
            u, v: domain points, shape ``(P,)``, inside the grid's outline.

        Returns:
            ``(corners (P, 3) int32, bary (P, 3))``: the point is ``sum_k bary[k] * X[corners[k]]``
            on the mesh (interpolation is exact in the (s, v) domain, where cells are rectangles).
        """
        u = np.asarray(u, np.float64)
        v = np.asarray(v, np.float64)
        s = u / _halfwidth(v)
        if np.any(np.abs(s) > 1.0) or np.any(np.abs(v) > 1.0):
            raise ValueError(f"domain points outside the face outline: u={u}, v={v}")
        cols = self.num_cols
        i = np.clip(np.searchsorted(self.rows, v) - 1, 0, len(self.rows) - 2)
        j = np.clip(np.searchsorted(self.s, s) - 1, 0, cols - 2)
        fv = (v - self.rows[i]) / (self.rows[i + 1] - self.rows[i])
        fs = (s - self.s[j]) / (self.s[j + 1] - self.s[j])
        a, b = self.index(i, j), self.index(i, j + 1)
        c, d = self.index(i + 1, j), self.index(i + 1, j + 1)
        corners = np.zeros((len(u), 3), np.int64)
        bary = np.zeros((len(u), 3))
        left = 0.5 * (self.s[j] + self.s[j + 1]) < 0.0
        for k in range(len(u)):
            if left[k]:  # cell split along a-d: triangles (a, b, d) and (a, d, c)
                if fs[k] >= fv[k]:
                    corners[k] = (a[k], b[k], d[k])
                    bary[k] = (1 - fs[k], fs[k] - fv[k], fv[k])
                else:
                    corners[k] = (a[k], d[k], c[k])
                    bary[k] = (1 - fv[k], fs[k], fv[k] - fs[k])
            else:  # split along b-c: triangles (a, b, c) and (b, d, c)
                if fs[k] + fv[k] <= 1.0:
                    corners[k] = (a[k], b[k], c[k])
                    bary[k] = (1 - fs[k] - fv[k], fs[k], fv[k])
                else:
                    corners[k] = (b[k], d[k], c[k])
                    bary[k] = (1 - fv[k], fs[k] + fv[k] - 1, 1 - fs[k])
        return corners.astype(np.int32), bary


@functools.lru_cache(maxsize=8)
def face_grid(resolution: str = "default") -> FaceGrid:
    """The parametric grid of the built-in face at a named resolution (cached).

    Args:
        resolution: one of ``RESOLUTIONS`` ("low", "default", "high").

    Returns:
        The ``FaceGrid``.

    Raises:
        ValueError: for an unknown resolution.
    """
    if resolution not in RESOLUTIONS:
        raise ValueError(f"unknown resolution {resolution!r}; known: {sorted(RESOLUTIONS)}")
    num_cols, num_rows = RESOLUTIONS[resolution]
    s = np.linspace(-1.0, 1.0, num_cols)
    s = 0.5 * (s - s[::-1])  # exactly antisymmetric, so mirrored vertices mirror to the last bit
    rows = _row_heights(num_rows)
    ss, vv = np.meshgrid(s, rows)
    u = (ss * _halfwidth(vv)).ravel()
    v = vv.ravel()
    i, j = np.meshgrid(np.arange(num_rows - 1), np.arange(num_cols - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    a, b = i * num_cols + j, i * num_cols + j + 1
    c, d = a + num_cols, b + num_cols
    left = (0.5 * (s[j] + s[j + 1]) < 0.0)[:, None]
    # Mirrored diagonals keep the mesh exactly left/right symmetric.
    tri1 = np.where(left, np.stack([a, b, d], 1), np.stack([a, b, c], 1))
    tri2 = np.where(left, np.stack([a, d, c], 1), np.stack([b, d, c], 1))
    faces = np.concatenate([tri1, tri2]).astype(np.int32)
    seam_row = int(np.argmin(np.abs(rows - V_MOUTH)))
    return FaceGrid(s=s, rows=rows, u=u, v=v, faces=faces, seam_row=seam_row)


# ---- expression basis ---------------------------------------------------------------------------
def _lid_fields(u, v, cx):
    """Blink and eye-widening fields (dv, domain units) for the eye centred at u = cx.

    A blink collapses the lid opening onto a line a quarter of the way up from the lower lid: the
    upper lid travels 3/4 of the opening, the lower lid 1/4, and the skin above/below follows with a
    short fall-off. The field is linear in v across the opening, so its interpolation on a coarse
    mesh still closes the lids. Eye widening lifts the upper lid and the lid skin above it.
    """
    q = (u - cx) / EYE_HW
    shape = np.sqrt(np.clip(1.0 - q**2, 0.0, None))
    upper = V_EYE + EYE_HH * shape
    lower = V_EYE - _LOWER_LID * EYE_HH * shape
    opening = upper - lower
    h = np.clip((v - lower) / np.maximum(opening, 1e-12), 0.0, 1.0)
    above = np.exp(-((np.maximum(v - upper, 0.0) / 0.07) ** 2))
    below = np.exp(-((np.maximum(lower - v, 0.0) / 0.04) ** 2))
    meet = 0.25
    blink = opening * np.where(v > upper, -(1 - meet) * above, np.where(v < lower, meet * below, meet - h))
    widen = shape * np.where(v > upper, above, h)
    return blink, widen


def _expression_fields(u: np.ndarray, v: np.ndarray, seam_width: float) -> dict[str, tuple]:
    """(du, dv, dn) per named component; residuals are added separately."""
    zero = np.zeros_like(u)
    seam = np.tanh((v - V_MOUTH) / seam_width)  # +1 on the upper lip, -1 on the lower lip
    upper_half, lower_half = 0.5 * (1 + seam), 0.5 * (1 - seam)
    mouth_u = np.exp(-((u / MOUTH_HW) ** 4))  # flat across the mouth, fading past the corners
    mouth_u_wide = np.exp(-((u / (1.3 * MOUTH_HW)) ** 4))
    lips = np.exp(-(((v - V_MOUTH) / 0.11) ** 2))
    lips_m = mouth_u * lips

    def corner(side, su=0.08, sv=0.07):
        return _gauss(u, v, side * MOUTH_HW, V_MOUTH, su, sv)

    cl, cr = corner(1.0), corner(-1.0)
    wl, wr = corner(1.0, 0.12, 0.12), corner(-1.0, 0.12, 0.12)
    upper_lip = mouth_u * np.exp(-(((v - V_MOUTH - 0.05) / 0.08) ** 2)) * upper_half
    lower_lip = mouth_u * np.exp(-(((v - V_MOUTH + 0.06) / 0.08) ** 2)) * lower_half

    # Each lip component gets its own spatial profile (not only its own mix of shared fields), so
    # the named components stay linearly independent and every one of them is identifiable from
    # the vertices: a narrow centre (pucker), a thin band at the lip line (parting), a tall band
    # (funnel flares the lips vertically), the lip level only (spread pulls the corners sideways).
    centre = np.exp(-((u / (0.6 * MOUTH_HW)) ** 2)) * lips
    line = mouth_u * np.exp(-(((v - V_MOUTH) / 0.05) ** 2))
    tall = mouth_u * np.exp(-(((v - V_MOUTH) / 0.16) ** 2))
    level = mouth_u_wide * np.exp(-(((v - V_MOUTH) / 0.07) ** 2))
    f: dict[str, tuple] = {
        "lip_close": (zero, -0.012 * seam * lips_m, -0.001 * lips_m),
        "lip_round": (-0.08 * u * mouth_u_wide * lips, -0.004 * seam * centre, 0.003 * centre),
        "lip_spread": (0.08 * u * level, 0.002 * (cl + cr), -0.001 * level),
        "lip_funnel": (-0.04 * u * mouth_u_wide * tall, 0.006 * seam * tall, 0.0025 * tall),
        "upper_lip_raise": (zero, 0.02 * upper_lip, 0.0005 * upper_lip),
        "lower_lip_depress": (zero, -0.02 * lower_lip, 0.0005 * lower_lip),
        "lip_part": (zero, 0.01 * seam * line, zero),
        "lip_tuck": (zero, 0.008 * lower_lip, -0.003 * lower_lip),
        "lip_tight": (
            -0.02 * u * lips_m,
            -0.005 * seam * mouth_u * np.exp(-(((v - V_MOUTH) / 0.06) ** 2)),
            -0.002 * lips_m,
        ),
        "mouth_corner_up": (0.01 * (cl - cr), 0.025 * (cl + cr), zero),
        "mouth_corner_down": (0.003 * (cl - cr), -0.02 * (cl + cr), zero),
        "mouth_stretch": (0.025 * (wl - wr), -0.008 * (wl + wr), zero),
    }
    for side, tag in ((1.0, "l"), (-1.0, "r")):
        inner = _gauss(u, v, side * 0.14, V_BROW + 0.01, 0.14, 0.13)
        outer = _gauss(u, v, side * 0.52, V_BROW - 0.01, 0.15, 0.13)
        brow = _gauss(u, v, side * 0.3, V_BROW, 0.24, 0.12)
        brow_in = _gauss(u, v, side * 0.2, V_BROW, 0.15, 0.12)
        f[f"brow_inner_up_{tag}"] = (zero, 0.03 * inner, zero)
        f[f"brow_outer_up_{tag}"] = (zero, 0.025 * outer, zero)
        f[f"brow_down_{tag}"] = (-0.01 * side * brow_in, -0.02 * brow, 0.001 * brow)
        blink, widen = _lid_fields(u, v, side * U_EYE)
        f[f"blink_{tag}"] = (zero, blink, zero)
        f[f"eye_wide_{tag}"] = (zero, 0.02 * widen, zero)
        cheek = _gauss(u, v, side * 0.42, -0.1, 0.17, 0.15)
        f[f"cheek_raise_{tag}"] = (zero, 0.02 * cheek, 0.002 * cheek)
        puff = _gauss(u, v, side * 0.38, -0.38, 0.15, 0.15)
        f[f"cheek_puff_{tag}"] = (zero, zero, 0.003 * puff)
        wrinkle = _gauss(u, v, side * 0.08, 0.05, 0.06, 0.1)
        f[f"nose_wrinkle_{tag}"] = (-0.003 * side * wrinkle, 0.012 * wrinkle, 0.001 * wrinkle)
    return f


# Residual modes: (direction, a, b) with field cos(a pi (u+1)/2) cos(b pi (v+1)/2); low frequency first.
_RESIDUALS = (
    ("n", 0, 1), ("v", 0, 0), ("u", 0, 0), ("n", 1, 0), ("v", 1, 0), ("u", 1, 0),
    ("n", 1, 1), ("v", 0, 1), ("u", 0, 1), ("n", 0, 2), ("v", 1, 1), ("u", 1, 1),
    ("n", 2, 0), ("v", 2, 0), ("u", 2, 0), ("n", 1, 2), ("v", 0, 2), ("u", 0, 2),
    ("n", 2, 1), ("v", 2, 1), ("u", 1, 2), ("n", 0, 3),
)


def _residual_field(u, v, direction, a, b):
    phi = np.cos(a * np.pi * (u + 1) / 2) * np.cos(b * np.pi * (v + 1) / 2)
    zero = np.zeros_like(u)
    if direction == "n":
        return zero, zero, 0.0015 * phi
    if direction == "v":
        return zero, 0.015 * phi, zero
    return 0.015 * phi, zero, zero


def _push(frame, field) -> np.ndarray:
    """Displacements (metres, (V, 3)) of a (du, dv, dn) field given the surface frame (xu, xv, n)."""
    (xu, xv, n), (du, dv, dn) = frame, field
    return du[:, None] * xu + dv[:, None] * xv + dn[:, None] * n


def surface_displacement(du: np.ndarray, dv: np.ndarray, dn: np.ndarray, *, resolution: str = "default") -> np.ndarray:
    """A displacement field over the domain, pushed onto the mean built-in face's surface.

    How the named expression components are made, open to other shape makers (the built-in ARKit rig,
    :func:`jaxtalk.export.arkit_rig`): ``du``, ``dv`` slide the skin along the surface (domain units,
    about 0.1 m each), ``dn`` moves it along the outward normal (metres).

    Args:
        du, dv, dn: per vertex of :func:`face_grid` ``(resolution)``, shape ``(V,)`` each.
        resolution: the mesh density.

    Returns:
        ``(V, 3)`` displacements in metres.

    Raises:
        ValueError: fields that are not one value per vertex.
    """
    grid = face_grid(resolution)
    fields = [np.asarray(f, np.float64) for f in (du, dv, dn)]
    if any(f.shape != grid.u.shape for f in fields):
        raise ValueError(f"du, dv, dn must each have shape {grid.u.shape}, got {[f.shape for f in fields]}")
    return _push(_mean_face_numpy(resolution)["frame"], fields)


def _seam_width(grid: FaceGrid) -> float:
    # Half the row spacing at the seam: the rows next to the seam sit on opposite lips.
    return 0.5 * float(grid.rows[grid.seam_row + 1] - grid.rows[grid.seam_row])


def _expression_basis(grid: FaceGrid) -> np.ndarray:
    u, v = grid.u, grid.v
    named = _expression_fields(u, v, _seam_width(grid))
    residual_names = [n for n in EXP_NAMES if n.startswith("residual_")]
    if len(residual_names) != len(_RESIDUALS):
        raise AssertionError("residual modes and layout disagree")
    for name, spec in zip(residual_names, _RESIDUALS):
        named[name] = _residual_field(u, v, *spec)
    frame = _surface_frame(u, v)
    basis = np.stack([_push(frame, named[name]) for name in EXP_NAMES], axis=-1)
    # Normalise each component to its peak displacement per unit (FLAME-like millimetres); blinks
    # keep their geometric scale (1.0 = lid closed).
    peak = np.linalg.norm(basis, axis=1).max(axis=0)
    target = np.array([_PEAK_MM.get(name.rsplit("_", 1)[0] if name[-2:] in ("_l", "_r") else name,
                                    _PEAK_MM["residual"] if name.startswith("residual_") else 2.5)
                       for name in EXP_NAMES]) * 1e-3
    scale = np.where(np.isnan(target), 1.0, target / peak)
    return basis * scale


# Peak displacement (mm) per unit coefficient; NaN keeps the geometric scale (blinks).
_PEAK_MM = {
    "blink": np.nan,
    "brow_inner_up": 3.0,
    "brow_outer_up": 2.5,
    "brow_down": 2.5,
    "eye_wide": 2.0,
    "nose_wrinkle": 1.5,
    "lip_spread": 2.0,
    "lip_close": 2.0,
    "residual": 1.5,
}


def _jaw_weights(grid: FaceGrid) -> np.ndarray:
    """Jaw skinning weight per vertex: sharp across the lip seam, smooth over cheeks and chin."""
    u, v = np.abs(grid.u), grid.v
    line = V_MOUTH + 0.3 * np.maximum(u - MOUTH_HW, 0.0)
    ramp = np.clip((u - 0.8 * MOUTH_HW) / (0.7 * MOUTH_HW), 0.0, 1.0)
    ramp = ramp * ramp * (3 - 2 * ramp)
    width = _seam_width(grid) * 0.6 + (0.08 - _seam_width(grid) * 0.6) * ramp
    weight = 0.5 * (1.0 + np.tanh((line - v) / (2.0 * width)))
    # Taper to exactly zero above the jaw line (temples and upper face never follow the jaw).
    taper = np.clip((line + 0.2 - v) / 0.15, 0.0, 1.0)
    return weight * taper * taper * (3 - 2 * taper)


# ---- regions and landmarks ----------------------------------------------------------------------
def _regions(grid: FaceGrid, jaw_weight: np.ndarray) -> dict[str, np.ndarray]:
    u, v = grid.u, grid.v
    cols = grid.num_cols
    mouth_cols = np.flatnonzero(np.abs(grid.s * _halfwidth(np.full_like(grid.s, V_MOUTH))) <= 0.5 * MOUTH_HW)
    eye_l = ((u - U_EYE) / 0.17) ** 2 + ((v - V_EYE) / 0.1) ** 2 <= 1.0
    eye_r = ((u + U_EYE) / 0.17) ** 2 + ((v - V_EYE) / 0.1) ** 2 <= 1.0
    regions = {
        "lips": np.flatnonzero((u / 0.27) ** 2 + ((v - V_MOUTH) / 0.13) ** 2 <= 1.0),
        "mouth_upper": (grid.seam_row + 1) * cols + mouth_cols,
        "mouth_lower": (grid.seam_row - 1) * cols + mouth_cols,
        "upper_face": np.flatnonzero(v >= 0.05),
        "eyes": np.flatnonzero(eye_l | eye_r),
        "eye_l": np.flatnonzero(eye_l),
        "eye_r": np.flatnonzero(eye_r),
        "brows": np.flatnonzero((np.abs(u) - 0.35) ** 2 / 0.28**2 + ((v - V_BROW) / 0.08) ** 2 <= 1.0),
        "nose": np.flatnonzero((u / 0.14) ** 2 + ((v - 0.08) / 0.28) ** 2 <= 1.0),
        "jaw": np.flatnonzero(jaw_weight > 0.5),
        "lower_face": np.flatnonzero(v < V_NOSE_TIP - 0.1),
    }
    return {k: np.asarray(idx, np.int32) for k, idx in regions.items()}


def _landmark_domain_points() -> np.ndarray:
    """The 68 landmarks as (u, v) domain points in iBUG order, shape (68, 2)."""
    pts: list[tuple[float, float]] = []
    v_top, v_bottom = 0.12, -0.92
    for k in range(17):  # jaw line, subject's right (x < 0) to left through the chin
        alpha = -np.pi / 2 + k * np.pi / 16
        v = v_top - (v_top - v_bottom) * np.cos(alpha)
        pts.append((0.93 * np.sin(alpha) * float(_halfwidth(np.array(v))), v))
    brow_u = [0.58, 0.47, 0.36, 0.25, 0.14]
    brow_v = [0.39, 0.425, 0.44, 0.435, 0.42]
    pts += [(-bu, bv) for bu, bv in zip(brow_u, brow_v)]  # right brow, outer -> inner
    pts += [(bu, bv) for bu, bv in zip(brow_u[::-1], brow_v[::-1])]  # left brow, inner -> outer
    pts += [(0.0, vv) for vv in (0.28, 0.16, 0.04, V_NOSE_TIP)]  # bridge, top -> tip
    pts += list(zip([-0.11, -0.055, 0.0, 0.055, 0.11], [-0.16, -0.18, -0.19, -0.18, -0.16]))

    def lid(du, upper):
        shape = np.sqrt(1 - (du / EYE_HW) ** 2)
        return V_EYE + (EYE_HH if upper else -_LOWER_LID * EYE_HH) * shape

    third, corner = EYE_HW / 3, 0.97 * EYE_HW
    for cx, first in ((-U_EYE, -1.0), (U_EYE, -1.0)):
        # Both eyes start at their image-left corner and run clockwise over the upper lid.
        du_seq = [first * corner, -third, third, corner, third, -third]
        for k, du in enumerate(du_seq):
            vv = V_EYE if k in (0, 3) else lid(du, k in (1, 2))
            pts.append((cx + du, vv))

    def outer_lip(uu, upper):
        r = np.clip(1 - (uu / MOUTH_HW) ** 2, 0.0, None) ** 0.7
        return V_MOUTH + (0.085 if upper else -0.1) * r

    outer_u = [-0.95, -0.6, -0.25, 0.0, 0.25, 0.6, 0.95, 0.6, 0.25, 0.0, -0.25, -0.6]
    for k, fu in enumerate(outer_u):
        uu = fu * MOUTH_HW
        pts.append((uu, V_MOUTH if k in (0, 6) else outer_lip(uu, k < 6)))
    return np.asarray(pts)


def _landmark_inner_lips(grid: FaceGrid) -> np.ndarray:
    # Half a row off the seam: on the upper/lower lip side of the seam, closed mouth ~ 2 mm gap.
    up = 0.5 * (grid.rows[grid.seam_row + 1] - V_MOUTH)
    down = 0.5 * (V_MOUTH - grid.rows[grid.seam_row - 1])
    inner_u = [-0.8, -0.4, 0.0, 0.4, 0.8, 0.4, 0.0, -0.4]
    inner_dv = [0.0, up, up, up, 0.0, -down, -down, -down]
    return np.asarray([(fu * MOUTH_HW, V_MOUTH + dv) for fu, dv in zip(inner_u, inner_dv)])


# ---- identity ------------------------------------------------------------------------------------
_NUM_SHAPE_MODES = 10


def _identity_offsets(grid: FaceGrid, frame, coeffs: np.ndarray) -> np.ndarray:
    """Local shape-mode offsets (metres) for shape coefficients ``coeffs[3:]``."""
    u, v = grid.u, grid.v
    zero = np.zeros_like(u)
    nose = np.exp(-((u / 0.08) ** 2)) * np.exp(-(((v - 0.05) / 0.25) ** 2))
    chin = _gauss(u, v, 0.0, V_CHIN, 0.25, 0.15)
    cheeks = _gauss(u, v, 0.45, -0.1, 0.2, 0.2) + _gauss(u, v, -0.45, -0.1, 0.2, 0.2)
    lips = np.exp(-((u / MOUTH_HW) ** 4)) * np.exp(-(((v - V_MOUTH) / 0.11) ** 2))
    brows = _gauss(u, v, 0.33, V_BROW, 0.22, 0.08) + _gauss(u, v, -0.33, V_BROW, 0.22, 0.08)
    eyes_l, eyes_r = _gauss(u, v, U_EYE, V_EYE, 0.2, 0.15), _gauss(u, v, -U_EYE, V_EYE, 0.2, 0.15)
    jaw = np.exp(-(((v + 0.7) / 0.3) ** 2))
    modes = [
        (zero, zero, 0.003 * nose),
        (zero, -0.02 * chin, 0.003 * chin),
        (zero, zero, 0.003 * cheeks),
        (zero, zero, 0.0015 * lips),
        (zero, zero, 0.002 * brows),
        (0.015 * (eyes_l - eyes_r), zero, zero),
        (0.03 * u * jaw, zero, zero),
    ]
    assert len(modes) == _NUM_SHAPE_MODES - 3
    offsets = np.zeros((len(u), 3))
    for c, mode in zip(coeffs[3:], modes):
        offsets += c * _push(frame, mode)
    return offsets


def _shape_coefficients(identity: int) -> np.ndarray:
    if identity == 0:
        return np.zeros(_NUM_SHAPE_MODES)
    rng = np.random.default_rng([abs(identity), int(identity < 0), 0x5FACE])
    return rng.standard_normal(_NUM_SHAPE_MODES)


@functools.lru_cache(maxsize=4)
def _mean_face_numpy(resolution: str) -> dict[str, object]:
    grid = face_grid(resolution)
    template = _embed(grid.u, grid.v)
    jaw = _jaw_weights(grid)
    weights = np.stack([1.0 - jaw, jaw], axis=1)
    lm_uv = np.concatenate([_landmark_domain_points(), _landmark_inner_lips(grid)])
    lm_vertices, lm_bary = grid.locate(lm_uv[:, 0], lm_uv[:, 1])
    return {
        "grid": grid,
        "template": template,
        "frame": _surface_frame(grid.u, grid.v),
        "exp_basis": _expression_basis(grid),
        "weights": weights,
        "regions": _regions(grid, jaw),
        "landmark_vertices": lm_vertices,
        "landmark_bary": lm_bary,
    }


def builtin_face(identity: int = 0, *, resolution: str = "default") -> LinearFaceModel:
    """The built-in procedural face model (deterministic, no files).

    Args:
        identity: 0 for the mean face; any other integer gives a deterministic smooth shape variation
            (face width/height/depth scales and local nose, chin, cheek, lip, brow, eye-spacing and
            jaw-width modes with seeded standard-normal coefficients). Same topology for all.
        resolution: mesh density, one of ``"low"`` (~1k vertices), ``"default"`` (~3.7k),
            ``"high"`` (~5.9k).

    Returns:
        A ``LinearFaceModel`` (float32 arrays unless 64-bit mode is on) with the 50 named expression
        components of ``jaxtalk.layout.EXP_NAMES``, joints (neck, jaw), skinning weights, the 68
        landmarks and regions: "lips" (LVE), "upper_face" (FDD: above mid-nose), "mouth_upper" /
        "mouth_lower" (paired rows just above/below the lip seam, same length and column order:
        MOD), "eyes", "eye_l", "eye_r", "brows", "nose", "jaw" (jaw weight > 0.5), "lower_face".

    Raises:
        ValueError: for an unknown resolution or a non-integer identity.
    """
    if isinstance(identity, bool) or not isinstance(identity, (int, np.integer)):
        raise ValueError(f"identity must be an integer, got {identity!r}")
    base = _mean_face_numpy(resolution)
    grid: FaceGrid = base["grid"]  # type: ignore[assignment]
    coeffs = _shape_coefficients(int(identity))
    scale = 1.0 + np.array([0.04, 0.04, 0.05]) * coeffs[:3]
    template = (base["template"] + _identity_offsets(grid, base["frame"], coeffs)) * scale
    joints = _JOINTS * scale
    num_joints = len(_PARENTS)
    return LinearFaceModel(
        template=jnp.asarray(template),
        faces=grid.faces,
        exp_basis=jnp.asarray(base["exp_basis"]),
        joints=jnp.asarray(joints),
        joint_exp_basis=jnp.zeros((num_joints, 3, len(EXP_NAMES)), jnp.asarray(template).dtype),
        weights=jnp.asarray(base["weights"]),
        pose_basis=None,
        landmark_vertices=base["landmark_vertices"],
        landmark_bary=jnp.asarray(base["landmark_bary"]),
        regions=dict(base["regions"]),  # type: ignore[arg-type]
        parents=_PARENTS,
        neck_joint=0,
        jaw_joint=1,
        # Static metadata: keep it identity-free so all identities share compiled programs.
        name="builtin",
    )
