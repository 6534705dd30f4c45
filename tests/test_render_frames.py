"""Shaded frames of the built-in face: the open mouth shows in the mouth region, determinism,
framing, side-by-side panels with captions, any topology, colours, and input errors."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.face import builtin_face
from jaxtalk.geometry.topology import make_variant
from jaxtalk.layout import JAW_OPEN_INDEX
from jaxtalk.render import RenderStyle, cavity_weights, fit_camera, iter_frames, render_frame, render_frames

SIZE = 128


@pytest.fixture(scope="module")
def face():
    return builtin_face(resolution="low")


@pytest.fixture(scope="module")
def clip(face):
    """Closed mouth, then the jaw open by 0.35 rad (index 50), then half open: (3, V, 3)."""
    params = np.zeros((3, 56), np.float32)
    params[1, JAW_OPEN_INDEX] = 0.35
    params[2, JAW_OPEN_INDEX] = 0.175
    return np.asarray(face.vertices_seq(params))


@pytest.fixture(scope="module")
def camera(clip):
    return fit_camera(clip, width=SIZE, height=SIZE)


def _window(camera, points, pad=2):
    xy, _ = camera.project(points)
    (c0, r0), (c1, r1) = np.floor(xy.min(0)).astype(int) - pad, np.ceil(xy.max(0)).astype(int) + pad
    return slice(max(r0, 0), r1), slice(max(c0, 0), c1)


def test_open_mouth_differs_in_the_mouth_not_the_upper_face(face, clip, camera):
    faces = np.asarray(face.faces)
    closed = render_frame(clip[0], faces, camera)
    opened = render_frame(clip[1], faces, camera)
    diff = np.abs(closed.astype(float) - opened.astype(float)).mean(-1)
    lips = face.regions["lips"]
    mouth = _window(camera, np.concatenate([clip[0][lips], clip[1][lips]]))
    upper = _window(camera, clip[0][face.regions["upper_face"]], pad=0)
    mouth_change, upper_change = diff[mouth].mean(), diff[upper].mean()
    assert mouth_change > 8.0  # grey levels: the lower lip and chin visibly move
    assert upper_change < 0.05 * mouth_change
    # The lower lip drops: rows below the closed mouth that were face now show other shading.
    assert (diff[mouth] > 20).mean() > 0.1


def test_rendering_is_deterministic_and_shaded(face, clip, camera):
    faces = np.asarray(face.faces)
    a = render_frame(clip[1], faces, camera)
    b = render_frame(clip[1], faces, camera)
    assert a.dtype == np.uint8 and a.shape == (SIZE, SIZE, 3)
    np.testing.assert_array_equal(a, b)
    style = RenderStyle()
    bg = np.round(255 * np.asarray(style.background)).astype(np.uint8)
    is_bg = np.all(a == bg, axis=-1)
    # The camera frames the whole face: the image border is all background, the centre is face.
    assert is_bg[0].all() and is_bg[-1].all() and is_bg[:, 0].all() and is_bg[:, -1].all()
    assert 0.3 < (~is_bg).mean() < 0.9 and not is_bg[SIZE // 2, SIZE // 2]
    # Shaded, not flat: the face pixels span a real range of brightness.
    luma = a[~is_bg].mean(-1)
    assert luma.max() - luma.min() > 60


def test_all_vertices_of_the_clip_project_inside_the_image(clip, camera):
    xy, depth = camera.project(clip)
    assert np.all(depth > 0)
    assert xy.min() > 0 and xy[..., 0].max() < SIZE and xy[..., 1].max() < SIZE


def test_side_by_side_panels_and_captions(face, clip, camera):
    faces = np.asarray(face.faces)
    single = render_frames(clip, faces, camera=camera)
    both = render_frames([clip, clip[::-1]], faces, camera=camera, captions=["truth", "prediction"])
    strip = both.shape[1] - SIZE
    assert single.shape == (3, SIZE, SIZE, 3)
    assert both.shape == (3, SIZE + strip, 2 * SIZE, 3) and strip > 0
    # Each panel is exactly the clip rendered alone (shared camera, panels independent).
    np.testing.assert_array_equal(both[:, strip:, :SIZE], single)
    np.testing.assert_array_equal(both[:, strip:, SIZE:], single[::-1])
    # Caption text is drawn (bright pixels on the dark strip), the same on every frame.
    assert (both[0, :strip].mean(-1) > 150).sum() > 20
    np.testing.assert_array_equal(both[0, :strip], both[2, :strip])


def test_default_camera_fits_the_clip(face, clip):
    frames = render_frames(clip, np.asarray(face.faces), size=(96, 80))
    assert frames.shape == (3, 80, 96, 3)
    assert len(list(iter_frames(clip, np.asarray(face.faces), size=64))) == 3


def test_any_topology_renders_the_same_surface(face, clip, camera):
    faces = np.asarray(face.faces)
    base = render_frame(clip[1], faces, camera).astype(float)
    shuffled = make_variant(np.asarray(face.template), faces, "shuffled", seed=3)
    moved = np.asarray(shuffled.transfer(clip[1:2]))[0]
    img = render_frame(moved, shuffled.faces, camera).astype(float)
    # Reordering vertices and faces changes nothing but exact depth ties on shared edges.
    assert (np.abs(img - base).max(-1) == 0).mean() > 0.98
    subdivided = make_variant(np.asarray(face.template), faces, "subdivided")
    moved = np.asarray(subdivided.transfer(clip[1:2]))[0]
    assert moved.shape[0] > 3 * face.num_vertices
    img = render_frame(moved, subdivided.faces, camera).astype(float)
    assert np.abs(img - base).mean() < 3.0


def test_style_options(face, clip, camera):
    faces = np.asarray(face.faces)
    plain = render_frame(clip[0], faces, camera)
    smooth = render_frame(clip[0], faces, camera, style=RenderStyle(supersample=2))
    assert smooth.shape == plain.shape
    assert np.abs(smooth.astype(float) - plain.astype(float)).mean() < 4.0
    red = np.tile([[0.9, 0.1, 0.1]], (face.num_vertices, 1))
    tinted = render_frame(clip[0], faces, camera, vertex_colors=red).astype(int)
    centre = tinted[SIZE // 2 - 5 : SIZE // 2 + 5, SIZE // 2 - 5 : SIZE // 2 + 5]
    assert np.all(centre[..., 0] > centre[..., 1] + 40)


def test_cavity_weights_by_hand():
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    posed = rest.copy()
    posed[3] = [2.0, 2.0, 0.0]  # second triangle: area 0.5 -> 1.5 (ratio 3); first unchanged
    w = cavity_weights(posed, rest, faces, 2.5)
    np.testing.assert_allclose(w, [0.0, (3.0 - 2.5) / 2.5], rtol=1e-6)
    posed[3] = [4.0, 4.0, 0.0]  # ratio 7 >= 2 * 2.5: fully cavity
    np.testing.assert_allclose(cavity_weights(posed, rest, faces, 2.5), [0.0, 1.0])


def test_rest_pose_draws_the_open_mouth_dark(face, clip, camera):
    faces, rest = np.asarray(face.faces), np.asarray(face.template)
    # At rest nothing is stretched: the image is unchanged.
    np.testing.assert_array_equal(
        render_frame(clip[0], faces, camera, rest_vertices=rest), render_frame(clip[0], faces, camera)
    )
    plain = render_frame(clip[1], faces, camera).astype(float)
    dark = render_frame(clip[1], faces, camera, rest_vertices=rest).astype(float)
    changed = np.abs(dark - plain).max(-1) > 0
    lips = face.regions["lips"]
    mouth = _window(camera, np.concatenate([clip[0][lips], clip[1][lips]]))
    assert changed[mouth].sum() > 30 and changed.sum() == changed[mouth].sum()  # only in the mouth
    assert dark[changed].mean() < plain[changed].mean() - 15  # darker there,
    assert (dark[mouth].mean(-1) < 80).sum() > 20  # with a core of cavity colour
    with pytest.raises(ValueError, match="rest_vertices"):
        render_frame(clip[1], faces, camera, rest_vertices=rest[:-1])


def test_bad_inputs_raise_clear_errors(face, clip, camera):
    faces = np.asarray(face.faces)
    nan = clip.copy()
    nan[2, 5, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or inf .*frame 2"):
        render_frames(nan, faces, camera=camera)
    with pytest.raises(ValueError, match="zero frames"):
        render_frames(clip[:0], faces, camera=camera)
    with pytest.raises(ValueError, match="mismatched faces"):
        render_frame(clip[0][:-10], faces, camera)
    with pytest.raises(ValueError, match="same number of frames"):
        render_frames([clip, clip[:2]], faces, camera=camera)
    with pytest.raises(ValueError, match="captions"):
        render_frames([clip, clip], faces, camera=camera, captions=["one"])
    with pytest.raises(ValueError, match="vertex_colors"):
        render_frame(clip[0], faces, camera, vertex_colors=np.ones((3, 3)))
    with pytest.raises(ValueError, match="empty list"):
        render_frames([], faces, camera=camera)
    with pytest.raises(ValueError, match="supersample"):
        RenderStyle(supersample=0)
