"""Blendshape rigs: a neutral mesh plus named morph targets, read from a file or made in code.

* :class:`Rig`: names, neutral vertices, per-shape vertex offsets ``(K, V, 3)``, triangles, and where the
  head turns (a bone's name and pivot, when the rig has them).
* :func:`load_rig`: a glTF 2.0 file (``.glb`` / ``.gltf``, morph targets named in ``extras.targetNames``
  as Blender, three.js and Maya's exporters write them) or a folder of OBJ files (``neutral.obj`` and one
  OBJ per shape, named by the file).
* :func:`arkit_rig`: the built-in rig, ARKit's 52 shapes made in code on the built-in procedural face,
  so that examples and tests need no download.
* :func:`arkit_shape_name` and :func:`symmetric_pairs`: names as rigs spell them (``eyeBlink_L``,
  ``blendShape1.EyeBlinkLeft``, ``mouthSmileLeft``) matched to ARKit's, and left/right pairs found by name.
  A rig with two shapes on one ARKit name (``jawOpen`` and ``JAWOPEN``) is refused
  (:func:`check_arkit_names`): the fit would split that shape's weight between them.

"Left" and "Right" are the subject's own sides, as in ARKit; on the built-in face the subject's left is +x.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxtalk.export.arkit import ARKIT_NAMES
from jaxtalk.types import Float, Int

__all__ = ["Rig", "load_rig", "arkit_rig", "arkit_shape_name", "arkit_halves", "check_arkit_names", "symmetric_pairs",
           "side_of", "NEUTRAL_NAMES", "RIG_SUFFIXES"]

RIG_SUFFIXES = (".glb", ".gltf")
# Words that name the neutral of an OBJ folder: the whole file stem (lower case) or one of its words
# between _ - . or spaces, as kits name it (ICT-FaceKit's generic_neutral_mesh.obj).
NEUTRAL_NAMES = ("neutral", "base", "basis", "rest", "default")

_ARKIT_LOWER = {n.lower(): n for n in ARKIT_NAMES}
_SIDE = re.compile(r"^(?P<stem>.*?)(?:(?:[_.\- ](?P<letter>[LRlr]))|(?:[_.\- ]?(?P<word>[Ll]eft|[Rr]ight)))$")


def side_of(name: str) -> tuple[str, str | None]:
    """``(stem, "Left" | "Right" | None)`` of a shape name, without a namespace prefix.

    ``eyeBlink_L`` -> ``("eyeBlink", "Left")``, ``blendShape1.mouthSmileRight`` -> ``("mouthSmile", "Right")``,
    ``jawOpen`` -> ``("jawOpen", None)``.
    """
    base = re.split(r"[:|/]", name.strip())[-1]
    if "." in base:  # a namespace (blendShape2.eyeBlink_L), but keep Blender's side suffix (eyeBlink.L)
        parts = base.split(".")
        base = f"{parts[-2]}.{parts[-1]}" if parts[-1] in ("L", "R", "l", "r") and len(parts) > 1 else parts[-1]
    match = _SIDE.match(base)
    if match is None or not match.group("stem"):
        return base, None
    side = match.group("letter") or match.group("word")
    return match.group("stem"), "Left" if side[0] in "Ll" else "Right"


def arkit_shape_name(name: str) -> str | None:
    """ARKit's name (``eyeBlinkLeft``) for a rig's shape name, or None when it is not one of the 52.

    Matches whatever case, a namespace prefix (``blendShape2.``, ``head:``), and ``_L`` / ``.R`` /
    ``Left`` / ``_right`` side suffixes.
    """
    stem, side = side_of(name)
    return _ARKIT_LOWER.get((stem + (side or "")).lower())


def arkit_halves(names: Sequence[str]) -> dict[str, tuple[int, int]]:
    """ARKit's shapes of both sides at once (``browInnerUp``, ``cheekPuff``, ...) that a rig splits into a left
    and a right half (ICT-FaceKit's ``browInnerUp_L`` / ``browInnerUp_R``) and has no whole shape for.

    Returns:
        ARKit name -> ``(left, right)`` shape indices; ARKit's curve is the mean of the two halves' weights
        (both halves at ``w`` make the whole shape at ``w``).
    """
    whole = {arkit_shape_name(n) for n in names}
    sides: dict[str, dict[str, int]] = {}
    for i, name in enumerate(names):
        stem, side = side_of(name)
        arkit = _ARKIT_LOWER.get(stem.lower())
        if side is not None and arkit is not None and arkit not in whole:
            sides.setdefault(arkit, {}).setdefault(side, i)
    return {arkit: (s["Left"], s["Right"]) for arkit, s in sides.items() if len(s) == 2}


def symmetric_pairs(names: Sequence[str]) -> list[tuple[int, int]]:
    """``(left, right)`` index pairs of shapes whose names differ only in their side suffix."""
    by_stem: dict[tuple[str, str], int] = {}
    for i, name in enumerate(names):
        stem, side = side_of(name)
        if side is not None:
            by_stem.setdefault((stem.lower(), side), i)
    return [(i, by_stem[(stem, "Right")]) for (stem, side), i in by_stem.items()
            if side == "Left" and (stem, "Right") in by_stem]


def check_arkit_names(names: Sequence[str], labels: Sequence[str] | None = None) -> None:
    """Refuse two shapes that :func:`arkit_shape_name` maps to one ARKit shape (``jawOpen`` and ``JAWOPEN``).

    Both would fit the same motion, so the solver splits the weight between them (each near half of it)
    while Live Link Face, whose ``JawOpen`` is one curve, carries only one of them: a rig that means one
    shape twice is a mistake to fix in the rig, not something to guess around.

    Args:
        names: the shape names.
        labels: what to call each shape in the message (its file's name); default the names, quoted.

    Raises:
        ValueError: naming the first two shapes on one ARKit name.
    """
    labels = [repr(n) for n in names] if labels is None else list(labels)
    seen: dict[str, int] = {}
    for i, name in enumerate(names):
        arkit = arkit_shape_name(name)
        if arkit is None:
            continue
        if arkit in seen:
            raise ValueError(f"{labels[seen[arkit]]} and {labels[i]} are both ARKit's {arkit!r}: the fit would split "
                             "its weight between them; keep one of them (rename or remove the other)")
        seen[arkit] = i


@dataclasses.dataclass(frozen=True, eq=False)
class Rig:
    """A blendshape rig: ``vertices = neutral + sum_k w_k deltas[k]``, weights in ``[0, 1]``.

    Attributes:
        names: the ``K`` shape names as the rig spells them.
        neutral: ``(V, 3)`` rest vertices, in the rig's own units and frame (float64).
        deltas: ``(K, V, 3)`` each shape's offsets at weight 1.
        faces: ``(F, 3)`` triangles.
        head_pivot: ``(3,)`` the point the head turns about (the head bone's or the neck's), or None.
        head_bone: the name of the rig's bone that turns the head, or None.
        name: a label (the file's stem, or ``"arkit"`` for the built-in rig).
        units: the unit of the vertices when known (``"m"``), else None (detected from the size).
    """

    names: tuple[str, ...]
    neutral: Float[np.ndarray, "verts 3"]
    deltas: Float[np.ndarray, "k verts 3"]
    faces: Int[np.ndarray, "tris 3"]
    head_pivot: Float[np.ndarray, "3"] | None = None
    head_bone: str | None = None
    name: str = "rig"
    units: str | None = None

    def __post_init__(self) -> None:
        neutral = np.asarray(self.neutral, np.float64)
        deltas = np.asarray(self.deltas, np.float64)
        faces = np.asarray(self.faces, np.int64)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "neutral", neutral)
        object.__setattr__(self, "deltas", deltas)
        object.__setattr__(self, "faces", faces)
        if neutral.ndim != 2 or neutral.shape[1] != 3 or neutral.shape[0] < 3:
            raise ValueError(f"the rig's neutral must have shape (verts >= 3, 3), got {neutral.shape}")
        if deltas.ndim != 3 or deltas.shape[1:] != neutral.shape or deltas.shape[0] < 1:
            raise ValueError(f"the rig has no morph targets of its mesh's {neutral.shape[0]} vertices "
                             f"(deltas of shape {deltas.shape}): a blendshape rig needs at least one")
        if len(self.names) != deltas.shape[0]:
            raise ValueError(f"{len(self.names)} names for {deltas.shape[0]} morph targets")
        if len(set(self.names)) != len(self.names):
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise ValueError(f"the rig names several morph targets {dup[0]!r}: shape names must be distinct")
        check_arkit_names(self.names)
        if not (np.all(np.isfinite(neutral)) and np.all(np.isfinite(deltas))):
            raise ValueError("the rig's vertices or morph targets hold NaN or inf")
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 1:
            raise ValueError(f"the rig's mesh needs triangles of shape (F, 3), got {faces.shape}")
        if faces.min() < 0 or faces.max() >= neutral.shape[0]:
            raise ValueError(f"the rig's triangles index vertices up to {faces.max()} of {neutral.shape[0]}")
        if self.head_pivot is not None:
            object.__setattr__(self, "head_pivot", np.asarray(self.head_pivot, np.float64).reshape(3))

    @property
    def num_shapes(self) -> int:
        """``K``."""
        return len(self.names)

    @property
    def num_vertices(self) -> int:
        """``V``."""
        return int(self.neutral.shape[0])

    @property
    def arkit(self) -> dict[str, int]:
        """ARKit name -> shape index, for the rig's shapes that are ARKit's (one each: see
        :func:`check_arkit_names`)."""
        out: dict[str, int] = {}
        for i, name in enumerate(self.names):
            arkit = arkit_shape_name(name)
            if arkit is not None:
                out[arkit] = i
        return out

    def pairs(self) -> list[tuple[int, int]]:
        """Left/right shape pairs found by name (:func:`symmetric_pairs`)."""
        return symmetric_pairs(self.names)

    def vertices(self, weights: Float[np.ndarray, "..."]) -> Float[np.ndarray, "frames verts 3"]:
        """The posed mesh of each frame's weights ``(T, K)``: ``neutral + weights @ deltas``."""
        w = np.asarray(weights, np.float64)
        if w.ndim != 2 or w.shape[1] != self.num_shapes:
            raise ValueError(f"weights must have shape (frames, {self.num_shapes}), got {w.shape}")
        return self.neutral + np.einsum("tk,kvc->tvc", w, self.deltas)

    def describe(self) -> str:
        """One line for a user."""
        arkit, pairs, halves = len(self.arkit), len(self.pairs()), sorted(arkit_halves(self.names))
        head = f", head bone {self.head_bone!r}" if self.head_bone else ""
        split = f", {', '.join(halves)} from left and right halves" if halves else ""
        return (f"rig {self.name!r}: {self.num_vertices} vertices, {self.faces.shape[0]} triangles, "
                f"{self.num_shapes} shapes ({arkit} ARKit-named{split}, {pairs} left/right pairs){head}")


# ---- loading ---------------------------------------------------------------------------------------
def load_rig(path: str | Path) -> Rig:
    """Read a blendshape rig: a ``.glb`` / ``.gltf`` with morph targets, or a folder of OBJ shapes.

    glTF: the mesh with morph targets and the most vertices is the face (a head file's eyes and teeth
    are separate meshes); its primitives are joined (those sharing a ``POSITION`` accessor share its
    vertices), the node's transform applied (a skinned mesh is read in its bind pose), the targets named
    by ``extras.targetNames`` (``target_k`` where unnamed). Meshopt- and Draco-compressed buffers are
    decoded and quantized attributes dequantized (:func:`jaxtalk.geometry.mesh_io.read_gltf`).
    A bone whose name holds ``head`` (else ``neck``) in the mesh's skin is the head bone, its rest
    position the head's pivot.

    OBJ folder: ``neutral.obj`` (or ``base`` / ``basis`` / ``rest`` / ``default``, alone or as a word of
    the name: ``generic_neutral_mesh.obj``) and one OBJ per shape,
    each with the neutral's vertices in the same order; a shape is named by its file's stem.

    Raises:
        FileNotFoundError: no such file or folder.
        ValueError: an unreadable file or compressed data that does not decode, a mesh without morph
            targets, an OBJ folder without
            a neutral or with shapes of another vertex count, two shapes (files or morph targets) on one
            ARKit name (:func:`check_arkit_names`).
    """
    path = Path(path)
    if path.is_dir():
        return _load_obj_folder(path)
    if not path.is_file():
        raise FileNotFoundError(f"rig not found: {str(path)!r}")
    if path.suffix.lower() not in RIG_SUFFIXES:
        raise ValueError(f"{str(path)!r}: a rig is a .glb / .gltf file with morph targets or a folder of OBJ "
                         f"shapes, got {path.suffix or 'no suffix'!r}")
    return _load_gltf(path)


def _target_position(target) -> int | None:
    return target.get("POSITION") if isinstance(target, dict) else getattr(target, "POSITION", None)


def _load_gltf(path: Path) -> Rig:
    import pygltflib

    from jaxtalk.geometry.mesh_io import node_world_matrices, read_gltf

    # Buffers joined, meshopt / Draco compression decoded, quantized attributes read as floats.
    doc = read_gltf(path)
    gltf = doc.gltf
    world = node_world_matrices(gltf)
    best = None
    for node_index, node in enumerate(gltf.nodes):
        if node.mesh is None:
            continue
        mesh = gltf.meshes[node.mesh]
        prims = [p for p in mesh.primitives if p.targets]
        if not prims:
            continue
        count = sum(gltf.accessors[a].count for a in {p.attributes.POSITION for p in prims})
        if best is None or count > best[0]:
            best = (count, node_index, prims)
    if best is None:
        raise ValueError(f"{str(path)!r} has no mesh with morph targets: a blendshape rig needs them "
                         f"({len(gltf.meshes)} meshes, none with targets)")
    _, node_index, prims = best
    node = gltf.nodes[node_index]
    mesh = gltf.meshes[node.mesh]
    num_targets = len(prims[0].targets)
    if any(len(p.targets) != num_targets for p in prims):
        raise ValueError(f"{str(path)!r}: the primitives of mesh {mesh.name!r} have different numbers of morph targets")
    names = list((mesh.extras or {}).get("targetNames") or (prims[0].extras or {}).get("targetNames") or [])
    if len(names) != num_targets:
        names = [f"target_{k}" for k in range(num_targets)]
    try:
        check_arkit_names(names)
    except ValueError as err:
        raise ValueError(f"{str(path)!r}: morph targets {err}") from None
    neutral_parts, delta_parts, face_parts, offset = [], [], [], 0
    # Primitives that share a POSITION accessor (one vertex buffer, an index buffer per material) share its
    # vertices: as load_mesh reads the file, each stored vertex once.
    offsets: dict[int, tuple[int, int]] = {}
    for prim in prims:
        if prim.mode not in (None, pygltflib.TRIANGLES):
            raise ValueError(f"{str(path)!r}: mesh {mesh.name!r} is not made of triangles (primitive mode {prim.mode})")
        if prim.attributes.POSITION not in offsets:
            base = doc.accessor(prim.attributes.POSITION).astype(np.float64)
            deltas = np.zeros((num_targets, *base.shape))
            for k, target in enumerate(prim.targets):
                position = _target_position(target)
                if position is not None:
                    deltas[k] = doc.accessor(position)
            offsets[prim.attributes.POSITION] = (offset, base.shape[0])
            neutral_parts.append(base)
            delta_parts.append(deltas)
            offset += base.shape[0]
        start, count = offsets[prim.attributes.POSITION]
        if prim.indices is not None:
            tri = doc.accessor(prim.indices).astype(np.int64).reshape(-1, 3)
        else:
            tri = np.arange(count - count % 3, dtype=np.int64).reshape(-1, 3)
        face_parts.append(tri + start)
    # A skinned mesh ignores its node's transform (glTF 2.0, 3.7.3.3): its bind pose is as stored.
    m = np.eye(4) if node.skin is not None else world.get(node_index, np.eye(4))
    neutral = np.concatenate(neutral_parts) @ m[:3, :3].T + m[:3, 3]
    deltas = np.concatenate(delta_parts, axis=1) @ m[:3, :3].T
    head_bone, pivot = None, None
    if node.skin is not None:
        joints = gltf.skins[node.skin].joints
        joint_names = [(j, (gltf.nodes[j].name or "")) for j in joints]
        for key in ("head", "neck"):
            found = [(j, n) for j, n in joint_names if key in n.lower() and "end" not in n.lower()]
            if found:
                head_bone = found[0][1]
                pivot = world.get(found[0][0], np.eye(4))[:3, 3]
                break
    return Rig(names=tuple(names), neutral=neutral, deltas=deltas, faces=np.concatenate(face_parts),
               head_pivot=pivot, head_bone=head_bone, name=path.stem)


def _load_obj_folder(folder: Path) -> Rig:
    from jaxtalk.geometry.canonical import load_mesh

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".obj" and p.is_file())
    neutral_files = [p for p in files if set(re.split(r"[_.\- ]+", p.stem.lower())) & set(NEUTRAL_NAMES)]
    if not neutral_files:
        raise ValueError(f"{str(folder)!r} holds no neutral shape: name it neutral.obj (found {len(files)} OBJ files)")
    if len(neutral_files) > 1:
        raise ValueError(f"{str(folder)!r} holds several neutral shapes ({', '.join(p.name for p in neutral_files)}): "
                         "keep one")
    neutral, faces = load_mesh(neutral_files[0])
    shapes = [p for p in files if p not in neutral_files]
    if not shapes:
        raise ValueError(f"{str(folder)!r} holds a neutral but no shapes: a blendshape rig needs at least one "
                         "more OBJ, named after its shape")
    try:  # before reading the shapes: the message names the two files
        check_arkit_names([p.stem for p in shapes], [p.name for p in shapes])
    except ValueError as err:
        raise ValueError(f"{str(folder)!r}: {err}") from None
    deltas = []
    for p in shapes:
        verts, _ = load_mesh(p)
        if verts.shape != neutral.shape:
            raise ValueError(f"{str(p)!r} has {verts.shape[0]} vertices but the neutral has {neutral.shape[0]}: "
                             "every shape must be the neutral's mesh, vertices in the same order")
        deltas.append(verts - neutral)
    return Rig(names=tuple(p.stem for p in shapes), neutral=neutral, deltas=np.stack(deltas), faces=faces,
               name=folder.name)


# ---- the built-in ARKit rig ---------------------------------------------------------------------------
# Jaw poses (axis-angle, radians) that the jaw shapes bake at weight 1: ARKit's jawOpen = 1 is a wide
# open mouth (0.3 rad drops the built-in face's lower lip by about 2.5 cm), a full jawLeft a visible slide.
_JAW_OPEN = 0.3
_JAW_SIDE = 0.08
_JAW_FORWARD_M = 0.004


def _arkit_fields(face, resolution: str) -> dict[str, np.ndarray]:
    """The 52 shapes' offsets (metres, ``(V, 3)``) on the built-in face at ``resolution``."""
    from jaxtalk.face.procedural import (
        EYE_HW,
        MOUTH_HW,
        U_EYE,
        V_CHIN,
        V_EYE,
        V_MOUTH,
        face_grid,
        surface_displacement,
    )
    from jaxtalk.layout import EXP_INDEX

    grid = face_grid(resolution)
    u, v = grid.u, grid.v
    zero = np.zeros_like(u)
    exp = np.asarray(face.exp_basis, np.float64)
    template = np.asarray(face.template, np.float64)

    def component(name: str, scale: float) -> np.ndarray:
        return scale * exp[:, :, EXP_INDEX[name]]

    def push(du=zero, dv=zero, dn=zero) -> np.ndarray:
        return surface_displacement(du, dv, dn, resolution=resolution)

    def jaw(pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray:
        params = np.zeros((1, 56), np.float32)
        params[0, 50:52] = (pitch, yaw)
        return np.asarray(face.vertices_seq(params), np.float64)[0] - template

    def gauss(cu, cv, su, sv):
        return np.exp(-(((u - cu) / su) ** 2) - ((v - cv) / sv) ** 2)

    def half(side: float) -> np.ndarray:  # the subject's left (side +1, x > 0) or right half, smoothly
        return 0.5 * (1.0 + np.tanh(side * u / 0.06))

    # The lips split sharply at the seam row, as the built-in face's own mouth components do.
    seam_width = 0.5 * float(grid.rows[grid.seam_row + 1] - grid.rows[grid.seam_row])
    seam = np.tanh((v - V_MOUTH) / seam_width)
    upper, lower = 0.5 * (1 + seam), 0.5 * (1 - seam)
    mouth_u = np.exp(-((u / MOUTH_HW) ** 4))
    upper_lip = mouth_u * np.exp(-(((v - V_MOUTH - 0.05) / 0.08) ** 2)) * upper
    lower_lip = mouth_u * np.exp(-(((v - V_MOUTH + 0.06) / 0.08) ** 2)) * lower
    upper_red = mouth_u * np.exp(-(((v - V_MOUTH - 0.02) / 0.04) ** 2)) * upper
    upper_high = mouth_u * np.exp(-(((v - V_MOUTH - 0.09) / 0.08) ** 2)) * upper
    lip_line = mouth_u * np.exp(-(((v - V_MOUTH) / 0.05) ** 2))
    mouth_area = np.exp(-((u / (1.4 * MOUTH_HW)) ** 4)) * np.exp(-(((v - V_MOUTH) / 0.14) ** 2))
    chin = gauss(0.0, V_CHIN + 0.1, 0.22, 0.12)
    jaw_weight = np.asarray(face.weights, np.float64)[:, face.jaw_joint]

    shapes: dict[str, np.ndarray] = {
        "jawOpen": jaw(pitch=_JAW_OPEN),
        # +y rotation takes the chin (in front of the joint) to +x; the jaw's bulge under the cheek it
        # moves towards keeps left and right from being exact opposites.
        "jawLeft": jaw(yaw=_JAW_SIDE) + push(dn=0.0015 * gauss(0.45, -0.7, 0.15, 0.15)),
        "jawRight": jaw(yaw=-_JAW_SIDE) + push(dn=0.0015 * gauss(-0.45, -0.7, 0.15, 0.15)),
        "jawForward": jaw_weight[:, None] * np.array([0.0, 0.0, _JAW_FORWARD_M]),
        "mouthClose": component("lip_close", 2.0),
        "mouthFunnel": component("lip_funnel", 2.0),
        "mouthPucker": component("lip_round", 2.0),
        # The whole mouth slides; the corner it slides towards deepens.
        "mouthLeft": push(du=0.04 * mouth_area, dn=-0.002 * mouth_area * half(1.0)),
        "mouthRight": push(du=-0.04 * mouth_area, dn=-0.002 * mouth_area * half(-1.0)),
        "mouthRollLower": component("lip_tuck", 2.0),
        # Rolling works at the red of the lip, a shrug lifts the skin above it too.
        "mouthRollUpper": push(dv=-0.008 * upper_red, dn=-0.003 * upper_red),
        "mouthShrugLower": push(dv=0.012 * lower_lip + 0.01 * chin, dn=0.002 * (lower_lip + chin)),
        "mouthShrugUpper": push(dv=0.006 * upper_high, dn=0.003 * upper_high),
        "browInnerUp": component("brow_inner_up_l", 1.2) + component("brow_inner_up_r", 1.2),
        "cheekPuff": component("cheek_puff_l", 2.0) + component("cheek_puff_r", 2.0),
        # No tongue on a face mask: the lower lip pushed out and down by it.
        "tongueOut": push(dv=-0.006 * lower_lip * gauss(0.0, V_MOUTH, 0.12, 1.0),
                          dn=0.005 * lower_lip * gauss(0.0, V_MOUTH, 0.12, 1.0)),
    }
    for side, word, tag in ((1.0, "Left", "l"), (-1.0, "Right", "r")):
        cu = side * U_EYE
        eye = gauss(cu, V_EYE, 0.9 * EYE_HW, 0.09)
        corner = gauss(side * MOUTH_HW, V_MOUTH, 0.08, 0.07)
        wide = gauss(side * MOUTH_HW, V_MOUTH, 0.12, 0.12)
        shapes.update({
            f"eyeBlink{word}": component(f"blink_{tag}", 1.0),
            f"eyeWide{word}": component(f"eye_wide_{tag}", 1.5),
            # The lids and the skin around the eye follow the gaze.
            # (the upper lid leads an upward look, the lower a downward one, the outer corner an outward one)
            f"eyeLookUp{word}": push(dv=0.012 * gauss(cu, V_EYE + 0.03, 0.9 * EYE_HW, 0.08)),
            f"eyeLookDown{word}": push(dv=-0.012 * gauss(cu, V_EYE - 0.03, 0.9 * EYE_HW, 0.08)),
            f"eyeLookIn{word}": push(du=-side * 0.012 * eye),  # towards the nose
            f"eyeLookOut{word}": push(du=side * 0.012 * gauss(cu + side * 0.04, V_EYE, 0.9 * EYE_HW, 0.09)),
            f"eyeSquint{word}": push(dv=0.012 * gauss(cu, V_EYE - 0.05, 0.9 * EYE_HW, 0.035)),
            f"mouthSmile{word}": push(du=side * 0.012 * corner, dv=0.03 * corner, dn=-0.001 * corner),
            f"mouthFrown{word}": push(du=side * 0.004 * corner, dv=-0.025 * corner),
            f"mouthDimple{word}": push(du=side * 0.015 * wide, dn=-0.003 * wide),
            f"mouthStretch{word}": push(du=side * 0.02 * wide, dv=-0.012 * wide),
            f"mouthPress{word}": push(dv=-0.008 * seam * lip_line * half(side), dn=-0.0015 * lip_line * half(side)),
            f"mouthLowerDown{word}": push(dv=-0.02 * lower_lip * half(side)),
            f"mouthUpperUp{word}": push(dv=0.02 * upper_lip * half(side)),
            f"browDown{word}": component(f"brow_down_{tag}", 1.5),
            f"browOuterUp{word}": component(f"brow_outer_up_{tag}", 1.5),
            f"cheekSquint{word}": component(f"cheek_raise_{tag}", 1.5),
            f"noseSneer{word}": component(f"nose_wrinkle_{tag}", 2.0),
        })
    return shapes


def arkit_rig(resolution: str = "default") -> Rig:
    """The built-in ARKit rig: the 52 shapes, by ARKit's names and in Live Link Face's order, made in code
    on the built-in procedural face (:func:`jaxtalk.face.builtin_face`, mean identity).

    Each shape is a localised displacement with its ARKit meaning: ``jawOpen`` is the face model's own
    jaw rotation (0.3 rad, a wide-open mouth), ``jawLeft`` / ``jawRight`` its sideways turn, the eye,
    brow, cheek and nose shapes its named expression components (``eyeBlinkLeft`` = 1 closes the lid),
    the one-sided mouth shapes fields of their own (``mouthSmileLeft`` lifts and pulls the subject's
    left corner, at x > 0). Left and right shapes mirror each other exactly. The head turns about the
    face model's neck joint.

    Args:
        resolution: the face's mesh density (``"low"``, ``"default"``, ``"high"``).

    Returns:
        A :class:`Rig` in metres, in the face model's frame (x: subject's left, y: up, z: out of the face).
    """
    from jaxtalk.face import builtin_face

    face = builtin_face(0, resolution=resolution)
    shapes = _arkit_fields(face, resolution)
    return Rig(names=ARKIT_NAMES, neutral=np.asarray(face.template, np.float64),
               deltas=np.stack([shapes[n] for n in ARKIT_NAMES]), faces=np.asarray(face.faces),
               head_pivot=np.asarray(face.joints, np.float64)[face.neck_joint], head_bone=None, name="arkit",
               units="m")
