"""Headless rendering of face meshes and plots.

* ``fit_camera`` / ``Camera``: one fixed view per clip, framing every frame.
* ``render_frame``, ``iter_frames``, ``render_frames``: shaded RGB frames from a vectorised NumPy
  z-buffer rasteriser (no display, no OpenGL), several clips side by side with captions.
* ``write_mp4`` (with an audio track), ``write_gif``, ``save_png``, ``render_clip``: files, atomically.
* ``plot_sweep``, ``plot_sweep_lines``, ``plot_training_curves``: PNG plots on matplotlib's Agg canvas.

matplotlib, Pillow and imageio are imported only when a caption, plot or file is made.
"""

from __future__ import annotations

from jaxtalk.render.camera import Camera, fit_camera
from jaxtalk.render.clip import render_clip
from jaxtalk.render.frames import caption_strip, iter_frames, render_frame, render_frames
from jaxtalk.render.plots import pivot_sweep, plot_sweep, plot_sweep_lines, plot_training_curves, training_series
from jaxtalk.render.rasterize import Fragments, rasterize
from jaxtalk.render.shading import RenderStyle, cavity_weights, vertex_normals
from jaxtalk.render.video import MediaInfo, fit_audio, probe_media, save_png, write_gif, write_mp4

__all__ = [
    "Camera",
    "fit_camera",
    "Fragments",
    "rasterize",
    "RenderStyle",
    "vertex_normals",
    "cavity_weights",
    "render_frame",
    "iter_frames",
    "render_frames",
    "caption_strip",
    "write_mp4",
    "write_gif",
    "save_png",
    "fit_audio",
    "probe_media",
    "MediaInfo",
    "render_clip",
    "pivot_sweep",
    "plot_sweep",
    "plot_sweep_lines",
    "plot_training_curves",
    "training_series",
]
