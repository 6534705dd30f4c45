"""fit_camera / Camera: framing, projection against hand-computed pinhole maths, orbit, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxtalk.render import Camera, fit_camera


def _points(seed: int = 0, n: int = 500) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # A face-sized blob, off the origin and asymmetric in depth (perspective makes framing non-trivial).
    return rng.normal(size=(n, 3)) * np.array([0.05, 0.08, 0.03]) + np.array([0.01, -0.02, 0.05])


@pytest.mark.parametrize("orthographic", [False, True])
@pytest.mark.parametrize("size", [(256, 256), (320, 200)])
def test_fit_frames_every_point_centred_with_margin(orthographic, size):
    pts = _points()
    width, height = size
    margin = 0.1
    cam = fit_camera(pts, width=width, height=height, margin=margin, orthographic=orthographic)
    xy, depth = cam.project(pts)
    assert np.all(depth > 0)
    lo, hi = xy.min(0), xy.max(0)
    assert np.all(lo > 0) and hi[0] < width and hi[1] < height
    # The tighter dimension spans exactly 1 - margin of the image, and the box is centred.
    fill = max((hi[0] - lo[0]) / width, (hi[1] - lo[1]) / height)
    np.testing.assert_allclose(fill, 1 - margin, rtol=1e-4)
    np.testing.assert_allclose((lo + hi) / 2, [width / 2, height / 2], atol=1e-2)


def test_fit_on_a_clip_frames_all_frames():
    clip = np.stack([_points(seed) for seed in range(4)])  # (T, V, 3)
    cam = fit_camera(clip, width=128, height=128)
    xy, _ = cam.project(clip)
    assert xy.shape == (4, 500, 2)
    assert xy.min() > 0 and xy.max() < 128


def test_projection_matches_pinhole_by_hand():
    cam = Camera(
        rotation=np.eye(3), target=np.array([0.0, 0.0, 0.0]), distance=2.0, focal=100.0,
        principal=(50.0, 40.0), width=100, height=80,
    )  # fmt: skip
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.1, 0.0], [0.2, 0.1, 1.0], [-0.3, 0.0, -1.0]])
    xy, depth = cam.project(pts)
    # Camera at z = +2 looking down -z: depth = 2 - z; x_pix = cx + f x / depth; y_pix = cy - f y / depth.
    want_depth = np.array([2.0, 2.0, 1.0, 3.0])
    want_xy = np.array([[50, 40], [60, 35], [70, 30], [40, 40]], float)
    np.testing.assert_allclose(depth, want_depth, rtol=1e-6)
    np.testing.assert_allclose(xy, want_xy, rtol=1e-5)
    ortho = Camera(np.eye(3), np.zeros(3), 2.0, 100.0, (50.0, 40.0), 100, 80, orthographic=True)
    xy_o, _ = ortho.project(pts)
    np.testing.assert_allclose(xy_o, [[50, 40], [70, 30], [70, 30], [20, 40]], rtol=1e-5)


def test_view_is_mirror_correct_and_yaw_orbits():
    # Seen from the front, the subject's left (+x) is on the image's right and up (+y) is up.
    cam = fit_camera(_points(), width=100, height=100)
    xy, _ = cam.project(np.array([[0.05, 0.0, 0.05], [-0.05, 0.0, 0.05], [0.0, 0.06, 0.05]]))
    assert xy[0, 0] > xy[1, 0] and xy[2, 1] < xy[1, 1]
    # Orbiting 90 degrees towards the subject's left: +x now points at the camera (nearer).
    side = fit_camera(_points(), width=100, height=100, yaw_deg=90.0)
    assert np.allclose(side.rotation[2], [1.0, 0.0, 0.0], atol=1e-12)
    _, depth = side.project(np.array([[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0]]))
    assert depth[0] < depth[1]
    # The rotation is orthonormal for any orbit.
    r = fit_camera(_points(), yaw_deg=30.0, pitch_deg=-20.0).rotation
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert math.isclose(np.linalg.det(r), 1.0, rel_tol=1e-12)


@pytest.mark.parametrize(
    ("points", "kwargs", "match"),
    [
        (np.zeros((0, 3)), {}, "empty"),
        (np.zeros((5, 2)), {}, r"\(\.\.\., 3\)"),
        (np.full((5, 3), np.nan), {}, "NaN"),
        (np.ones((5, 3)), {}, "one position"),
        (_points(), {"margin": 1.0}, "margin"),
        (_points(), {"width": 0}, "width"),
        (_points(), {"fov_deg": 0.0}, "fov_deg"),
        (_points(), {"pitch_deg": 90.0}, "pitch_deg"),
    ],
)
def test_fit_errors(points, kwargs, match):
    with pytest.raises(ValueError, match=match):
        fit_camera(points, **kwargs)
