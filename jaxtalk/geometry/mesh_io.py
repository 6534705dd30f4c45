"""Face files read as their authors wrote them: every vertex the file stores, once, in the file's order.

A vertex sequence that jaxtalk writes (``sample --mesh``'s animation, ``retarget --mesh``'s input) must line
up with the file the user has, so nothing here merges, splits or reorders vertices:

* OBJ (:func:`read_obj`): the ``v`` records, in order and count; ``f`` records index them (polygons
  triangulated as fans). Texture coordinates, normals, materials, objects and groups are ignored: a
  multi-material head with per-corner UVs keeps its vertex count. Read here rather than by trimesh, whose
  OBJ loader makes one mesh per ``usemtl`` block and a vertex per distinct (position, UV, normal) corner,
  whatever its options (``group_material``, ``split_objects``, ``maintain_order``): a 26,719-vertex face kit
  with 12 materials comes back with 257,701 vertices.
* PLY, OFF, STL: trimesh with ``process=False``; for PLY also ``fix_texture=False``, which keeps the
  ``vertex`` element as it is (by default trimesh splits vertices whose corners have different UVs).
  STL stores no shared vertices: three per triangle, as in the file.
* glTF / GLB (:func:`read_gltf`, :class:`GltfFile`): each triangle primitive's ``POSITION`` accessor,
  concatenated in node order then primitive order, node transforms applied (a skinned mesh's bind pose as
  stored). Primitives of one mesh that share a ``POSITION`` accessor (one vertex buffer, an index buffer
  per material, as exporters write them) share its vertices instead of repeating them. Buffers compressed
  with ``EXT_meshopt_compression`` / ``KHR_meshopt_compression`` are decoded (the ``meshopt`` package),
  Draco-compressed primitives (``KHR_draco_mesh_compression``) too (``DracoPy``), quantized attributes
  (``KHR_mesh_quantization``) are dequantized, and textures are never read: a KTX2 texture
  (``KHR_texture_basisu``) is passed over with a note (:class:`MeshFileNote`).
"""

from __future__ import annotations

import base64
import importlib
import os
import urllib.parse
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.types import Float, Int

__all__ = ["MESH_SUFFIXES", "read_accessor", "MeshFileNote", "GltfFile", "load_mesh", "read_obj", "read_gltf", "read_gltf_mesh",
           "node_world_matrices"]

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
_MESHOPT = ("EXT_meshopt_compression", "KHR_meshopt_compression")
_DRACO = "KHR_draco_mesh_compression"
# Texture formats that need a decoder of their own; jaxtalk reads no texture, so they are only noted.
_TEXTURE_EXTENSIONS = {"KHR_texture_basisu": "KTX2", "EXT_texture_webp": "WebP", "EXT_texture_avif": "AVIF"}
_TRIANGLES, _STRIP, _FAN = 4, 5, 6


class MeshFileNote(UserWarning):
    """Something in a face file that jaxtalk passes over (a KTX2 texture); the command line prints it as one
    ``note:`` line."""

    cli_prefix = "note"


def load_mesh(path: str | os.PathLike[str]) -> tuple[Float[np.ndarray, "verts 3"], Int[np.ndarray, "faces 3"]]:
    """Read a triangle mesh (OBJ, PLY, GLB/GLTF, OFF, STL) with the file's own vertices, in the file's order.

    Nothing is merged, split or reordered, so an output vertex sequence lines up with the file the user
    has: an OBJ's ``v`` records (whatever its materials, groups, texture coordinates and normals), a PLY's
    vertex element, a glTF's ``POSITION`` accessors (meshopt or Draco compression decoded, node transforms
    applied). Polygons are triangulated. (Also importable from :mod:`jaxtalk.geometry.canonical`.)

    Args:
        path: the mesh file.

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int64)`` as stored (the file's units).

    Raises:
        FileNotFoundError: no such file.
        ValueError: an unsupported suffix, an unreadable file, a point cloud or a mesh without triangles.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"mesh file not found: {str(p)!r}")
    suffix = p.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"{str(p)!r}: expected a mesh file ({', '.join(MESH_SUFFIXES)}), got {suffix or 'no suffix'!r}")
    if suffix == ".obj":
        vertices, faces = read_obj(p)
    elif suffix in (".glb", ".gltf"):
        vertices, faces = read_gltf_mesh(p)
    else:
        vertices, faces = _read_with_trimesh(p)
    if faces.shape[0] == 0:
        if vertices.shape[0] == 0:
            raise ValueError(f"{str(p)!r} holds no vertices: not a mesh")
        raise ValueError(f"{str(p)!r} is a point cloud ({vertices.shape[0]} points, no faces); "
                         "a mesh with triangles is needed")
    return vertices, faces


def _read_with_trimesh(p: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # local: importing trimesh is not free

    kwargs: dict[str, Any] = {"process": False}
    if p.suffix.lower() == ".ply":
        kwargs["fix_texture"] = False  # keep the vertex element; the default splits vertices at UV seams
    try:
        loaded = trimesh.load(p, **kwargs)
    except Exception as err:  # trimesh raises many types for a broken file
        raise ValueError(f"{str(p)!r} could not be read as a mesh: {err}") from None
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        if not meshes:
            kinds = sorted({type(g).__name__ for g in loaded.geometry.values()}) or ["nothing"]
            raise ValueError(f"{str(p)!r} holds no triangle mesh (found: {', '.join(kinds)})")
        loaded = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
    if isinstance(loaded, trimesh.PointCloud):
        return np.asarray(loaded.vertices, np.float64).reshape(-1, 3), np.zeros((0, 3), np.int64)
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(f"{str(p)!r} is a {type(loaded).__name__}, not a triangle mesh")
    return np.asarray(loaded.vertices, np.float64).reshape(-1, 3), np.asarray(loaded.faces, np.int64).reshape(-1, 3)


# ---- OBJ -------------------------------------------------------------------------------------------------
def _obj_index(token: str, count: int, lineno: int, p: Path) -> int:
    head = token.split("/", 1)[0]
    try:
        index = int(head)
    except ValueError:
        raise ValueError(f"{str(p)!r} line {lineno}: {token!r} is not a vertex index; an OBJ face lists vertex "
                         "numbers (1-based, or negative to count back)") from None
    if index == 0:
        raise ValueError(f"{str(p)!r} line {lineno}: vertex index 0; OBJ vertex numbers start at 1")
    return index - 1 if index > 0 else count + index


def read_obj(path: str | os.PathLike[str]) -> tuple[Float[np.ndarray, "verts 3"], Int[np.ndarray, "faces 3"]]:
    """An OBJ's ``v`` records in order and count, and its ``f`` records as triangles of them.

    Polygons become fans ``(0, i, i + 1)``, a quad ``(0, 1, 2), (0, 2, 3)``, in the file's face order. The
    texture and normal numbers of a corner (``f 1/4/2 ...``) are ignored, as are ``vt``, ``vn``, ``usemtl``,
    ``o``, ``g``, ``s``, lines and points; a fourth ``v`` value (``w``) or vertex colours are dropped.

    Args:
        path: the ``.obj`` file.

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int64)``; ``F`` is 0 for a file without faces.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a ``v`` with fewer than three numbers, a face with fewer than three corners, or a face
            index that is not a number or names no vertex (each with its line number).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"mesh file not found: {str(p)!r}")
    coords: list[str] = []
    polygons: list[tuple[int, list[int]]] = []
    count = 0
    pending, start = "", 0
    with open(p, encoding="utf-8", errors="replace") as fh:
        for lineno, raw in enumerate(fh, 1):
            line = raw.rstrip("\r\n")
            if line.endswith("\\"):  # a continued record: joined with the next line
                if not pending:
                    start = lineno
                pending += line[:-1] + " "
                continue
            if pending:
                line, pending = pending + line, ""
            else:
                start = lineno
            head = line.lstrip()[:1]
            if head != "v" and head != "f":  # only v and f records matter (vt and vn are told apart below)
                continue
            parts = line.split("#", 1)[0].split()
            if not parts:
                continue
            if parts[0] == "v":
                if len(parts) < 4:
                    raise ValueError(f"{str(p)!r} line {start}: a vertex needs x y z, got {line.strip()!r}")
                coords.extend(parts[1:4])
                count += 1
            elif parts[0] == "f":
                if len(parts) < 4:
                    raise ValueError(f"{str(p)!r} line {start}: a face needs at least three vertices, "
                                     f"got {line.strip()!r}")
                polygons.append((start, [_obj_index(t, count, start, p) for t in parts[1:]]))
    try:
        vertices = np.array(coords, np.float64).reshape(-1, 3)
    except ValueError as err:
        raise ValueError(f"{str(p)!r}: a vertex holds something that is not a number ({err})") from None
    triangles: list[list[int]] = []
    for lineno, poly in polygons:
        bad = [i for i in poly if not 0 <= i < count]
        if bad:
            which = f"names vertex {bad[0] + 1}" if bad[0] >= 0 else "counts back past the first vertex"
            raise ValueError(f"{str(p)!r} line {lineno}: a face {which} but the file has {count}")
        triangles.extend([poly[0], poly[i], poly[i + 1]] for i in range(1, len(poly) - 1))
    faces = np.array(triangles, np.int64).reshape(-1, 3)
    return vertices, faces


# ---- glTF ------------------------------------------------------------------------------------------------
def _node_matrix(node: Any) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    if node.matrix:
        return np.asarray(node.matrix, np.float64).reshape(4, 4).T  # stored column-major
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(np.asarray(node.rotation or [0.0, 0.0, 0.0, 1.0], np.float64)).as_matrix() @ np.diag(
        np.asarray(node.scale or [1.0, 1.0, 1.0], np.float64))
    m[:3, 3] = np.asarray(node.translation or [0.0, 0.0, 0.0], np.float64)
    return m


def node_world_matrices(gltf: Any) -> dict[int, Float[np.ndarray, "4 4"]]:
    """Each node's world matrix (``4 x 4``), for the nodes of the file's scenes (every root when it has none).

    Args:
        gltf: a parsed file (``pygltflib.GLTF2``).

    Returns:
        node index -> its transform composed from the root, in the order the scenes reach the nodes.
    """
    out: dict[int, np.ndarray] = {}

    def visit(node: int, parent: np.ndarray) -> None:
        if node in out:  # a malformed file whose nodes form a cycle
            return
        out[node] = parent @ _node_matrix(gltf.nodes[node])
        for child in gltf.nodes[node].children or []:
            visit(child, out[node])

    scenes = gltf.scenes or []
    roots = [n for s in scenes for n in (s.nodes or [])]
    if not roots:  # no scene: every node that is nobody's child
        children = {c for n in gltf.nodes for c in (n.children or [])}
        roots = [i for i in range(len(gltf.nodes)) if i not in children]
    for root in roots:
        visit(root, np.eye(4))
    return out


def _ext(obj: Any, name: str) -> dict | None:
    extensions = getattr(obj, "extensions", None) or {}
    found = extensions.get(name)
    return found if isinstance(found, dict) else None


# glTF's component types (its enum values: FLOAT, UNSIGNED_BYTE, UNSIGNED_SHORT, UNSIGNED_INT, BYTE,
# SHORT) and accessor types; pygltflib is imported only where a file is opened.
_COMPONENT_DTYPES = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5120: np.int8, 5122: np.int16}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _view_rows(blob: bytes, gltf: pygltflib.GLTF2, view_index: int, byte_offset: int, count: int,
               dtype: np.dtype, width: int) -> np.ndarray:
    view = gltf.bufferViews[view_index]
    start = (view.byteOffset or 0) + (byte_offset or 0)
    stride = view.byteStride or dtype.itemsize * width
    raw = np.frombuffer(blob, np.uint8, count=stride * (count - 1) + dtype.itemsize * width, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, (count, dtype.itemsize * width), (stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(count, width)


def read_accessor(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """Accessor ``index`` of a glTF whose one buffer is ``blob``, as ``(count, width)`` (``(count,)`` for
    scalars); a sparse accessor's substitutions applied (morph targets are often stored sparse).

    Raises:
        ValueError: a component type glTF does not allow.
    """
    acc = gltf.accessors[index]
    if acc.componentType not in _COMPONENT_DTYPES:
        raise ValueError(f"accessor {index} has an unknown component type {acc.componentType}")
    dtype = np.dtype(_COMPONENT_DTYPES[acc.componentType])
    width = _WIDTHS[acc.type]
    if acc.bufferView is None:
        out = np.zeros((acc.count, width), dtype)
    else:
        out = _view_rows(blob, gltf, acc.bufferView, acc.byteOffset, acc.count, dtype, width).copy()
    sparse = acc.sparse
    if sparse is not None and sparse.count:
        idx = sparse.indices
        rows = _view_rows(blob, gltf, idx.bufferView, idx.byteOffset, sparse.count,
                          np.dtype(_COMPONENT_DTYPES[idx.componentType]), 1)[:, 0].astype(np.int64)
        vals = sparse.values
        out[rows] = _view_rows(blob, gltf, vals.bufferView, vals.byteOffset, sparse.count, dtype, width)
    return out[:, 0] if width == 1 else out


class GltfFile:
    """A glTF 2.0 file (``.gltf`` or ``.glb``) whose buffers are joined into one blob, compressed data decoded.

    After opening, every accessor reads as plain data from :attr:`blob`: meshopt-compressed buffer views
    are decoded into it, and a Draco-compressed primitive's ``POSITION`` and index accessors point at its
    decoded data. :func:`read_accessor` reads them raw, :meth:`accessor` as numbers
    (a normalized integer accessor as floats).

    Attributes:
        path: the file.
        gltf: the parsed document (``pygltflib.GLTF2``), its buffer views and accessors rewritten to the blob.
        blob: every buffer's bytes, then the decoded data.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        import pygltflib

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"glTF file not found: {str(self.path)!r}")
        try:
            self.gltf = pygltflib.GLTF2().load(str(self.path))
        except Exception as err:  # pygltflib raises whatever its parser meets
            raise ValueError(f"{str(self.path)!r} is not a readable glTF file ({err})") from None
        if self.gltf is None:
            raise ValueError(f"{str(self.path)!r} is not a readable glTF file")
        self._parts: list[bytes] = []
        self._size = 0
        bases = [self._append(self._buffer_bytes(i, b)) for i, b in enumerate(self.gltf.buffers)]
        for view in self.gltf.bufferViews:
            if view.buffer is not None and 0 <= view.buffer < len(bases):
                view.byteOffset = bases[view.buffer] + (view.byteOffset or 0)
                view.buffer = 0
        self._decode_meshopt(bases)
        self._decode_draco()
        self.blob = b"".join(self._parts)
        self._note_textures()

    # -- buffers
    def _where(self) -> str:
        return repr(str(self.path))

    def _append(self, data: bytes) -> int:
        pad = -self._size % 4  # keep every part 4-byte aligned, as glTF's own offsets are
        if pad:
            self._parts.append(b"\0" * pad)
            self._size += pad
        base = self._size
        self._parts.append(data)
        self._size += len(data)
        return base

    def _buffer_bytes(self, index: int, buffer: Any) -> bytes:
        uri = buffer.uri
        if uri is None:
            if index == 0 and self.path.suffix.lower() == ".glb":
                return self.gltf.binary_blob() or b""
            # A meshopt fallback buffer holds nothing: its views are all decoded from the compressed one.
            return b""
        if uri.startswith("data:"):
            try:
                return base64.b64decode(uri.split(",", 1)[1])
            except Exception as err:  # binascii.Error or a missing comma
                raise ValueError(f"{self._where()}: buffer {index}'s embedded data is not base64 ({err})") from None
        target = self.path.parent / urllib.parse.unquote(uri)
        if not target.is_file():
            raise FileNotFoundError(f"{self._where()} refers to buffer {uri!r}, which is not beside it "
                                    f"({str(target)!r}): keep the .bin files next to the .gltf")
        return target.read_bytes()

    def _decoder(self, module: str, compression: str, otherwise: str) -> Any:
        try:  # a main dependency, so missing only from an environment put together by hand
            return importlib.import_module(module)
        except ImportError:
            raise ValueError(f"{self._where()} is {compression}-compressed and the {module} package is missing: "
                             f"pip install {module} ({otherwise})") from None

    def _decode_meshopt(self, bases: list[int]) -> None:
        views = [(i, v, name, ext) for i, v in enumerate(self.gltf.bufferViews) for name in _MESHOPT
                 if (ext := _ext(v, name)) is not None]
        if not views:
            return
        meshopt = self._decoder("meshopt", "meshopt", "or decompress it with `gltfpack -noq`")
        joined = b"".join(self._parts)
        for i, view, name, ext in views:
            buffer, offset = int(ext.get("buffer", 0)), int(ext.get("byteOffset", 0))
            length, stride, count = int(ext["byteLength"]), int(ext["byteStride"]), int(ext["count"])
            start = bases[buffer] + offset if 0 <= buffer < len(bases) else len(joined)
            if start + length > len(joined):
                raise ValueError(f"{self._where()}: meshopt buffer view {i} runs past the end of buffer {buffer}; "
                                 "the file is cut short or damaged: export it again")
            try:
                rows = meshopt.decode_gltf_buffer(joined[start:start + length], count, stride, ext["mode"],
                                                  ext.get("filter", "NONE"))
            except Exception as err:  # the decoder's ValueError or RuntimeError for corrupt data
                raise ValueError(f"{self._where()}: buffer view {i} could not be decoded ({name}: {err}); "
                                 "the file is damaged: export it again") from None
            data = np.ascontiguousarray(rows).tobytes()
            view.buffer, view.byteOffset, view.byteLength = 0, self._append(data), len(data)
            if ext["mode"] == "ATTRIBUTES":
                view.byteStride = view.byteStride or stride
            view.extensions = {k: v for k, v in (view.extensions or {}).items() if k != name}

    def _decode_draco(self) -> None:
        import pygltflib

        prims = [p for m in self.gltf.meshes for p in m.primitives if _ext(p, _DRACO) is not None]
        if not prims:
            return
        DracoPy = self._decoder("DracoPy", "Draco", "or save the file without Draco compression")  # noqa: N806
        joined = b"".join(self._parts)
        decoded: dict[int, Any] = {}
        done: set[int] = set()
        for prim in prims:
            ext = _ext(prim, _DRACO)
            view_index = int(ext["bufferView"])
            if view_index not in decoded:
                view = self.gltf.bufferViews[view_index]
                start = view.byteOffset or 0
                try:
                    decoded[view_index] = DracoPy.decode(joined[start:start + view.byteLength])
                except Exception as err:  # DracoPy raises its own types for corrupt data
                    raise ValueError(f"{self._where()}: a Draco-compressed primitive could not be decoded "
                                     f"({err}); the file is damaged: export it again") from None
            mesh = decoded[view_index]
            position = prim.attributes.POSITION
            if position is not None and position not in done:
                unique_id = (ext.get("attributes") or {}).get("POSITION")
                attr = mesh.get_attribute_by_unique_id(unique_id) if unique_id is not None else None
                points = np.asarray(attr["data"] if attr is not None else mesh.points, np.float32).reshape(-1, 3)
                self._point_accessor(position, points, pygltflib.FLOAT)
                done.add(position)
            if prim.indices is not None and prim.indices not in done:
                faces = np.asarray(mesh.faces, np.uint32).reshape(-1)
                self._point_accessor(prim.indices, faces, pygltflib.UNSIGNED_INT)
                done.add(prim.indices)
            prim.extensions = {k: v for k, v in (prim.extensions or {}).items() if k != _DRACO}

    def _point_accessor(self, index: int, data: np.ndarray, component: int) -> None:
        import pygltflib

        raw = np.ascontiguousarray(data).tobytes()
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=self._append(raw), byteLength=len(raw)))
        acc = self.gltf.accessors[index]
        acc.bufferView, acc.byteOffset, acc.componentType, acc.count = len(self.gltf.bufferViews) - 1, 0, component, len(data)
        acc.normalized, acc.sparse = False, None

    def _note_textures(self) -> None:
        used = set(self.gltf.extensionsUsed or []) | set(self.gltf.extensionsRequired or [])
        kinds = [kind for name, kind in _TEXTURE_EXTENSIONS.items() if name in used]
        if kinds:
            warnings.warn(MeshFileNote(f"{self._where()}: its {' and '.join(kinds)} textures are not read "
                                       "(jaxtalk reads only the geometry)"), stacklevel=3)

    # -- reading
    def accessor(self, index: int) -> np.ndarray:
        """Accessor ``index`` as numbers, ``(count, width)`` (``(count,)`` for scalars); a normalized integer
        accessor (``KHR_mesh_quantization``) as floats in ``[0, 1]`` or ``[-1, 1]``, as glTF defines them.

        Raises:
            ValueError: an index or component type the file does not have.
        """
        if not 0 <= index < len(self.gltf.accessors):
            raise ValueError(f"{self._where()}: accessor {index} does not exist ({len(self.gltf.accessors)} in the file)")
        try:
            out = read_accessor(self.gltf, self.blob, index)
        except ValueError as err:
            raise ValueError(f"{self._where()}: {err}") from None
        if self.gltf.accessors[index].normalized and out.dtype.kind in "iu":
            info = np.iinfo(out.dtype)
            out = out / float(info.max)
            if info.min < 0:
                out = np.maximum(out, -1.0)
        return out


def read_gltf(path: str | os.PathLike[str]) -> GltfFile:
    """Open a ``.gltf`` / ``.glb`` with its buffers joined and decoded (:class:`GltfFile`).

    Raises:
        FileNotFoundError: no such file, or a ``.gltf``'s ``.bin`` buffer not beside it.
        ValueError: a file that is not glTF, or compressed data that does not decode.
    """
    return GltfFile(path)


def _triangles(mode: int | None, idx: np.ndarray) -> np.ndarray | None:
    if mode in (None, _TRIANGLES):
        return idx[: idx.shape[0] - idx.shape[0] % 3].reshape(-1, 3)
    if mode == _STRIP and idx.shape[0] >= 3:
        k = np.arange(idx.shape[0] - 2)
        tri = np.stack([idx[k], idx[k + 1], idx[k + 2]], axis=1)
        odd = k % 2 == 1  # every other triangle of a strip is wound the other way
        tri[odd] = tri[odd][:, [1, 0, 2]]
        return tri
    if mode == _FAN and idx.shape[0] >= 3:
        k = np.arange(1, idx.shape[0] - 1)
        return np.stack([np.full_like(k, idx[0]), idx[k], idx[k + 1]], axis=1)
    return None  # points and lines: not a surface


def read_gltf_mesh(path: str | os.PathLike[str]) -> tuple[Float[np.ndarray, "verts 3"], Int[np.ndarray, "faces 3"]]:
    """A glTF's triangle meshes as one: each node's triangle primitives in node then primitive order,
    ``POSITION`` accessors concatenated (one that several primitives of a mesh share, once), transforms applied.

    A skinned mesh is read in its bind pose, as stored (glTF ignores a skinned mesh's node transform); a
    mesh used by two nodes appears twice, once per placement.

    Args:
        path: the ``.gltf`` / ``.glb`` file.

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int64)``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: an unreadable file, undecodable compressed data, or no triangle mesh in it.
    """
    doc = read_gltf(path)
    gltf = doc.gltf
    world = node_world_matrices(gltf)
    vertices: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    total = 0
    for node_index in sorted(world):
        node = gltf.nodes[node_index]
        if node.mesh is None:
            continue
        m = np.eye(4) if node.skin is not None else world[node_index]
        offsets: dict[int, tuple[int, int]] = {}  # POSITION accessor -> (offset, count) within this placement
        for prim in gltf.meshes[node.mesh].primitives:
            position = prim.attributes.POSITION
            if position is None:
                continue
            if position not in offsets:
                base = doc.accessor(position).astype(np.float64).reshape(-1, 3)
                count = base.shape[0]
            else:
                count = offsets[position][1]
            if prim.indices is not None:
                idx = doc.accessor(prim.indices).astype(np.int64).reshape(-1)
            else:
                idx = np.arange(count, dtype=np.int64)
            tri = _triangles(prim.mode, idx)
            if tri is None:
                continue
            if tri.size and (tri.min() < 0 or tri.max() >= count):
                raise ValueError(f"{doc._where()}: a primitive's indices reach vertex {int(tri.max())} of its {count}")
            if position not in offsets:
                offsets[position] = (total, count)
                vertices.append(base @ m[:3, :3].T + m[:3, 3])
                total += count
            faces.append(tri + offsets[position][0])
    if not vertices:
        raise ValueError(f"{doc._where()} holds no triangle mesh ({len(gltf.meshes)} meshes, none with triangles)")
    return np.concatenate(vertices), np.concatenate(faces).astype(np.int64)
