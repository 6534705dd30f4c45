"""Face meshes of the kinds people bring, with known semantic points, for the alignment tests
and ``experiments/canonical_alignment.py``.

Every builder returns a :class:`Shape`: vertices in metres in the built-in face's frame (+y up, +z out
of the face), triangles, and a few semantic points with the indices of the 68 iBUG landmarks they are
(nose tip 30, mouth corners 48 / 54, eye corners 36 / 39 / 42 / 45).

* :func:`mediapipe_face`: MediaPipe's canonical face (``jaxtalk/geometry/data``; a real mask of 468
  vertices, shipped in centimetres).
* :func:`procedural_head`: a whole head in the way of FLAME's template: a built-in face of another
  identity with the back of the skull, a neck and two ears, as separate components.
* :func:`bfm_mask`: a BFM-style mask cut from that head (:func:`cut_mask`, which cuts any head): in
  front of the ears, mid-forehead to under the chin, so part of the template's forehead has nothing
  under it and the cheeks reach past the template's rim.
* :func:`head_scan`: the head as a scan gives it: 1 mm noise on every vertex and holes.
* :func:`real_scan` / :func:`flame_template`: menpo3d's head scan (``experiments/fetch_real_scan.sh``)
  and FLAME's template when a user has it; None otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

# Where the fetch scripts (``experiments/fetch_*.sh``) put public face files: ``.cache/assets`` of the
# folder the suite or an experiment runs from (the repository root), or ``$JAXTALK_ASSETS``.
ASSETS = Path(os.environ.get("JAXTALK_ASSETS", Path.cwd() / ".cache" / "assets"))
REAL_SCAN = ASSETS / "james.obj"
# FLAME's template is not redistributable: a user who has it (e.g. DECA's data/head_template.obj and
# its landmark_embedding as .npz with full_faces / full_bary) puts it here.
FLAME_TEMPLATE = ASSETS / "flame_head_template.obj"
FLAME_LANDMARKS = ASSETS / "flame_landmarks.npz"
# The ICT Face Model's neutral head (``experiments/fetch_ict_face_kit.sh``) and its 68 Multi-PIE landmarks,
# as its README lists them (0-based vertex indices).
ICT_FACE_KIT = ASSETS / "ict_face_kit.obj"
ICT_LANDMARKS = (1225, 1888, 1052, 367, 1719, 1722, 2199, 1447, 966, 3661, 4390, 3927, 3924, 2608, 3272, 4088, 3443,
                 268, 493, 1914, 2044, 1401, 3615, 4240, 4114, 2734, 2509, 978, 4527, 4942, 4857, 1140, 2075, 1147,
                 4269, 3360, 1507, 1542, 1537, 1528, 1518, 1511, 3742, 3751, 3756, 3721, 3725, 3732, 5708, 5695, 2081,
                 0, 4275, 6200, 6213, 6346, 6461, 5518, 5957, 5841, 5702, 5711, 5533, 6216, 6207, 6470, 5517, 5966)

# iBUG-68 indices of the semantic points checked after alignment.
SEMANTIC = {"nose tip": 30, "mouth corner r": 48, "mouth corner l": 54, "eye outer r": 36, "eye inner r": 39,
            "eye inner l": 42, "eye outer l": 45}
# The same points in MediaPipe's face-landmark topology (its vertex indices; 4 is the pronasale, the
# nose's most prominent point, as iBUG's 30 is).
MEDIAPIPE_SEMANTIC = (4, 61, 291, 33, 133, 362, 263)


@dataclasses.dataclass(frozen=True)
class Shape:
    """A face mesh in metres and its semantic points.

    Attributes:
        name: what it is.
        vertices: ``(V, 3)`` metres.
        faces: ``(F, 3)``.
        points: ``(len(SEMANTIC), 3)`` metres, in :data:`SEMANTIC`'s order.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    points: np.ndarray


def template() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The template STM aligns to (the built-in face, identity 0, ``low``) and its semantic points."""
    from jaxtalk.face import builtin_face
    from jaxtalk.models.freetalk.data import neutral_landmarks

    face = builtin_face(0, resolution="low")
    landmarks = neutral_landmarks(face).astype(np.float64)
    return np.asarray(face.template, np.float64), np.asarray(face.faces, np.int64), landmarks[list(SEMANTIC.values())]


def template_landmarks() -> np.ndarray:
    """The template's 68 landmarks (metres), which let :func:`~jaxtalk.geometry.canonical.canonicalize`
    fit real faces through MediaPipe's face."""
    from jaxtalk.face import builtin_face
    from jaxtalk.models.freetalk.data import neutral_landmarks

    return neutral_landmarks(builtin_face(0, resolution="low")).astype(np.float64)


def mediapipe_face() -> Shape:
    """MediaPipe's canonical face as its OBJ file has it (``jaxtalk/geometry/data``), in metres."""
    from jaxtalk.geometry.canonical import MEDIAPIPE_FACE_FILE, load_mesh

    v, f = load_mesh(MEDIAPIPE_FACE_FILE)
    v = v * 0.01
    return Shape("MediaPipe canonical face", v, f, v[list(MEDIAPIPE_SEMANTIC)])


def procedural_head(identity: int = 2) -> Shape:
    """A built-in face (``default`` resolution) with the back of the skull, a neck and two ears, each
    its own component (metres)."""
    return _head(identity, f"built-in head (identity {identity}): face, skull, neck, ears")


def captured_head(identity: int = 2) -> Shape:
    """A whole head in the way of a captured ARKit head (three.js's ``facecap.glb``): a deep skull and a
    short neck tilted forward, so that the head's longest axis runs from the chin to the back of the skull
    (its principal axes point nowhere in particular), with eyeballs, teeth and lashes of their own
    (:func:`with_inner_parts`, eyes and mouth open)."""
    head = _head(identity, f"captured-style head (identity {identity}): deep skull, short tilted neck, ears",
                 skull=((0.08, 0.11, 0.12), (0.0, 0.03, -0.04)), neck=(0.05, 0.4))
    return with_inner_parts(head, holes=True, lashes=True)


def _head(identity: int, name: str, skull: tuple = ((0.08, 0.115, 0.1), (0.0, 0.015, -0.005)),
          neck: tuple = (0.128, 0.0)) -> Shape:
    """A built-in face with the back of a skull (half-axes, centre), a neck (height, forward tilt in
    radians, open at both ends) and two ears, each its own component (metres)."""
    import trimesh

    from jaxtalk.face import builtin_face
    from jaxtalk.models.freetalk.data import neutral_landmarks

    face = builtin_face(identity, resolution="default")
    parts = [trimesh.Trimesh(np.asarray(face.template, np.float64), np.asarray(face.faces), process=False)]
    back = trimesh.creation.icosphere(subdivisions=4)
    back.apply_scale(skull[0])
    back.apply_translation(skull[1])
    back.update_faces(back.triangles_center[:, 2] < 0.015)  # behind the face
    height, tilt = neck
    column = trimesh.creation.cylinder(radius=0.052, height=height, sections=48)  # open ends below
    column.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2 + tilt, [1, 0, 0]))
    column.apply_translation([0.0, -0.086 - height / 2, -0.03])
    column.update_faces(np.abs(column.face_normals @ [0.0, np.cos(tilt), np.sin(tilt)]) < 0.5)
    parts += [back, column]
    for side in (-1.0, 1.0):
        ear = trimesh.creation.icosphere(subdivisions=3)
        ear.apply_scale([0.012, 0.03, 0.018])
        ear.apply_translation([side * 0.082, 0.0, -0.012])
        parts.append(ear)
    head = trimesh.util.concatenate(parts)
    points = neutral_landmarks(face).astype(np.float64)[list(SEMANTIC.values())]
    return Shape(name, np.asarray(head.vertices, np.float64), np.asarray(head.faces, np.int64), points)


def cut_mask(shape: Shape) -> Shape:
    """A BFM-style mask cut from a head: in front of the ears, from mid-forehead to under the chin
    (measured in the template's frame, where the head's semantic points put it), so that part of the
    template's forehead has nothing under it and the cheeks reach past the template's rim."""
    from jaxtalk.geometry.canonical import umeyama

    scale, rotation, shift = umeyama(shape.points, template()[2], scale=True)
    centre = (scale * shape.vertices @ rotation.T + shift)[shape.faces].mean(axis=1)
    keep = (centre[:, 2] > -0.02) & (centre[:, 1] > -0.115) & (centre[:, 1] < 0.065)
    used, faces = np.unique(shape.faces[keep], return_inverse=True)
    return Shape(f"BFM-style mask cut from the {shape.name}", shape.vertices[used], faces.reshape(-1, 3), shape.points)


def bfm_mask(identity: int = 3) -> Shape:
    """:func:`cut_mask` of :func:`procedural_head`."""
    return cut_mask(procedural_head(identity))


def head_scan(identity: int = 1, seed: int = 0) -> Shape:
    """:func:`procedural_head` as a scanner gives it: 1 mm of noise on every vertex and 3% of the
    triangles missing (holes)."""
    head = procedural_head(identity)
    rng = np.random.default_rng(seed)
    v = head.vertices + rng.normal(scale=0.001, size=head.vertices.shape)
    f = head.faces[rng.random(len(head.faces)) > 0.03]
    return Shape(f"built-in head scan (identity {identity}): 1 mm noise, holes", v, f, head.points)


def real_scan() -> Shape | None:
    """menpo3d's ``james.obj`` (a textured head scan with neck and ears, millimetres, its own pose) and
    its landmarks, or None when ``experiments/fetch_real_scan.sh`` has not fetched it."""
    from jaxtalk.geometry.canonical import load_mesh

    if not (REAL_SCAN.is_file() and REAL_SCAN.with_suffix(".ljson").is_file()):
        return None
    v, f = load_mesh(REAL_SCAN)
    points = np.asarray(json.loads(REAL_SCAN.with_suffix(".ljson").read_text())["groups"]["LJSON"]["landmarks"]["points"])
    points = points[np.r_[0:17, 29:34, 43:48, 34:43, 17:23, 23:29, 48:68]]  # menpo's groups -> iBUG order
    return Shape("menpo3d james.obj head scan", v * 1e-3, f, points[list(SEMANTIC.values())] * 1e-3)


def flame_template() -> Shape | None:
    """FLAME's template head (5,023 vertices, metres, at a standing person's height) with its 68
    landmarks from the barycentric embedding, or None where the user has not put it there."""
    from jaxtalk.geometry.canonical import load_mesh

    if not (FLAME_TEMPLATE.is_file() and FLAME_LANDMARKS.is_file()):
        return None
    v, f = load_mesh(FLAME_TEMPLATE)
    emb = np.load(FLAME_LANDMARKS)
    landmarks = np.einsum("nk,nkd->nd", emb["full_bary"].reshape(-1, 3), v[f[emb["full_faces"].reshape(-1)]])
    return Shape("FLAME template head", v, f, landmarks[list(SEMANTIC.values())])


def ict_face_kit() -> Shape | None:
    """The ICT Face Model's neutral head as its kit ships it (26,719 vertices, centimetres, 12 materials: skin,
    neck, scleras, irises, lashes, teeth, gums and tongue...) with its own 68 landmarks, or None when
    ``experiments/fetch_ict_face_kit.sh`` has not fetched it."""
    from jaxtalk.geometry.canonical import load_mesh

    if not ICT_FACE_KIT.is_file():
        return None
    v, f = load_mesh(ICT_FACE_KIT)
    points = v[np.asarray(ICT_LANDMARKS)[list(SEMANTIC.values())]]
    return Shape("ICT Face Model kit (cm, eyes, lashes, teeth, gums)", v * 1e-2, f, points * 1e-2)


def posed(seed: int, *arrays: np.ndarray) -> list[np.ndarray]:
    """``arrays`` (positions, metres) under one random rotation and a shift of up to 1.5 m (a head in a
    room)."""
    from scipy.spatial.transform import Rotation

    rotation = Rotation.random(random_state=seed).as_matrix()
    shift = np.random.default_rng(seed).uniform(-1.5, 1.5, size=3)
    return [a @ rotation.T + shift for a in arrays]


def write_face_kit_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Write a face as an artist's kit writes it: ``o`` / ``g`` lines, three ``usemtl`` blocks that share
    vertices along their borders, a texture coordinate and a normal of its own at every corner (so that no
    two corners of a vertex agree), quads, and corners written ``v/vt/vn``, ``v//vn`` and, in the last
    block, ``-k/vt`` (counting back from the last vertex).

    Returns:
        The triangles a reader that keeps the ``v`` records must give, in file order: each quad as
        ``(a, b, c), (a, c, d)``.
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    count = vertices.shape[0]
    # Quads from pairs of neighbouring triangles: (a, b, c) and its neighbour across c->a, (a, c, d).
    by_edge = {(int(t[i]), int(t[(i + 1) % 3])): (k, i) for k, t in enumerate(faces) for i in range(3)}
    used, polygons = np.zeros(len(faces), bool), []
    for k, (a, b, c) in enumerate(faces.tolist()):
        if used[k]:
            continue
        used[k] = True
        other = by_edge.get((a, c))
        if k % 2 == 0 and other is not None and not used[other[0]]:
            n, i = other
            used[n] = True
            polygons.append([a, b, c, int(faces[n][(i + 2) % 3])])
        else:
            polygons.append([a, b, c])
    lines = ["# a face kit: skin, eyes and teeth share vertices", "mtllib kit.mtl", "o head"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    corners = sum(len(p) for p in polygons)
    rng = np.random.default_rng(0)
    lines += [f"vt {u:.6f} {w:.6f}" for u, w in rng.uniform(size=(corners, 2))]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in rng.normal(size=(corners, 3))]
    blocks = np.array_split(np.arange(len(polygons)), 3)
    block_vertices = [{v for p in block for v in polygons[p]} for block in blocks]
    assert block_vertices[0] & block_vertices[1] and block_vertices[1] & block_vertices[2], "blocks share no vertex"
    corner, expected = 0, []
    for block, (material, head) in zip(blocks, [("skin", ["g face"]), ("eyes", ["g eyes", "s 1"]),
                                                  ("teeth", ["o mouth", "g teeth"])]):
        lines += [*head, f"usemtl {material}"]
        for p in block:
            polygon = polygons[p]
            cells = []
            for v in polygon:
                corner += 1
                if material == "skin":
                    cells.append(f"{v + 1}/{corner}/{corner}")
                elif material == "eyes":
                    cells.append(f"{v + 1}//{corner}")
                else:
                    cells.append(f"{v - count}/{corner}")
            lines.append("f " + " ".join(cells))
            expected += [[polygon[0], polygon[i], polygon[i + 1]] for i in range(1, len(polygon) - 1)]
    path.write_text("\n".join(lines) + "\n")
    return np.array(expected, np.int64)


def with_inner_parts(shape: Shape, *, holes: bool = False, lashes: bool = False, parts: bool = True) -> Shape:
    """``shape`` as a face kit has it: two eyeballs (spheres of 12 mm radius whose fronts show 1 mm in front
    of the face's surface at the eyes, as an open eye's do), a row of teeth (a curved box 10 mm high and
    5 mm thick, 3 mm behind the lips) and, with ``lashes``, a thin sheet of lashes over each eye, each
    its own component after the face's vertices (which keep their indices). With ``holes`` the eyes
    and the mouth are cut open first (the eyeballs and teeth show through); ``parts=False`` gives that
    face alone. Built in the template's frame (where the semantic points put the face) and carried back
    into the shape's own."""
    import trimesh

    from jaxtalk.geometry.canonical import umeyama

    scale, rotation, shift = umeyama(shape.points, template()[2], scale=True)
    face = scale * shape.vertices @ rotation.T + shift  # template frame, metres
    _, mouth_r, mouth_l, eye_or, eye_ir, eye_il, eye_ol = scale * shape.points @ rotation.T + shift
    eyes = [((outer + inner) / 2, float(np.linalg.norm(outer - inner))) for outer, inner in
            ((eye_or, eye_ir), (eye_il, eye_ol))]
    middle, width = (mouth_r + mouth_l) / 2, float(np.linalg.norm(mouth_l - mouth_r))

    def front_at(x: float, y: float) -> float:
        """The face's depth (z) at (x, y): its front-most vertex within 4 mm across."""
        return float(face[np.linalg.norm(face[:, :2] - [x, y], axis=1) < 0.004, 2].max())

    kept = np.ones(len(shape.faces), bool)
    if holes:  # an ellipse over each eye, a slit between the lips
        centre = face[shape.faces].mean(axis=1)
        for c, w in eyes:
            kept &= ((centre[:, 0] - c[0]) / (0.4 * w)) ** 2 + ((centre[:, 1] - c[1]) / 0.005) ** 2 > 1
        kept &= ~((np.abs(centre[:, 1] - middle[1]) < 0.002) & (np.abs(centre[:, 0] - middle[0]) < 0.45 * width))
    added = []
    for c, w in eyes:
        eye = trimesh.creation.icosphere(subdivisions=3, radius=0.012)
        eye.apply_translation([c[0], c[1], front_at(*c[:2]) + 0.001 - 0.012])
        added.append(eye)
        if lashes:
            sheet = trimesh.creation.box([w, 0.0005, 0.008])
            sheet.apply_translation([c[0], c[1] + 0.005, front_at(*c[:2]) + 0.002])
            added.append(sheet)
    # The teeth: a box bent along an arc through the mouth corners, its front 3 mm behind the lips.
    radius, front = 0.6 * width, front_at(*middle[:2]) - 0.003
    teeth = trimesh.creation.box([1.0, 0.010, 0.005]).subdivide().subdivide().subdivide()
    u, y, d = teeth.vertices.T  # u in [-0.5, 0.5] along the row, d across its thickness
    angle = u * 2.0 * np.arcsin(min(1.0, 0.55 * width / radius))
    bend = radius - 0.0025 - d
    teeth.vertices = np.c_[middle[0] + bend * np.sin(angle), middle[1] + y, front - radius + bend * np.cos(angle)]
    added.append(teeth)
    extra = trimesh.util.concatenate(added) if parts else trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    placed = ((np.asarray(extra.vertices) - shift) @ rotation) / scale  # back into the shape's frame
    vertices = np.concatenate([shape.vertices, placed])
    faces = np.concatenate([shape.faces[kept], np.asarray(extra.faces, np.int64).reshape(-1, 3) + len(shape.vertices)])
    what = ("open eyes and mouth, " if holes else "") + ("eyeballs, teeth" + (", lashes" if lashes else "") if parts else "")
    return Shape(f"{shape.name} ({what.rstrip(', ') or 'as it is'})", vertices, faces, shape.points)
