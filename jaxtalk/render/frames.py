"""Shaded RGB frames of face meshes: one frame, a clip, or several clips side by side with captions.

Frames are rendered on the CPU by the NumPy rasteriser (``jaxtalk.render.rasterize``), so nothing
needs a display or OpenGL. A clip shares one camera (fitted once to all of its frames unless given),
so the motion, not the framing, changes between frames. Any triangle mesh renders: the built-in face,
FLAME, or FreeTalk's topology variants.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator, Sequence

import numpy as np

from jaxtalk.render.camera import Camera, fit_camera
from jaxtalk.render.rasterize import rasterize
from jaxtalk.render.shading import RenderStyle, cavity_weights, shade
from jaxtyping import UInt8

from jaxtalk.types import Array, Float, Int, Shaped

__all__ = ["render_frame", "iter_frames", "render_frames", "caption_strip", "check_vertices", "check_faces"]

ArrayLike = Array | np.ndarray


def check_vertices(vertices: Shaped[ArrayLike, "..."], *, name: str = "vertices", batched: bool = True) -> np.ndarray:
    """Validate a vertex array and return it as float32 NumPy.

    Args:
        vertices: ``(T, V, 3)`` if ``batched`` else ``(V, 3)``.
        name: how to call it in error messages.
        batched: whether a leading frame axis is expected.

    Returns:
        The vertices as a float32 ``np.ndarray`` of the same shape.

    Raises:
        ValueError: for a wrong shape, zero frames or vertices, or NaN/inf (with the first bad frame).
    """
    v = np.asarray(vertices)
    want = "(T, V, 3)" if batched else "(V, 3)"
    if v.ndim != (3 if batched else 2) or v.shape[-1] != 3:
        raise ValueError(f"{name} must have shape {want}, got {v.shape}")
    if not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"{name} must be floating point, got dtype {v.dtype}")
    if batched and v.shape[0] == 0:
        raise ValueError(f"{name} has zero frames: nothing to render")
    if v.shape[-2] == 0:
        raise ValueError(f"{name} has zero vertices")
    v = v.astype(np.float32, copy=False)
    finite = np.isfinite(v).all(axis=(-2, -1))
    if not np.all(finite):
        where = f"frame {int(np.argmin(finite))}" if batched else "the mesh"
        raise ValueError(f"{name} holds NaN or inf (first in {where})")
    return v


def check_faces(faces: Shaped[ArrayLike, "..."], num_vertices: int, *, name: str = "faces") -> np.ndarray:
    """Validate triangles against a vertex count and return them as int32 NumPy.

    Args:
        faces: triangles, ``(F, 3)`` integer vertex indices.
        num_vertices: number of vertices they must index.
        name: how to call it in error messages.

    Returns:
        ``(F, 3)`` int32 array.

    Raises:
        ValueError: for a wrong shape or dtype, no triangles, or an index outside ``[0, num_vertices)``.
    """
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{name} must have shape (F, 3), got {f.shape}")
    if f.shape[0] == 0:
        raise ValueError(f"{name} is empty: no triangles to render")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name} must be integer vertex indices, got dtype {f.dtype}")
    if f.min() < 0 or f.max() >= num_vertices:
        raise ValueError(
            f"{name} index vertices {int(f.min())}..{int(f.max())} but the mesh has {num_vertices} vertices "
            f"(mismatched faces and vertices?)"
        )
    return f.astype(np.int32, copy=False)


def _compose(pixel: np.ndarray, colors: np.ndarray, height: int, width: int, style: RenderStyle) -> np.ndarray:
    """Paint fragment colours (display, 0-255) over the background; box-filter a supersampled image."""
    background = np.float32(255.0) * np.asarray(style.background, np.float32)
    s = style.supersample
    if s == 1:
        image = np.empty((height * width, 3), np.uint8)
        image[:] = (background + np.float32(0.5)).astype(np.uint8)
        image[pixel] = (colors + np.float32(0.5)).astype(np.uint8)
        return image.reshape(height, width, 3)
    image = np.empty((height * width, 3), np.float32)
    image[:] = background
    image[pixel] = colors
    image = image.reshape(height // s, s, width // s, s, 3).mean(axis=(1, 3))
    return (image + np.float32(0.5)).astype(np.uint8)


def _scaled(camera: Camera, factor: int) -> Camera:
    """The same view at ``factor`` times the resolution (for supersampling)."""
    if factor == 1:
        return camera
    cx, cy = camera.principal
    return Camera(
        rotation=camera.rotation,
        target=camera.target,
        distance=camera.distance,
        focal=camera.focal * factor,
        principal=(cx * factor, cy * factor),
        width=camera.width * factor,
        height=camera.height * factor,
        orthographic=camera.orthographic,
    )


def _render_checked(
    vertices: np.ndarray,
    faces: np.ndarray,
    camera: Camera,
    style: RenderStyle,
    colors: np.ndarray | None,
    rest: np.ndarray | None,
) -> np.ndarray:
    cam = _scaled(camera, style.supersample)
    verts_cam = cam.to_camera(vertices)
    xy, depth = cam.project_camera(verts_cam)
    frags = rasterize(xy, depth, faces, cam.height, cam.width, perspective=not cam.orthographic)
    cavity = None if rest is None else cavity_weights(vertices, rest, faces, style.cavity_stretch)
    colors = shade(
        frags, verts_cam, faces, style, vertex_colors=colors, cavity=cavity, orthographic=cam.orthographic
    )
    return _compose(frags.pixel, colors, cam.height, cam.width, style)


def _check_colors(colors: Shaped[ArrayLike, "..."] | None, num_vertices: int) -> np.ndarray | None:
    if colors is None:
        return None
    c = np.asarray(colors, np.float32)
    if c.shape != (num_vertices, 3):
        raise ValueError(f"vertex_colors must have shape ({num_vertices}, 3), got {c.shape}")
    if not (np.all(np.isfinite(c)) and c.min() >= 0.0 and c.max() <= 1.0):
        raise ValueError("vertex_colors must be finite RGB values in [0, 1]")
    return c


def _check_rest(rest: Shaped[ArrayLike, "..."] | None, num_vertices: int, name: str = "rest_vertices") -> np.ndarray | None:
    if rest is None:
        return None
    r = check_vertices(rest, name=name, batched=False)
    if r.shape[0] != num_vertices:
        raise ValueError(f"{name} has {r.shape[0]} vertices but the mesh has {num_vertices}")
    return r


def render_frame(
    vertices: Float[ArrayLike, "..."],
    faces: Int[ArrayLike, "..."],
    camera: Camera,
    *,
    style: RenderStyle = RenderStyle(),
    vertex_colors: Float[ArrayLike, "..."] | None = None,
    rest_vertices: Float[ArrayLike, "..."] | None = None,
) -> UInt8[np.ndarray, "height width 3"]:
    """Render one shaded frame of a triangle mesh.

    Args:
        vertices: mesh vertices in metres, ``(V, 3)``.
        faces: triangles, ``(F, 3)`` integer indices into ``vertices``.
        camera: the view (its ``width``/``height`` set the image size).
        style: colours, lights and anti-aliasing.
        vertex_colors: optional per-vertex albedo in ``[0, 1]``, ``(V, 3)``.
        rest_vertices: optional rest pose of the mesh (e.g. the model's template), ``(V, 3)``: then
            triangles stretched far beyond their rest area (the skin spanning an open mouth) are
            drawn as mouth cavity (``shading.cavity_weights``).

    Returns:
        RGB image, ``(camera.height, camera.width, 3)`` uint8.

    Raises:
        ValueError: for malformed or non-finite vertices, faces that index missing vertices, or
            vertex colours / rest vertices of the wrong shape.
    """
    v = check_vertices(vertices, batched=False)
    f = check_faces(faces, v.shape[0])
    rest = _check_rest(rest_vertices, v.shape[0])
    return _render_checked(v, f, camera, style, _check_colors(vertex_colors, v.shape[0]), rest)


@functools.lru_cache(maxsize=8)
def _font(size: int):
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)


def caption_strip(
    text: str, width: int, style: RenderStyle = RenderStyle(), *, height: int | None = None
) -> UInt8[np.ndarray, "rows width 3"]:
    """A strip with centred caption text on the background colour, to stack above a panel.

    Args:
        text: the caption (one line; shrunk to fit the width).
        width: strip width in pixels.
        style: gives the background colour.
        height: strip height in pixels (default: about 9% of the width, at least 16).

    Returns:
        RGB strip, ``(height, width, 3)`` uint8.
    """
    from PIL import Image, ImageDraw

    rows = height if height is not None else max(16, round(0.09 * width))
    bg = tuple(int(round(255 * c)) for c in style.background)
    strip = Image.new("RGB", (width, rows), bg)
    draw = ImageDraw.Draw(strip)
    size = max(6, int(rows * 0.62))
    while size > 6 and draw.textlength(text, font=_font(size)) > 0.96 * width:
        size -= 1
    draw.text((width / 2, rows / 2), text, fill=(235, 235, 235), font=_font(size), anchor="mm")
    return np.asarray(strip, np.uint8)


def _as_list(x, name: str) -> list:
    if isinstance(x, (list, tuple)):
        if len(x) == 0:
            raise ValueError(f"{name} is an empty list: nothing to render")
        return list(x)
    return [x]


def _per_clip(value, n: int, name: str) -> list:
    """One entry per clip from None, a single array (shared), or a list with one entry per clip."""
    values = list(value) if isinstance(value, (list, tuple)) else [value] * n
    if len(values) != n:
        raise ValueError(f"got {len(values)} {name} for {n} clips")
    return values


def iter_frames(
    vertices: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."]],
    faces: Int[ArrayLike, "..."] | Sequence[Int[ArrayLike, "..."]],
    *,
    camera: Camera | None = None,
    size: int | tuple[int, int] = 256,
    captions: Sequence[str] | None = None,
    style: RenderStyle = RenderStyle(),
    vertex_colors: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."] | None] | None = None,
    rest_vertices: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."] | None] | None = None,
    margin: int | float = 0.08,
) -> Iterator[UInt8[np.ndarray, "height total_width 3"]]:
    """Render a clip frame by frame (a generator, so long clips never sit in memory at once).

    Several clips (e.g. ground truth | prediction, or one motion on several topologies) render side
    by side, one panel each, in one shared camera, so equal sizes on screen are equal sizes in metres.

    Args:
        vertices: one clip ``(T, V, 3)`` or a list of clips ``(T, V_i, 3)`` with the same ``T``.
        faces: the triangles ``(F, 3)``: one array for every clip, or a list with one per clip.
        camera: the view of every panel; default: ``fit_camera`` on all frames of all clips (so the
            whole motion stays inside the image) with ``size`` and ``margin``.
        size: panel size in pixels, ``side`` or ``(width, height)``, when ``camera`` is None.
        captions: one caption per clip, drawn in a strip above each panel (None: no strip).
        style: colours, lights and anti-aliasing.
        vertex_colors: per-vertex albedo ``(V_i, 3)``: None, one array for every clip, or one per clip.
        rest_vertices: rest pose ``(V_i, 3)`` (None, one for every clip, or one per clip) to draw the
            open mouth as a cavity (see ``render_frame``).
        margin: framing margin when the camera is fitted.

    Yields:
        RGB frames, ``(H, n_clips * W, 3)`` uint8 with ``H = height`` plus the caption strip.

    Raises:
        ValueError: (before the first frame) for empty or malformed clips, NaN/inf vertices, clips of
            different lengths, faces/colours that do not match their clip, or a caption count that is
            not one per clip.
    """
    clips = [check_vertices(v, name=f"vertices[{i}]") for i, v in enumerate(_as_list(vertices, "vertices"))]
    n = len(clips)
    num_frames = clips[0].shape[0]
    if any(c.shape[0] != num_frames for c in clips):
        raise ValueError(f"clips must have the same number of frames, got {[c.shape[0] for c in clips]}")
    face_list = _per_clip(faces, n, "face arrays")
    face_list = [check_faces(f, c.shape[1], name=f"faces[{i}]") for i, (f, c) in enumerate(zip(face_list, clips))]
    color_list = _per_clip(vertex_colors, n, "vertex_colors")
    color_list = [_check_colors(c, clip.shape[1]) for c, clip in zip(color_list, clips)]
    rest_list = _per_clip(rest_vertices, n, "rest_vertices")
    rest_list = [_check_rest(r, clip.shape[1], f"rest_vertices[{i}]") for i, (r, clip) in enumerate(zip(rest_list, clips))]
    if captions is not None and len(captions) != n:
        raise ValueError(f"got {len(captions)} captions for {n} clips")
    if camera is None:
        width, height = (size, size) if isinstance(size, int) else size
        camera = fit_camera(
            np.concatenate([c.reshape(-1, 3) for c in clips]), width=width, height=height, margin=margin
        )
    strips = None if captions is None else [caption_strip(t, camera.width, style) for t in captions]

    def generate() -> Iterator[np.ndarray]:
        for t in range(num_frames):
            panels = [
                _render_checked(c[t], f, camera, style, col, rest)
                for c, f, col, rest in zip(clips, face_list, color_list, rest_list)
            ]
            if strips is not None:
                panels = [np.concatenate([s, p], axis=0) for s, p in zip(strips, panels)]
            yield panels[0] if n == 1 else np.concatenate(panels, axis=1)

    # Validation above runs eagerly (this is not itself a generator function); frames are lazy.
    return generate()


def render_frames(
    vertices: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."]],
    faces: Int[ArrayLike, "..."] | Sequence[Int[ArrayLike, "..."]],
    **kwargs,
) -> UInt8[np.ndarray, "frames height total_width 3"]:
    """All frames of a clip (or of clips side by side) as one array; see ``iter_frames`` for arguments.

    Returns:
        RGB frames, ``(T, H, n_clips * W, 3)`` uint8.

    Raises:
        ValueError: as ``iter_frames``.
    """
    return np.stack(list(iter_frames(vertices, faces, **kwargs)))
