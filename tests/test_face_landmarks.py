"""The 68 landmarks of the built-in face and the standard 68-point graph."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.face import LANDMARK_EDGES, LANDMARK_PARTS, builtin_face
from jaxtalk.layout import EXP_INDEX


@pytest.fixture(scope="module")
def face():
    return builtin_face(resolution="low")


@pytest.fixture(scope="module")
def rest(face):
    return np.asarray(face.landmarks(jnp.zeros(56)), np.float64)


def _pose(face, **values):
    p = np.zeros(56, np.float32)
    for name, value in values.items():
        p[50 if name == "jaw" else EXP_INDEX[name]] = value
    return np.asarray(face.landmarks(jnp.asarray(p)), np.float64)


def test_graph_is_the_standard_68_point_graph():
    edges = LANDMARK_EDGES
    assert edges.shape == (64, 2) and edges.dtype == np.int32
    assert np.all(edges[:, 0] < edges[:, 1]) and edges.max() == 67
    assert len({tuple(e) for e in edges.tolist()}) == len(edges)
    degree = np.bincount(edges.ravel(), minlength=68)
    # Closed loops: every eye and lip point has degree 2.
    for part in ("eye_r", "eye_l", "lips_outer", "lips_inner"):
        first, last, closed = LANDMARK_PARTS[part]
        assert closed and np.all(degree[first : last + 1] == 2), part
    # Open polylines: end points of degree 1 (the jaw ends at the ears).
    assert degree[0] == degree[16] == 1 and np.all(degree[1:16] == 2)
    assert degree[17] == degree[21] == degree[22] == degree[26] == 1
    assert degree[30] == 2 and degree[33] == 3  # nose tip joined to the nostril base
    expected = {(36, 41), (42, 47), (48, 59), (60, 67), (30, 33), (0, 1), (21, 22)} - {(21, 22)}
    assert expected <= {tuple(e) for e in edges.tolist()}
    assert (21, 22) not in {tuple(e) for e in edges.tolist()}  # the brows are separate parts


def test_68_points_lie_on_the_mesh(face, rest):
    import trimesh

    assert rest.shape == (68, 3)
    mesh = trimesh.Trimesh(np.asarray(face.template, np.float64), face.faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, rest)
    assert dist.max() < 1e-6
    np.testing.assert_allclose(face.landmark_bary.sum(axis=1), 1.0, atol=1e-6)
    assert np.all(np.asarray(face.landmark_bary) >= -1e-9)


def test_left_right_ordering_follows_ibug(rest):
    x = rest[:, 0]
    right_side = [*range(0, 8), *range(17, 22), *range(36, 42), 48, 49, 50, 58, 59, 60, 61, 67, 31, 32]
    left_side = [*range(9, 17), *range(22, 27), *range(42, 48), 52, 53, 54, 55, 56, 63, 64, 65, 34, 35]
    assert np.all(x[right_side] < -1e-3) and np.all(x[left_side] > 1e-3)
    np.testing.assert_allclose(x[[8, 27, 28, 29, 30, 33, 51, 57, 62, 66]], 0.0, atol=1e-6)
    # Along each part, x runs the iBUG way (jaw right-to-left, brows and eye corners outer/inner).
    assert np.all(np.diff(x[0:17]) > 0) and np.all(np.diff(x[17:27]) > 0)
    assert x[36] < x[39] < 0 < x[42] < x[45]
    # Vertical order: brows above eyes above the nose tip above the mouth above the chin.
    y = rest[:, 1]
    assert y[17:27].min() > y[36:48].max() > y[30] > y[48:68].max()
    assert y[48:68].min() > y[8] and y[51] > y[62] > y[66] > y[57]
    # The nose tip sticks out furthest.
    assert rest[30, 2] == pytest.approx(rest[:, 2].max())


def test_mouth_landmarks_follow_the_jaw(face, rest):
    opened = _pose(face, jaw=0.3)
    assert opened[66, 1] - opened[62, 1] < rest[66, 1] - rest[62, 1] - 0.008  # inner lips separate
    assert rest[57, 1] - opened[57, 1] > 0.01  # lower lip goes down more than 1 cm
    assert rest[8, 1] - opened[8, 1] > 0.01  # and so does the chin
    np.testing.assert_allclose(opened[17:48], rest[17:48], atol=1e-6)  # brows, nose, eyes stay


# The lids span only a few grid rows; the coarse "low" mesh interpolates the closure less exactly.
@pytest.mark.parametrize("resolution, closed_fraction", [("default", 0.2), ("low", 0.45)])
def test_eye_landmarks_close_with_blink(resolution, closed_fraction):
    face = builtin_face(resolution=resolution)
    rest = _pose(face)

    def opening(lm, upper, lower):
        return np.linalg.norm(lm[upper] - lm[lower], axis=1).mean()

    left, right = ([43, 44], [47, 46]), ([37, 38], [41, 40])
    blinked = _pose(face, blink_l=1.0)
    assert opening(rest, *left) > 0.005  # an open eye is several millimetres
    assert opening(blinked, *left) < closed_fraction * opening(rest, *left)
    assert opening(blinked, *right) == pytest.approx(opening(rest, *right), abs=1e-6)
    both = _pose(face, blink_l=1.0, blink_r=1.0)
    assert opening(both, *right) < closed_fraction * opening(rest, *right)


def test_landmarks_of_a_new_identity_keep_their_semantics():
    other = builtin_face(11, resolution="low")
    lm = np.asarray(other.landmarks(jnp.zeros(56)))
    assert np.all(lm[0:8, 0] < 0) and np.all(lm[9:17, 0] > 0) and lm[30, 2] == pytest.approx(lm[:, 2].max())
