"""A fixed pinhole (or orthographic) camera that frames a set of points, and point projection.

Coordinates follow FLAME's frame: metres, x to the subject's left, y up, z out of the face. The camera
frame is OpenGL's: x right, y up, z towards the viewer, the camera at the origin looking down -z.
Pixel coordinates are continuous: pixel ``(row i, column j)`` covers ``[j, j+1) x [i, i+1)`` and its
centre is ``(j + 0.5, i + 0.5)``; rows grow downwards.

A clip is framed ONCE (``fit_camera`` on every frame's vertices, or on the template with a margin) so
that all its frames share one camera: a per-frame fit would zoom with the jaw and hide the motion.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaxtalk.types import Array, Float

# Python scalars: beartype (under pytest) does not promote int to float.
Real = int | float

__all__ = ["Camera", "fit_camera"]

ArrayLike = Array | np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A camera with a fixed pose and intrinsics.

    Attributes:
        rotation: world-to-camera rotation, ``(3, 3)``; its rows are the camera's right, up and back
            axes in world coordinates.
        target: world point the camera looks at (it lands at camera coordinates ``(0, 0, -distance)``).
        distance: camera-to-target distance in metres (> 0).
        focal: pixels per unit of ``x/depth`` (perspective) or pixels per metre (orthographic).
        principal: pixel coordinates ``(cx, cy)`` of the optical axis.
        width: image width in pixels.
        height: image height in pixels.
        orthographic: parallel projection instead of perspective.
    """

    rotation: np.ndarray
    target: np.ndarray
    distance: Real
    focal: Real
    principal: tuple[Real, Real]
    width: int
    height: int
    orthographic: bool = False

    def __post_init__(self) -> None:
        if np.shape(self.rotation) != (3, 3) or np.shape(self.target) != (3,):
            raise ValueError(
                f"rotation must be (3, 3) and target (3,), got {np.shape(self.rotation)} and {np.shape(self.target)}"
            )
        if not (self.distance > 0 and self.focal > 0):
            raise ValueError(f"distance and focal must be positive, got {self.distance} and {self.focal}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    def to_camera(self, points: Float[ArrayLike, "*batch 3"]) -> Float[np.ndarray, "*batch 3"]:
        """World points in camera coordinates (x right, y up, z towards the viewer; camera at 0).

        Args:
            points: world points, shape ``(..., 3)``.

        Returns:
            Camera-frame points, shape ``(..., 3)`` (float32).
        """
        p = np.asarray(points, np.float32) - self.target.astype(np.float32)
        q = p @ self.rotation.astype(np.float32).T
        q[..., 2] -= np.float32(self.distance)
        return q

    def project_camera(
        self, points_cam: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[np.ndarray, "*batch 2"], Float[np.ndarray, "*batch"]]:
        """Project camera-frame points to pixels.

        Args:
            points_cam: points in camera coordinates, shape ``(..., 3)``.

        Returns:
            ``(xy, depth)``: pixel coordinates ``(..., 2)`` and the distance in front of the camera
            along the view axis ``(...)`` (positive in front).
        """
        q = np.asarray(points_cam, np.float32)
        depth = -q[..., 2]
        if self.orthographic:
            sx, sy = q[..., 0], q[..., 1]
        else:
            # Points at or behind the camera get a dummy scale; the rasteriser drops them by depth.
            inv = np.float32(1.0) / np.where(depth > 0, depth, np.float32(1.0))
            sx, sy = q[..., 0] * inv, q[..., 1] * inv
        cx, cy = self.principal
        xy = np.stack([cx + self.focal * sx, cy - self.focal * sy], axis=-1).astype(np.float32)
        return xy, depth

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[np.ndarray, "*batch 2"], Float[np.ndarray, "*batch"]]:
        """Project world points to pixels (``to_camera`` then ``project_camera``).

        Args:
            points: world points, shape ``(..., 3)``.

        Returns:
            ``(xy, depth)`` as in ``project_camera``.
        """
        return self.project_camera(self.to_camera(points))


def _look_rotation(yaw_deg: Real, pitch_deg: Real) -> np.ndarray:
    """World-to-camera rotation of a camera orbiting the target by yaw (about y) and pitch (about x)."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    back = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    return np.stack([right, up, back])


def fit_camera(
    points: Float[ArrayLike, "..."],
    *,
    width: int = 256,
    height: int = 256,
    margin: Real = 0.08,
    fov_deg: Real = 15.0,
    orthographic: bool = False,
    yaw_deg: Real = 0.0,
    pitch_deg: Real = 0.0,
) -> Camera:
    """A camera in front of the points (light from the front, face towards +z) that frames all of them.

    The camera orbits the centre of the points' bounding box by ``yaw_deg`` (positive: towards the
    subject's left) and ``pitch_deg`` (positive: from above), sits far enough that the bounding sphere
    fits the field of view, and its focal length and principal point are then set so that the
    projected points span exactly ``1 - margin`` of the image in the tighter dimension, centred.

    Args:
        points: world points to frame, shape ``(..., 3)`` with any leading axes, e.g. a template
            ``(V, 3)`` or every frame of a clip ``(T, V, 3)`` (then all frames fit).
        width: image width in pixels.
        height: image height in pixels.
        margin: fraction of the image left empty around the points, in ``[0, 1)``.
        fov_deg: apex angle in degrees, in ``(0, 120)``, of the viewing cone that the points'
            bounding sphere fills: it sets the camera distance and so the strength of perspective
            (small values approach an orthographic look; 10-20 degrees is a portrait lens).
        orthographic: parallel projection (``fov_deg`` then only sets the camera distance).
        yaw_deg: orbit about the vertical axis in degrees.
        pitch_deg: orbit about the horizontal axis in degrees, in ``(-90, 90)``.

    Returns:
        The ``Camera``.

    Raises:
        ValueError: for points that are empty, not ``(..., 3)``, non-finite or all coincident, or for
            out-of-range sizes, margin, field of view or pitch.
    """
    pts = np.asarray(points, np.float64)
    if pts.ndim < 1 or pts.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {pts.shape}")
    pts = pts.reshape(-1, 3)
    if pts.shape[0] == 0:
        raise ValueError("points is empty: nothing to frame")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"points holds NaN or inf (first at row {int(np.argwhere(~np.isfinite(pts))[0, 0])})")
    for name, size in (("width", width), ("height", height)):
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
            raise ValueError(f"{name} must be a positive integer, got {size!r}")
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"margin must be in [0, 1), got {margin}")
    if not 0.0 < fov_deg < 120.0:
        raise ValueError(f"fov_deg must be in (0, 120), got {fov_deg}")
    if not -90.0 < pitch_deg < 90.0:
        raise ValueError(f"pitch_deg must be in (-90, 90), got {pitch_deg}")

    target = 0.5 * (pts.min(0) + pts.max(0))
    rotation = _look_rotation(yaw_deg, pitch_deg)
    q = (pts - target) @ rotation.T
    radius = float(np.sqrt((q**2).sum(-1).max()))
    if radius <= 1e-12:
        raise ValueError("points are all at one position: nothing to frame")
    # The bounding sphere inside the viewing cone: every point is then well in front of the camera.
    distance = radius / math.sin(math.radians(fov_deg) / 2.0)
    if orthographic:
        sx, sy = q[:, 0], q[:, 1]
    else:
        depth = distance - q[:, 2]
        sx, sy = q[:, 0] / depth, q[:, 1] / depth
    span_x, span_y = float(np.ptp(sx)), float(np.ptp(sy))
    spans = [s for s in ((span_x, width), (span_y, height)) if s[0] > 0]
    if not spans:
        raise ValueError("points all project to one pixel (they lie on the view axis): nothing to frame")
    focal = (1.0 - margin) * min(size / span for span, size in spans)
    # Principal point chosen so the projected bounding box is centred (perspective makes it
    # asymmetric about the optical axis when the points are not symmetric in depth).
    cx = width / 2.0 - focal * 0.5 * float(sx.max() + sx.min())
    cy = height / 2.0 + focal * 0.5 * float(sy.max() + sy.min())
    return Camera(
        rotation=rotation,
        target=target,
        distance=distance,
        focal=focal,
        principal=(cx, cy),
        width=int(width),
        height=int(height),
        orthographic=orthographic,
    )
