"""Face files read with the file's own vertices (``jaxtalk.geometry.mesh_io``, ``load_mesh``, ``load_rig``).

An OBJ kit with materials, groups, per-corner UVs and normals keeps its ``v`` records; a PLY with per-corner
UVs keeps its vertex element; glTF primitives that share a vertex buffer read it once; meshopt- and
Draco-compressed glTFs read as their uncompressed sources (a rig's morph targets too); quantized positions
are dequantized; a KTX2 texture is passed over with a note. The glTFs are built here with pygltflib and
compressed with the same packages jaxtalk decodes with (``meshopt``, ``DracoPy``).
"""

from __future__ import annotations

import json

import numpy as np
import pygltflib
import pytest

from jaxtalk.testing.faces import write_face_kit_obj
from test_export_browser import node_tools  # noqa: F401  (a fixture: tests/js's npm tools, gltfpack among them)
from jaxtalk.geometry.canonical import load_mesh
from jaxtalk.geometry.mesh_io import MeshFileNote, read_obj


def _face(scale: float = 1000.0):
    from jaxtalk.face import builtin_face

    face = builtin_face(3, resolution="low")
    return scale * np.asarray(face.template, np.float64), np.asarray(face.faces, np.int64)


# ---- OBJ / PLY ------------------------------------------------------------------------------------------
def test_an_obj_kit_keeps_its_v_records_in_order_and_count(tmp_path):
    vertices, faces = _face()
    path = tmp_path / "kit.obj"
    expected = write_face_kit_obj(path, vertices, faces)
    v_lines = np.array([line.split()[1:4] for line in path.read_text().splitlines() if line.startswith("v ")], float)
    got_v, got_f = load_mesh(path)
    assert got_v.shape == v_lines.shape == vertices.shape
    np.testing.assert_array_equal(got_v, v_lines)
    np.testing.assert_array_equal(got_f, expected)
    # The same surface as the source: every source triangle is there, quads split along their diagonal.
    assert {tuple(sorted(t)) for t in got_f.tolist()} == {tuple(sorted(t)) for t in faces.tolist()}


def test_obj_records_are_read_as_written(tmp_path):
    path = tmp_path / "bits.obj"
    path.write_text("# comment\nv 0 0 0 1\nv 1 0 0 0.5 0.5 0.5\n  v 1 1 0\nv 0 1 0\nvt 0 0\nl 1 2\nf 1 2 \\\n 3 4\n"
                    "p 1\nf -1 -3 -2 # a comment\n")
    vertices, faces = read_obj(path)
    np.testing.assert_array_equal(vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 2, 3], [3, 1, 2]])


@pytest.mark.parametrize(("text", "message"), [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "line 4: a face names vertex 4 but the file has 3"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "line 4: vertex index 0"),
    ("v 0 0 0\nv 1 0 0\nf 1 2\n", "line 3: a face needs at least three vertices"),
    ("v 0 0\n", "line 1: a vertex needs x y z"),
    ("v 0 0 0\nf a b c\n", "line 2: 'a' is not a vertex index"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "is a point cloud"),
    ("# nothing\n", "holds no vertices"),
])
def test_obj_errors_name_the_line_and_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_mesh(path)


def test_a_ply_with_per_corner_uvs_keeps_its_vertex_element(tmp_path):
    vertices, faces = _face()
    rng = np.random.default_rng(0)
    header = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
              "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices",
              "property list uchar float texcoord", "end_header"]
    rows = [f"{x:.4f} {y:.4f} {z:.4f}" for x, y, z in vertices.tolist()]
    rows += ["3 %d %d %d 6 " % tuple(f) + " ".join(f"{u:.3f}" for u in rng.uniform(size=6)) for f in faces.tolist()]
    path = tmp_path / "face.ply"
    path.write_text("\n".join(header + rows) + "\n")
    got_v, got_f = load_mesh(path)
    np.testing.assert_allclose(got_v, vertices, atol=1e-4)
    np.testing.assert_array_equal(got_f, faces)


# ---- glTF -----------------------------------------------------------------------------------------------
class _Doc:
    """A glTF document and its one buffer, built a view at a time."""

    _COMPONENTS = {np.dtype(np.float32): pygltflib.FLOAT, np.dtype(np.uint16): pygltflib.UNSIGNED_SHORT,
                   np.dtype(np.uint32): pygltflib.UNSIGNED_INT, np.dtype(np.int16): pygltflib.SHORT}

    def __init__(self) -> None:
        self.gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0"), scenes=[pygltflib.Scene(nodes=[])], scene=0)
        self.blob = bytearray()

    def view(self, data: bytes) -> int:
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data)))
        self.blob += data
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, *, normalized: bool = False) -> int:
        array = np.ascontiguousarray(array)
        kind = {1: pygltflib.SCALAR, 3: pygltflib.VEC3}[1 if array.ndim == 1 else array.shape[1]]
        self.gltf.accessors.append(pygltflib.Accessor(
            bufferView=self.view(array.tobytes()), componentType=self._COMPONENTS[array.dtype], count=len(array),
            type=kind, normalized=normalized or None,
            min=array.reshape(len(array), -1).min(0).tolist(), max=array.reshape(len(array), -1).max(0).tolist()))
        return len(self.gltf.accessors) - 1

    def mesh(self, primitives: list[pygltflib.Primitive], **node) -> int:
        self.gltf.meshes.append(pygltflib.Mesh(primitives=primitives))
        self.gltf.nodes.append(pygltflib.Node(mesh=len(self.gltf.meshes) - 1, **node))
        self.gltf.scenes[0].nodes.append(len(self.gltf.nodes) - 1)
        return len(self.gltf.nodes) - 1

    def save(self, path, blob: bytes | None = None) -> None:
        blob = bytes(self.blob if blob is None else blob)
        blob += b"\0" * (-len(blob) % 4)
        self.gltf.buffers = [pygltflib.Buffer(byteLength=len(blob)), *self.gltf.buffers[1:]]
        if path.suffix == ".gltf":  # the buffer beside it, as exporters write a .gltf
            (path.parent / f"{path.stem}.bin").write_bytes(blob)
            self.gltf.buffers[0].uri = f"{path.stem}.bin"
            path.write_text(self.gltf.gltf_to_json())
        else:
            self.gltf.set_binary_blob(blob)
            self.gltf.save_binary(str(path))


def _face_doc(vertices, faces, *, split: int = 3) -> _Doc:
    """The face as one mesh whose primitives (one per material) share one vertex buffer, moved by a node."""
    doc = _Doc()
    position = doc.accessor(vertices.astype(np.float32))
    prims = [pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=position),
                                 indices=doc.accessor(part.reshape(-1).astype(np.uint16)), material=k)
             for k, part in enumerate(np.array_split(faces, split))]
    doc.mesh(prims, translation=[10.0, 0.0, 0.0])
    return doc


def _corners_from_lowest(triangles: np.ndarray) -> np.ndarray:
    """Each triangle's corners turned to start at its lowest index (same winding): meshopt's index codec
    may turn a triangle's corners, so a decoded file's triangles equal the source's up to that turn."""
    triangles = np.asarray(triangles)
    first = np.argmin(triangles, axis=1)[:, None]
    return np.take_along_axis(triangles, (first + np.arange(3)) % 3, axis=1)


def _meshopt(doc: _Doc, *, exponential: set[int] = frozenset()) -> tuple[bytes, list[int]]:
    """Compress every buffer view the meshopt way (``EXT_meshopt_compression``): the encoded bytes in buffer 0,
    a fallback buffer 1 that holds nothing; the views in ``exponential`` (float rows) filtered first."""
    import meshopt

    index_views = {doc.gltf.accessors[p.indices].bufferView for m in doc.gltf.meshes for p in m.primitives
                   if p.indices is not None}
    compressed, fallback = bytearray(), 0
    for i, view in enumerate(doc.gltf.bufferViews):
        data = bytes(doc.blob[view.byteOffset:view.byteOffset + view.byteLength])
        acc = next(a for a in doc.gltf.accessors if a.bufferView == i)
        if i in index_views:
            indices = np.frombuffer(data, np.uint16 if acc.componentType == pygltflib.UNSIGNED_SHORT else np.uint32)
            encoded, mode, stride, filt = meshopt.encode_gltf_buffer(indices, "TRIANGLES"), "TRIANGLES", indices.itemsize, "NONE"
        else:
            stride = len(data) // acc.count
            rows = np.frombuffer(data, np.uint8).reshape(acc.count, stride)
            filt = "NONE"
            if i in exponential:
                rows, filt = meshopt.encode_filter_exp(rows.view(np.float32), 23, "Separate"), "EXPONENTIAL"
            encoded, mode = meshopt.encode_gltf_buffer(rows, "ATTRIBUTES"), "ATTRIBUTES"
        compressed += b"\0" * (-len(compressed) % 4)
        view.extensions = {"EXT_meshopt_compression": {
            "buffer": 0, "byteOffset": len(compressed), "byteLength": len(encoded), "byteStride": stride,
            "count": acc.count, "mode": mode, "filter": filt}}
        compressed += encoded
        fallback += -fallback % 4
        view.buffer, view.byteOffset, view.byteStride = 1, fallback, stride if mode == "ATTRIBUTES" else None
        fallback += view.byteLength
    doc.gltf.buffers = [pygltflib.Buffer(byteLength=0), pygltflib.Buffer(
        byteLength=fallback, extensions={"EXT_meshopt_compression": {"fallback": True}})]
    doc.gltf.extensionsUsed = doc.gltf.extensionsRequired = ["EXT_meshopt_compression"]
    return bytes(compressed), sorted(index_views)


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_gltf_primitives_sharing_one_vertex_buffer_read_it_once(tmp_path, suffix):
    vertices, faces = _face()
    _face_doc(vertices, faces).save(tmp_path / f"face{suffix}")
    got_v, got_f = load_mesh(tmp_path / f"face{suffix}")
    np.testing.assert_allclose(got_v, vertices + [10.0, 0.0, 0.0], atol=1e-3)  # float32 in the file
    np.testing.assert_array_equal(got_f, faces)


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_a_meshopt_compressed_gltf_reads_as_its_uncompressed_source(tmp_path, suffix):
    vertices, faces = _face()
    _face_doc(vertices, faces).save(tmp_path / f"plain{suffix}")
    doc = _face_doc(vertices, faces)
    compressed, _ = _meshopt(doc)
    doc.save(tmp_path / f"packed{suffix}", compressed)
    assert len(compressed) < 0.7 * len(_face_doc(vertices, faces).blob)
    plain, packed = load_mesh(tmp_path / f"plain{suffix}"), load_mesh(tmp_path / f"packed{suffix}")
    np.testing.assert_array_equal(packed[0], plain[0])
    np.testing.assert_array_equal(_corners_from_lowest(packed[1]), _corners_from_lowest(plain[1]))
    # A filtered view (the exponential filter gltfpack writes for floats) decodes through the filter.
    doc = _face_doc(vertices, faces)
    compressed, _ = _meshopt(doc, exponential={0})
    assert doc.gltf.bufferViews[0].extensions["EXT_meshopt_compression"]["filter"] == "EXPONENTIAL"
    doc.save(tmp_path / f"filtered{suffix}", compressed)
    filtered = load_mesh(tmp_path / f"filtered{suffix}")
    np.testing.assert_allclose(filtered[0], plain[0], rtol=0, atol=1e-6 * np.abs(plain[0]).max())
    np.testing.assert_array_equal(_corners_from_lowest(filtered[1]), _corners_from_lowest(plain[1]))


def test_a_meshopt_compressed_rig_reads_its_morph_targets(tmp_path):
    from jaxtalk.export import arkit_rig, export_rig_animation, load_rig

    rig = arkit_rig("low")
    export_rig_animation(rig, np.zeros((2, rig.num_shapes)), tmp_path / "rig.glb")
    gltf = pygltflib.GLTF2().load(str(tmp_path / "rig.glb"))
    doc = _Doc()
    doc.gltf, doc.blob = gltf, bytearray(gltf.binary_blob())
    compressed, _ = _meshopt(doc)
    doc.save(tmp_path / "packed.glb", compressed)
    assert "EXT_meshopt_compression" in json.dumps(pygltflib.GLTF2().load(str(tmp_path / "packed.glb")).extensionsRequired)
    plain, packed = load_rig(tmp_path / "rig.glb"), load_rig(tmp_path / "packed.glb")
    assert packed.names == plain.names == rig.names
    np.testing.assert_array_equal(packed.neutral, plain.neutral)
    np.testing.assert_array_equal(packed.deltas, plain.deltas)
    np.testing.assert_array_equal(_corners_from_lowest(packed.faces), _corners_from_lowest(plain.faces))
    np.testing.assert_allclose(packed.deltas, rig.deltas, atol=1e-6)


def test_a_draco_compressed_gltf_reads_its_decoded_vertices(tmp_path):
    import DracoPy

    vertices, faces = _face()
    encoded = DracoPy.encode(vertices.astype(np.float32), faces.astype(np.uint32), quantization_bits=16)
    decoded = DracoPy.decode(encoded)
    doc = _Doc()
    view = doc.view(encoded)
    doc.gltf.accessors += [
        pygltflib.Accessor(componentType=pygltflib.FLOAT, count=len(vertices), type=pygltflib.VEC3,
                           min=vertices.min(0).tolist(), max=vertices.max(0).tolist()),
        pygltflib.Accessor(componentType=pygltflib.UNSIGNED_SHORT, count=faces.size, type=pygltflib.SCALAR)]
    doc.mesh([pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=0), indices=1, extensions={
        "KHR_draco_mesh_compression": {"bufferView": view, "attributes": {"POSITION": 0}}})])
    doc.gltf.extensionsUsed = doc.gltf.extensionsRequired = ["KHR_draco_mesh_compression"]
    doc.save(tmp_path / "draco.glb")
    got_v, got_f = load_mesh(tmp_path / "draco.glb")
    assert got_v.shape == vertices.shape
    np.testing.assert_array_equal(got_v, np.asarray(decoded.points, np.float64))
    np.testing.assert_array_equal(got_f, np.asarray(decoded.faces, np.int64))
    # Draco stores the vertices in an order of its own; the surface is the source's, within its quantization.
    np.testing.assert_allclose(got_v[got_f].mean(axis=1).mean(0), vertices[faces].mean(axis=1).mean(0), atol=0.01)


def test_quantized_positions_are_dequantized(tmp_path):
    """KHR_mesh_quantization as gltfpack writes it: normalized int16 positions, the scale in the node."""
    vertices, faces = _face()
    scale = float(np.abs(vertices).max())
    doc = _Doc()
    position = doc.accessor(np.round(vertices / scale * 32767).astype(np.int16), normalized=True)
    doc.mesh([pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=position),
                                  indices=doc.accessor(faces.reshape(-1).astype(np.uint32)))], scale=[scale] * 3)
    doc.gltf.extensionsUsed = doc.gltf.extensionsRequired = ["KHR_mesh_quantization"]
    doc.save(tmp_path / "quantized.glb")
    got_v, got_f = load_mesh(tmp_path / "quantized.glb")
    np.testing.assert_allclose(got_v, vertices, atol=scale / 32767)
    np.testing.assert_array_equal(got_f, faces)


def test_a_ktx2_texture_is_passed_over_with_a_note(tmp_path):
    from typer.testing import CliRunner

    from jaxtalk.cli import app

    vertices, faces = _face()
    doc = _face_doc(vertices, faces)
    image = doc.view(b"\xabKTX 20\xbb\r\n\x1a\n" + bytes(64))  # a KTX2 file's signature: never decoded
    doc.gltf.images = [pygltflib.Image(bufferView=image, mimeType="image/ktx2")]
    doc.gltf.textures = [pygltflib.Texture(extensions={"KHR_texture_basisu": {"source": 0}})]
    doc.gltf.extensionsUsed = doc.gltf.extensionsRequired = ["KHR_texture_basisu"]
    doc.save(tmp_path / "ktx2.glb")
    with pytest.warns(MeshFileNote, match="KTX2 textures are not read"):
        got_v, got_f = load_mesh(tmp_path / "ktx2.glb")
    assert got_v.shape == vertices.shape and np.array_equal(got_f, faces)
    # On the command line, one `note:` line (here before render's refusal of a file of another vertex count).
    np.save(tmp_path / "v.npy", np.zeros((2, 10, 3), np.float32))
    result = CliRunner().invoke(app, ["render", str(tmp_path / "v.npy"), "--faces", str(tmp_path / "ktx2.glb"),
                                      "--out", str(tmp_path / "x.gif")])
    assert result.exit_code == 2, result.output
    notes = [line for line in result.output.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "KTX2 textures are not read" in notes[0], result.output
    assert "Warning" not in result.output


def test_gltf_errors_name_the_file_and_the_fix(tmp_path):
    vertices, faces = _face()
    _face_doc(vertices, faces).save(tmp_path / "face.gltf")
    (tmp_path / "face.bin").unlink()
    with pytest.raises(FileNotFoundError, match="keep the .bin files next to the .gltf"):
        load_mesh(tmp_path / "face.gltf")
    doc = _face_doc(vertices, faces)
    compressed, _ = _meshopt(doc)
    doc.save(tmp_path / "broken.glb", compressed[: len(compressed) // 2])
    with pytest.raises(ValueError, match="broken.glb.*meshopt buffer view|broken.glb.*could not be decoded"):
        load_mesh(tmp_path / "broken.glb")


@pytest.mark.external
def test_what_gltfpack_writes_reads_as_its_uncompressed_output(node_tools, tmp_path):  # noqa: F811
    """gltfpack (npm, through tests/js's lock file) as files are shipped: meshopt compression (``-c``,
    ``EXT_meshopt_compression``; ``-cz``, ``KHR_meshopt_compression``), quantization, filters. Each reads as
    gltfpack's own uncompressed output (``-noq``): the same vertices in the same order where only the
    compression differs, the same vertices, morph targets and triangles up to quantization otherwise."""
    import subprocess

    from scipy.spatial import cKDTree

    from jaxtalk.export import arkit_rig, export_rig_animation, load_rig

    rig = arkit_rig("low")
    export_rig_animation(rig, np.zeros((2, rig.num_shapes)), tmp_path / "rig.glb")

    def pack(name: str, *options: str):
        out = tmp_path / f"{name}.glb"
        subprocess.run(["node", str(node_tools / "node_modules" / "gltfpack" / "cli.js"), "-i", str(tmp_path / "rig.glb"),
                        "-o", str(out), *options], check=True, capture_output=True)
        return out

    reference = load_rig(pack("plain", "-noq"))
    assert reference.num_vertices == rig.num_vertices
    step = 2.0 * np.abs(reference.neutral).max() / (2**14 - 1)  # gltfpack's default 14-bit positions
    for name, options, required, same_order in [("meshopt", ["-noq", "-c"], {"EXT_meshopt_compression"}, True),
                                                ("quantized", ["-c"], {"EXT_meshopt_compression",
                                                                       "KHR_mesh_quantization"}, True),
                                                ("khr", ["-cz"], {"KHR_meshopt_compression",
                                                                  "KHR_mesh_quantization"}, False)]:
        path = pack(name, *options)
        assert set(pygltflib.GLTF2().load(str(path)).extensionsRequired) == required
        got = load_rig(path)
        vertices, faces = load_mesh(path)
        np.testing.assert_array_equal(vertices, got.neutral)
        np.testing.assert_array_equal(faces, got.faces)
        assert got.names == reference.names and got.num_vertices == reference.num_vertices
        # Each vertex to the reference's nearest (the identity where the order is the same): one to one.
        distance, order = cKDTree(reference.neutral).query(got.neutral)
        assert np.unique(order).size == order.size and distance.max() <= step, (name, distance.max())
        if same_order:
            np.testing.assert_array_equal(order, np.arange(order.size))
        np.testing.assert_allclose(got.deltas, reference.deltas[:, order], rtol=0, atol=step)
        assert ({tuple(t) for t in _corners_from_lowest(order[got.faces]).tolist()}
                == {tuple(t) for t in _corners_from_lowest(reference.faces).tolist()})
