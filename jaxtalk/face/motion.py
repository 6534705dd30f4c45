"""Motion tracks on a face model: the face's own deformation and its 68 landmark displacements.

``prepare`` stores the landmark displacements of every clip for FreeTalk's ATS, and the models,
evaluation and experiments compute the same ones, so they live with the face model.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxtalk.types import MOTION_FPS, NECK_SLICE, PARAM_DIM, Float

__all__ = ["without_head_pose", "bucketed_motion", "landmark_motion"]

_BUCKET_FRAMES = 10 * MOTION_FPS


def without_head_pose(motion: Float[np.ndarray, "frames params"]) -> Float[np.ndarray, "frames params"]:
    """The motion with the neck rotation zeroed: the face's own deformation only.

    FreeTalk animates a face mesh from speech (EmoVOCA and VOCASET carry no head pose); SynthTalk's
    head sway is partly random and would otherwise dominate the landmark displacements.
    """
    m = np.array(motion, np.float32, copy=True)
    m[..., NECK_SLICE] = 0.0
    return m


def bucketed_motion(motion: Float[np.ndarray, "frames params"]) -> tuple[Any, int]:
    """``(rows, T)``: the neutral face (zero parameters) as row 0, then the ``T`` frames of ``motion``,
    padded to a whole bucket by repeating the last frame so tracks of many lengths share one
    compiled face program; displacements are rows ``1 .. T`` minus row 0.

    Raises:
        ValueError: motion not of shape ``(T > 0, 56)``.
    """
    m = np.asarray(motion, np.float32)
    if m.ndim != 2 or m.shape[1] != PARAM_DIM or m.shape[0] == 0:
        raise ValueError(f"motion must have shape (frames > 0, {PARAM_DIM}), got {m.shape}")
    n = m.shape[0]
    total = -(-(n + 1) // _BUCKET_FRAMES) * _BUCKET_FRAMES
    rows = np.concatenate([np.zeros((1, PARAM_DIM), np.float32), m, np.repeat(m[-1:], total - n - 1, axis=0)])
    return jnp.asarray(rows), n


def landmark_motion(face: Any, motion: Float[np.ndarray, "frames params"]) -> Float[np.ndarray, "frames 68 3"]:
    """Landmark displacements ``L_t - L_tpl`` of a motion track on a face (metres, float32).

    Raises:
        ValueError: motion not of shape ``(T > 0, 56)``.
    """
    rows, n = bucketed_motion(motion)
    lms = np.asarray(face.landmarks_seq(rows))
    return (lms[1 : n + 1] - lms[:1]).astype(np.float32)
