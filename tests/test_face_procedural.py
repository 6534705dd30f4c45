"""The built-in procedural face: mesh validity, symmetry, regions, basis locality/scale/meaning, jaw."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.face import builtin_face
from jaxtalk.face.procedural import face_grid
from jaxtalk.geometry.topology import mesh_summary
from jaxtalk.layout import EXP_INDEX, EXP_NAMES

REQUIRED_REGIONS = ("lips", "upper_face", "mouth_upper", "mouth_lower", "eyes", "jaw")


@pytest.fixture(scope="module")
def face():
    return builtin_face()


@pytest.fixture(scope="module")
def basis(face):
    return np.asarray(face.exp_basis, np.float64)


def mirror_index(resolution: str = "default") -> np.ndarray:
    grid = face_grid(resolution)
    idx = np.arange(len(grid.u)).reshape(len(grid.rows), grid.num_cols)
    return idx[:, ::-1].ravel()


def test_mesh_is_a_manifold_disk_of_face_size(face):
    import trimesh

    template = np.asarray(face.template, np.float64)
    assert 2000 <= face.num_vertices <= 6000
    summary = mesh_summary(template, face.faces)
    assert summary["manifold"], summary
    assert summary["components"] == 1 and summary["boundary_loops"] == 1
    mesh = trimesh.Trimesh(template, face.faces, process=False)
    assert mesh.is_winding_consistent and len(mesh.split(only_watertight=False)) == 1
    # Outward normals face +z (the viewer) on average; metres like FLAME.
    assert mesh.face_normals[:, 2].mean() > 0.5
    height, width = np.ptp(template[:, 1]), np.ptp(template[:, 0])
    assert 0.17 < height < 0.23 and 0.11 < width < 0.17
    # The nose tip is the most forward point of the face's centre line.
    nose = template[face.regions["nose"]]
    assert nose[:, 2].max() == pytest.approx(template[:, 2].max())


@pytest.mark.parametrize("resolution, lo, hi", [("low", 500, 2000), ("high", 5000, 6000)])
def test_other_resolutions(resolution, lo, hi):
    model = builtin_face(resolution=resolution)
    assert lo <= model.num_vertices <= hi
    assert mesh_summary(np.asarray(model.template), model.faces)["manifold"]


def test_face_is_mirror_symmetric_and_left_right_components_mirror(face, basis):
    template = np.asarray(face.template, np.float64)
    m = mirror_index()
    flip = np.array([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(template[m] * flip, template, atol=1e-9)
    for name in EXP_NAMES:
        if name.endswith("_l"):
            right = basis[:, :, EXP_INDEX[name[:-2] + "_r"]]
            np.testing.assert_allclose(basis[m, :, EXP_INDEX[name]] * flip, right, atol=1e-9, err_msg=name)
    for name in ("lip_round", "lip_close", "mouth_corner_up"):  # symmetric components mirror themselves
        b = basis[:, :, EXP_INDEX[name]]
        np.testing.assert_allclose(b[m] * flip, b, atol=1e-9, err_msg=name)


def test_regions_exist_and_sit_where_they_should(face):
    template = np.asarray(face.template)
    for key in REQUIRED_REGIONS:
        assert key in face.regions and len(face.regions[key]) > 0
    lips_y = template[face.regions["lips"], 1].mean()
    eyes_y = template[face.regions["eyes"], 1].mean()
    assert template[face.regions["upper_face"], 1].min() > lips_y
    assert eyes_y > template[face.regions["nose"], 1].min() > lips_y
    upper, lower = template[face.regions["mouth_upper"]], template[face.regions["mouth_lower"]]
    assert upper.shape == lower.shape
    assert np.abs(upper[:, 0] - lower[:, 0]).max() < 5e-4  # paired points across the lips for MOD
    assert np.all(upper[:, 1] > lower[:, 1])
    assert np.all(np.isin(face.regions["mouth_upper"], face.regions["lips"]))


def _peak_mm(basis):
    return 1e3 * np.linalg.norm(basis, axis=1).max(axis=0)


def test_expression_units_move_skin_by_millimetres(basis):
    peak = _peak_mm(basis)
    for name, p in zip(EXP_NAMES, peak):
        if name.startswith("blink"):
            assert 5.0 < p < 12.0, (name, p)  # one unit = a full blink (the eye opening)
        else:
            assert 1.0 <= p <= 3.5, (name, p)


def _support_centroid(face, basis, name):
    disp = np.linalg.norm(basis[:, :, EXP_INDEX[name]], axis=1)
    strong = disp > 0.5 * disp.max()
    return np.asarray(face.template)[strong].mean(axis=0), strong


def test_named_components_are_localised_in_their_region(face, basis):
    template = np.asarray(face.template)
    region_of = {"lip_": "lips", "mouth_": "lips", "upper_lip": "lips", "lower_lip": "lips",
                 "blink_l": "eye_l", "blink_r": "eye_r", "eye_wide_l": "eye_l", "eye_wide_r": "eye_r"}
    for name in EXP_NAMES[:28]:
        disp = np.linalg.norm(basis[:, :, EXP_INDEX[name]], axis=1)
        # Local: under 5% of the peak beyond 5 cm from where the component acts strongly.
        strong = template[disp > 0.5 * disp.max()]
        dist = np.min(np.linalg.norm(template[:, None, :] - strong[None, :, :], axis=2), axis=1)
        far = dist > 0.05
        assert disp[far].max() < 0.05 * disp.max(), name
        for prefix, region in region_of.items():
            if name.startswith(prefix):
                idx = face.regions[region]
                assert disp[idx].max() == pytest.approx(disp.max()), (name, region)
        # Left components act on the subject's left (x > 0), right ones on x < 0.
        centroid, _ = _support_centroid(face, basis, name)
        if name.endswith("_l"):
            assert centroid[0] > 0.005, name
        if name.endswith("_r"):
            assert centroid[0] < -0.005, name


def test_residual_components_are_smooth_global_modes(face, basis):
    for name in EXP_NAMES[28:]:
        disp = np.linalg.norm(basis[:, :, EXP_INDEX[name]], axis=1)
        assert np.mean(disp > 0.1 * disp.max()) > 0.3, name


def _move(face, name, amount=1.0):
    p = np.zeros(56, np.float32)
    p[EXP_INDEX[name]] = amount
    return np.asarray(face.vertices(jnp.asarray(p))) - np.asarray(face.template)


def test_components_move_in_their_named_direction(face):
    template = np.asarray(face.template)
    lm0 = np.asarray(face.landmarks(jnp.zeros(56)))
    mouth_w = np.linalg.norm(lm0[48] - lm0[54])

    def landmarks_after(name, amount=1.0):
        p = np.zeros(56, np.float32)
        p[EXP_INDEX[name]] = amount
        return np.asarray(face.landmarks(jnp.asarray(p)))

    # Rounding narrows the mouth and pushes the lips forward; spreading widens it.
    rounded = landmarks_after("lip_round")
    assert np.linalg.norm(rounded[48] - rounded[54]) < mouth_w - 0.001
    assert rounded[51, 2] > lm0[51, 2] + 0.001
    spread = landmarks_after("lip_spread")
    assert np.linalg.norm(spread[48] - spread[54]) > mouth_w + 0.001
    # Smile corners go up, frown corners go down.
    assert landmarks_after("mouth_corner_up")[54, 1] > lm0[54, 1] + 0.001
    assert landmarks_after("mouth_corner_down")[48, 1] < lm0[48, 1] - 0.001
    # Inner brow raise lifts landmark 22 (left inner brow), not 21 (right inner brow).
    raised = landmarks_after("brow_inner_up_l")
    assert raised[22, 1] > lm0[22, 1] + 0.002 and abs(raised[21, 1] - lm0[21, 1]) < 2e-4
    assert landmarks_after("brow_down_r")[19, 1] < lm0[19, 1] - 0.001
    # Lip part opens the inner lips; lip close presses them together.
    gap0 = lm0[62, 1] - lm0[66, 1]
    parted, closed = landmarks_after("lip_part"), landmarks_after("lip_close")
    assert parted[62, 1] - parted[66, 1] > gap0 + 0.0005
    assert closed[62, 1] - closed[66, 1] < gap0
    # Cheek puff bulges the left cheek outward along its normal.
    puff = _move(face, "cheek_puff_l")
    cheek = np.argmax(np.linalg.norm(puff, axis=1))
    assert template[cheek, 0] > 0.02 and puff[cheek, 0] > 0 and puff[cheek, 2] > 0


def test_jaw_opening_opens_the_mouth(face):
    template = np.asarray(face.template)
    p = np.zeros(56, np.float32)
    p[50] = 0.3
    posed = np.asarray(face.vertices(jnp.asarray(p)))
    up, lo = face.regions["mouth_upper"], face.regions["mouth_lower"]
    mod_rest = np.linalg.norm(template[up] - template[lo], axis=1).mean()
    mod_open = np.linalg.norm(posed[up] - posed[lo], axis=1).mean()
    assert mod_open - mod_rest > 0.01  # > 1 cm more mouth opening
    drop = template[lo, 1] - posed[lo, 1]
    assert np.all((drop > 0.008) & (drop < 0.04))  # lower lip moves down ~1-4 cm
    np.testing.assert_allclose(posed[face.regions["upper_face"]], template[face.regions["upper_face"]], atol=1e-6)
    assert np.all(np.isin(lo, face.regions["jaw"])) and not np.any(np.isin(up, face.regions["jaw"]))


def test_identities_are_deterministic_shape_variations():
    mean = builtin_face(resolution="low")
    a, a2, b = (builtin_face(k, resolution="low") for k in (3, 3, 4))
    np.testing.assert_array_equal(np.asarray(a.template), np.asarray(a2.template))
    np.testing.assert_array_equal(a.faces, mean.faces)
    np.testing.assert_array_equal(np.asarray(a.exp_basis), np.asarray(mean.exp_basis))
    for other in (a, b):
        offset = np.linalg.norm(np.asarray(other.template) - np.asarray(mean.template), axis=1)
        assert 0.002 < offset.max() < 0.02  # millimetres to a couple of centimetres
        assert mesh_summary(np.asarray(other.template), other.faces)["manifold"]
    assert not np.allclose(np.asarray(a.template), np.asarray(b.template))
    np.testing.assert_array_equal(np.asarray(builtin_face(0, resolution="low").template), np.asarray(mean.template))


@pytest.mark.parametrize(
    "kwargs, match",
    [({"resolution": "huge"}, "unknown resolution 'huge'"), ({"identity": True}, "identity must be an integer")],
)
def test_bad_arguments_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        builtin_face(**kwargs)
