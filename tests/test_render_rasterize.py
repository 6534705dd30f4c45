"""rasterize: against a brute-force per-pixel reference, exact barycentrics, coverage, edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.render import rasterize


def brute_force(xy, depth, faces, height, width, perspective):
    """Per pixel centre, per triangle: inside test and screen-linear depth key; nearest wins.

    Returns the face image and a mask of pixels whose answer is ambiguous (a centre within rounding
    of an edge, or two triangles at nearly the same depth there).
    """
    image = np.full((height, width), -1)
    ambiguous = np.zeros((height, width), bool)
    for i in range(height):
        for j in range(width):
            p = np.array([j + 0.5, i + 0.5])
            hits = []
            for f, (a, b, c) in enumerate(faces):
                m = np.column_stack([xy[b] - xy[a], xy[c] - xy[a]])
                l1, l2 = np.linalg.solve(m, p - xy[a])
                lam = np.array([1 - l1 - l2, l1, l2])
                if np.abs(lam).min() < 1e-4:
                    ambiguous[i, j] = True
                if lam.min() >= 0:
                    z = depth[[a, b, c]]
                    key = lam @ (1 / z) if perspective else -(lam @ z)
                    hits.append((key, f))
            if hits:
                hits.sort()
                image[i, j] = hits[-1][1]
                if len(hits) > 1 and abs(hits[-1][0] - hits[-2][0]) < 1e-5 * abs(hits[-1][0]):
                    ambiguous[i, j] = True
    return image, ambiguous


@pytest.mark.parametrize("perspective", [True, False])
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_brute_force(seed, perspective):
    rng = np.random.default_rng(seed)
    height, width = 20, 26
    num = 7
    xy = rng.uniform(-4, [width + 4, height + 4], size=(3 * num, 2))  # some poke outside the image
    depth = rng.uniform(1.0, 3.0, size=3 * num)  # overlapping triangles at various depths, some crossing
    faces = np.arange(3 * num).reshape(num, 3)
    faces[1::2] = faces[1::2, ::-1]  # both windings
    frags = rasterize(xy, depth, faces, height, width, perspective=perspective)
    want, ambiguous = brute_force(xy, depth, faces, height, width, perspective)
    got = frags.face_image()
    assert (want >= 0).sum() > 100  # the scene really covers the image
    np.testing.assert_array_equal(got[~ambiguous], want[~ambiguous])
    assert ambiguous.mean() < 0.1


def test_barycentrics_are_exact_and_perspective_correct():
    # One triangle in camera space, projected with a pinhole camera (focal f, principal c).
    f, c = 40.0, np.array([16.0, 12.0])
    cam_pts = np.array([[-0.3, -0.2, -1.0], [0.4, -0.25, -2.5], [0.05, 0.3, -1.6]])
    depth = -cam_pts[:, 2]
    xy = np.column_stack([c[0] + f * cam_pts[:, 0] / depth, c[1] - f * cam_pts[:, 1] / depth])
    frags = rasterize(xy, depth, np.array([[0, 1, 2]]), 24, 32, perspective=True)
    assert frags.pixel.size > 50
    np.testing.assert_allclose(frags.bary.sum(1), 1.0, atol=1e-5)
    assert frags.bary.min() > -1e-4
    # Perspective-correct weights interpolate the 3-D point on the triangle seen through the pixel:
    # it must project exactly onto that pixel's centre.
    point = frags.bary @ cam_pts
    rows, cols = np.divmod(frags.pixel, 32)
    proj = np.column_stack([c[0] + f * point[:, 0] / -point[:, 2], c[1] - f * point[:, 1] / -point[:, 2]])
    np.testing.assert_allclose(proj, np.column_stack([cols + 0.5, rows + 0.5]), atol=2e-3)
    # Screen-space (affine) weights would not: they miss by up to a pixel here.
    screen = rasterize(xy, depth, np.array([[0, 1, 2]]), 24, 32, perspective=False)
    np.testing.assert_allclose(screen.bary @ xy, np.column_stack([cols + 0.5, rows + 0.5]), atol=2e-3)
    assert np.abs(frags.bary - screen.bary).max() > 0.02


def test_coverage_equals_area_and_shared_edges_leave_no_cracks():
    # A 40x30 rectangle split into two triangles along its diagonal covers exactly 1200 pixel centres.
    xy = np.array([[5.0, 4.0], [45.0, 4.0], [45.0, 34.0], [5.0, 34.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    frags = rasterize(xy, np.ones(4), faces, 40, 50)
    image = frags.face_image()
    assert frags.pixel.size == 40 * 30
    assert np.all(image[4:34, 5:45] >= 0) and (image >= 0).sum() == 1200
    assert np.all(np.diff(frags.pixel) > 0)


def test_nearer_triangle_occludes_and_behind_camera_is_skipped():
    xy = np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0]] * 3)
    depth = np.array([2.0] * 3 + [1.0] * 3 + [-1.0] * 3)
    faces = np.arange(9).reshape(3, 3)
    image = rasterize(xy, depth, faces, 20, 20).face_image()
    assert set(np.unique(image)) == {-1, 1}


def test_degenerate_and_offscreen_give_empty_fragments():
    xy = np.array([[1.0, 1.0], [5.0, 5.0], [9.0, 9.0], [-50.0, -50.0], [-40.0, -50.0], [-50.0, -40.0]])
    frags = rasterize(xy, np.ones(6), np.array([[0, 1, 2], [3, 4, 5]]), 10, 10)
    assert frags.pixel.size == 0 and frags.bary.shape == (0, 3)
    assert np.all(frags.face_image() == -1)


def test_faces_out_of_range_raise():
    with pytest.raises(ValueError, match="faces index vertices"):
        rasterize(np.zeros((3, 2)), np.ones(3), np.array([[0, 1, 3]]), 4, 4)
