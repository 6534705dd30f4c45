"""One call from vertex sequences (and audio) to a video file: ``render_clip``."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxtalk.files import check_output_path
from jaxtalk.render.camera import Camera
from jaxtalk.render.frames import iter_frames
from jaxtalk.render.shading import RenderStyle
from jaxtalk.render.video import check_audio_duration, write_gif, write_mp4
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS, Array, Float, Int

# Python scalars: beartype (under pytest) does not promote int to float.
Real = int | float

__all__ = ["render_clip"]

ArrayLike = Array | np.ndarray


def render_clip(
    path: str | os.PathLike,
    vertices: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."]],
    faces: Int[ArrayLike, "..."] | Sequence[Int[ArrayLike, "..."]],
    *,
    audio: Float[ArrayLike, "..."] | None = None,
    sample_rate: int = AUDIO_SAMPLE_RATE,
    fps: Real = MOTION_FPS,
    captions: Sequence[str] | None = None,
    camera: Camera | None = None,
    size: int | tuple[int, int] = 256,
    style: RenderStyle = RenderStyle(),
    vertex_colors: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."] | None] | None = None,
    rest_vertices: Float[ArrayLike, "..."] | Sequence[Float[ArrayLike, "..."] | None] | None = None,
) -> Path:
    """Render vertex sequences (one clip, or several side by side) to an mp4 or a GIF.

    Frames are rendered and encoded one at a time, so a long clip needs little memory.

    Args:
        path: output file; ``.mp4`` (H.264, with ``audio`` as an AAC track) or ``.gif`` (no audio).
        vertices: one clip ``(T, V, 3)`` or a list of clips with the same ``T`` (see ``iter_frames``).
        faces: ``(F, 3)`` for all clips or one per clip.
        audio: optional samples for an mp4, trimmed/padded to the video (``video.fit_audio`` rule).
        sample_rate: audio sample rate in Hz.
        fps: frame rate (25 = the motion rate of jaxtalk).
        captions: one caption per clip.
        camera: shared view; default fitted to every frame of every clip.
        size: panel size when the camera is fitted, ``side`` or ``(width, height)``.
        style: colours, lights and anti-aliasing.
        vertex_colors: optional per-vertex albedo (see ``iter_frames``).
        rest_vertices: optional rest pose(s) to draw the open mouth as a cavity (see ``iter_frames``).

    Returns:
        The written path.

    Raises:
        ValueError: for another suffix, audio with a GIF, or anything ``iter_frames``/``write_mp4``
            reject (checked before encoding starts).
        FileNotFoundError, NotADirectoryError, PermissionError: if the directory cannot be written.
    """
    out = check_output_path(path, (".mp4", ".gif"))
    if out.suffix.lower() == ".gif" and audio is not None:
        raise ValueError(f"a GIF cannot carry audio; write an .mp4 instead of {str(out)!r}")
    frames = iter_frames(
        vertices, faces, camera=camera, size=size, captions=captions, style=style, vertex_colors=vertex_colors,
        rest_vertices=rest_vertices,
    )
    if out.suffix.lower() == ".gif":
        return write_gif(out, frames, fps=fps)
    if audio is not None:
        # Check the duration rule before spending time on rendering.
        num_frames = np.shape(vertices[0] if isinstance(vertices, (list, tuple)) else vertices)[0]
        check_audio_duration(audio, num_frames, fps=fps, sample_rate=sample_rate)
    return write_mp4(out, frames, fps=fps, audio=audio, sample_rate=sample_rate)
