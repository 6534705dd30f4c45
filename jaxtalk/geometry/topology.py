"""Topology variants of a mesh with an exact map to the base surface (FreeTalk's any-topology setting).

Each variant vertex carries a base triangle index and barycentric coordinates, so the ground-truth
motion of a variant is known for any base motion: ``variant_vertex = sum_k bary_k * base_vertex``.

Kinds:
* ``"subdivided"``: one midpoint subdivision (``trimesh.remesh.subdivide``); exact by construction.
* ``"decimated"``: quadric decimation to ~45% of the faces (``simplify_quadric_decimation``, needs
  ``fast-simplification``), then every vertex is projected onto the base surface
  (``trimesh.proximity.closest_point``) and replaced by its projection, so the map is exact for the
  variant as returned.
* ``"retriangulated"``: an even (Poisson-disk-like) resample of the base surface
  (``trimesh.sample.sample_surface_even``, face and barycentric known by construction) plus the base
  boundary, triangulated by Delaunay in a 2-D parameter domain: the Tutte embedding of the base disk
  (boundary on a circle by arc length), which is a bijection, so every 2-D triangle is a valid patch
  of the surface. Needs a disk-topology base (one boundary loop).
* ``"shuffled"``: the same mesh with vertex order, face order and each face's starting corner permuted.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax.numpy as jnp
import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg
import scipy.spatial

from jaxtalk.types import Array, Float, Int

__all__ = ["TopologyVariant", "make_variant", "mesh_summary", "KINDS"]

KINDS = ("subdivided", "decimated", "retriangulated", "shuffled")
Kind = Literal["subdivided", "decimated", "retriangulated", "shuffled"]


@dataclasses.dataclass(frozen=True, eq=False)
class TopologyVariant:
    """A remeshed face with an exact map onto the base mesh surface.

    Attributes:
        vertices: variant rest vertices, ``(V', 3)``.
        faces: variant triangles, ``(F', 3)`` int32.
        face_index: base triangle holding each variant vertex, ``(V',)`` int32.
        barycentric: barycentric coordinates in that triangle, ``(V', 3)``.
        kind: which variant ("subdivided", "decimated", "retriangulated", "shuffled").
        base_faces: the base mesh's triangles, ``(F, 3)`` (needed to interpolate base motion).
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_index: np.ndarray
    barycentric: np.ndarray
    kind: str
    base_faces: np.ndarray

    def _interpolation_matrix(self, num_base: int) -> scipy.sparse.csr_matrix:
        """The sparse (V', V) barycentric interpolation matrix (3 entries per row), built once."""
        cached = self.__dict__.get("_interp")
        if cached is None or cached.shape[1] != num_base:
            cached = _interpolation_rows(self, num_base)
            object.__setattr__(self, "_interp", cached)
        return cached

    def transfer(
        self, base_vertex_seq: Float[Array | np.ndarray, "..."]
    ) -> Float[Array | np.ndarray, "*frames verts 3"]:
        """Carry base-mesh vertex positions over to this variant (barycentric interpolation).

        Args:
            base_vertex_seq: base vertices, ``(T, V, 3)`` or ``(V, 3)``; NumPy in -> NumPy out,
                JAX in -> JAX out (jit/grad friendly).

        Returns:
            Variant vertices, ``(T, V', 3)`` or ``(V', 3)``.

        Raises:
            ValueError: if the vertex axis does not match the base mesh.
        """
        num_base = int(self.base_faces.max()) + 1
        shape = np.shape(base_vertex_seq)
        if len(shape) < 2 or shape[-1] != 3 or shape[-2] < num_base:
            raise ValueError(f"base_vertex_seq must end in (V >= {num_base}, 3), got {shape}")
        corners = self.base_faces[self.face_index]  # (V', 3)
        # Three gathers weighted by one barycentric column each: no (..., V', 3, 3) temporary.
        if isinstance(base_vertex_seq, np.ndarray):
            # One sparse (V', V) product over all frames and coordinates at once.
            x = base_vertex_seq
            flat = np.moveaxis(x, -2, 0).reshape(x.shape[-2], -1)
            matrix = self._interpolation_matrix(x.shape[-2]).astype(np.result_type(x.dtype, np.float32))
            out = (matrix @ flat).astype(x.dtype, copy=False)
            return np.moveaxis(out.reshape(len(corners), *x.shape[:-2], 3), 0, -2)
        x = jnp.asarray(base_vertex_seq)
        bary = jnp.asarray(self.barycentric, x.dtype)
        out_shape = (*x.shape[:-2], len(corners), 3)
        return sum(
            jnp.broadcast_to(bary[:, k, None], out_shape) * jnp.take(x, jnp.asarray(corners[:, k]), axis=-2)
            for k in range(3)
        )


def _interpolation_rows(variant: TopologyVariant, num_base: int) -> scipy.sparse.csr_matrix:
    corners = variant.base_faces[variant.face_index]
    rows = np.repeat(np.arange(len(corners)), 3)
    return scipy.sparse.csr_matrix(
        (variant.barycentric.reshape(-1), (rows, corners.reshape(-1))), shape=(len(corners), num_base)
    )


def mesh_summary(vertices: np.ndarray, faces: np.ndarray) -> dict[str, int | bool]:
    """Manifoldness facts of a triangle mesh (checked with trimesh's edge bookkeeping).

    Args:
        vertices: ``(V, 3)``; faces: ``(F, 3)``.

    Returns:
        ``{"vertices", "faces", "components", "boundary_loops", "nonmanifold_edges",
        "nonmanifold_vertices", "degenerate_faces", "unreferenced_vertices", "winding_consistent",
        "manifold"}``; "manifold" means no edge in more than two faces, no vertex whose link is not a
        single fan, no degenerate face, no unreferenced vertex, consistent winding.
    """
    import trimesh

    faces = np.asarray(faces)
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), faces, process=False, validate=False)
    edges = mesh.edges_sorted
    _, edge_counts = np.unique(edges, axis=0, return_counts=True)
    unique_edges, inverse = np.unique(edges, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    boundary = unique_edges[np.bincount(inverse, minlength=len(unique_edges)) == 1]
    # A boundary vertex with more than two boundary edges is a pinch point (bow-tie).
    boundary_degree = np.bincount(boundary.reshape(-1), minlength=len(vertices))
    num_loops = 0
    if len(boundary):
        graph = scipy.sparse.coo_matrix(
            (np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(len(vertices),) * 2
        )
        _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
        num_loops = len(np.unique(labels[np.unique(boundary)]))
    # Pinched vertices: more than two boundary edges, or faces around the vertex in several fans.
    nonmanifold_vertices = int(np.sum((boundary_degree > 2) | _split_fans(faces, len(vertices))))
    referenced = np.zeros(len(vertices), bool)
    referenced[faces.reshape(-1)] = True
    degenerate = int(np.sum((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])))
    components = int(len(trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(faces)))))
    out = {
        "vertices": int(len(vertices)),
        "faces": int(len(faces)),
        "components": components,
        "boundary_loops": int(num_loops),
        "nonmanifold_edges": int(np.sum(edge_counts > 2)),
        "nonmanifold_vertices": nonmanifold_vertices,
        "degenerate_faces": degenerate,
        "unreferenced_vertices": int(np.sum(~referenced)),
        "winding_consistent": bool(mesh.is_winding_consistent),
    }
    out["manifold"] = bool(
        out["nonmanifold_edges"] == 0
        and nonmanifold_vertices == 0
        and degenerate == 0
        and out["unreferenced_vertices"] == 0
        and out["winding_consistent"]
    )
    return out


def _split_fans(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """Mask of vertices whose incident faces form more than one edge-connected fan."""
    # Corner (face f, vertex v) nodes; two corners of the same vertex are joined when their faces
    # share an edge through that vertex. Components per vertex > 1 means a pinched vertex.
    num_faces = len(faces)
    corner_vertex = faces.reshape(-1)
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    half_face = np.tile(np.arange(num_faces), 3)
    key = np.sort(half, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, half_face = key[order], half_face[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    fa, fb, ek = half_face[:-1][same], half_face[1:][same], key[:-1][same]
    # corner id = 3 * face + position of the vertex in the face
    def corner_id(f, v):
        pos = np.argmax(faces[f] == v[:, None], axis=1)
        return 3 * f + pos

    rows, cols = [], []
    for end in (0, 1):
        v = ek[:, end]
        rows.append(corner_id(fa, v))
        cols.append(corner_id(fb, v))
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * num_faces,) * 2)
    _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
    fans_per_vertex = np.zeros(num_vertices, np.int64)
    pairs = np.unique(np.stack([corner_vertex, labels]), axis=1)
    np.add.at(fans_per_vertex, pairs[0], 1)
    return fans_per_vertex > 1


def _one_hot_map(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """For every vertex, one face that contains it and the one-hot barycentric selecting it."""
    face_of = np.full(num_vertices, -1, np.int64)
    corner_of = np.zeros(num_vertices, np.int64)
    for k in range(3):
        face_of[faces[:, k]] = np.arange(len(faces))
        corner_of[faces[:, k]] = k
    if np.any(face_of < 0):
        raise ValueError(f"base mesh has {int(np.sum(face_of < 0))} unreferenced vertices")
    return face_of, np.eye(3)[corner_of]


def _subdivided(vertices, faces, rng):
    import trimesh

    new_vertices, new_faces = trimesh.remesh.subdivide(vertices, faces)
    num_base = len(vertices)
    face_index = np.zeros(len(new_vertices), np.int64)
    bary = np.zeros((len(new_vertices), 3))
    face_index[:num_base], bary[:num_base] = _one_hot_map(faces, num_base)
    # New vertices are exact midpoints of base edges: find each edge in one base face (corner k of
    # face f starts edge (faces[f, k], faces[f, k+1])), then match midpoints to new vertices.
    num_faces = len(faces)
    starts = faces.T.reshape(-1)  # corner-major: entry k * F + f
    ends = np.roll(faces, -1, axis=1).T.reshape(-1)
    keys = np.stack([np.minimum(starts, ends), np.maximum(starts, ends)], axis=1)
    keys, first = np.unique(keys, axis=0, return_index=True)
    edge_face, edge_corner = first % num_faces, first // num_faces
    mids = 0.5 * (vertices[keys[:, 0]] + vertices[keys[:, 1]])
    dist, target = scipy.spatial.cKDTree(new_vertices[num_base:]).query(mids)
    if len(keys) != len(new_vertices) - num_base or dist.max() > 1e-9 * (1 + np.abs(vertices).max()):
        raise RuntimeError("subdivision produced vertices that are not base edge midpoints")
    rows = num_base + target
    face_index[rows] = edge_face
    bary[rows, edge_corner] = 0.5
    bary[rows, (edge_corner + 1) % 3] = 0.5
    # Snap to the exact interpolant (the subdivided coordinates already are, up to rounding).
    new_vertices = np.einsum("vkc,vk->vc", vertices[faces[face_index]], bary)
    return new_vertices, new_faces, face_index, bary


def _project(vertices, faces, points):
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    closest, _, face_index = trimesh.proximity.closest_point(mesh, points)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[face_index], closest)
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return face_index.astype(np.int64), bary


def _decimated(vertices, faces, rng):
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    target = max(int(0.45 * len(faces)), 4)
    simple = mesh.simplify_quadric_decimation(face_count=target)
    simple.remove_unreferenced_vertices()
    face_index, bary = _project(vertices, faces, np.asarray(simple.vertices))
    new_vertices = np.einsum("vkc,vk->vc", vertices[faces[face_index]], bary)
    return new_vertices, np.asarray(simple.faces), face_index, bary


def _boundary_loop(faces: np.ndarray) -> np.ndarray:
    """The ordered vertex loop of the single boundary of a disk mesh."""
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = {(int(a), int(b)) for a, b in half}
    boundary = [(a, b) for a, b in key if (b, a) not in key]
    if not boundary:
        raise ValueError("retriangulated variants need a mesh with a boundary (a disk), got a closed mesh")
    nxt = dict(boundary)
    if len(nxt) != len(boundary):
        raise ValueError("mesh boundary is not a simple loop (pinched boundary vertex)")
    start = boundary[0][0]
    loop = [start]
    while True:
        v = nxt[loop[-1]]
        if v == start:
            break
        loop.append(v)
    if len(loop) != len(boundary):
        raise ValueError(f"retriangulated variants need exactly one boundary loop, "
                         f"got {len(boundary)} boundary edges in several loops")
    return np.asarray(loop)


def _tutte_embedding(vertices: np.ndarray, faces: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Tutte (uniform-weight harmonic) map of a disk mesh onto the unit disk, boundary by arc length."""
    n = len(vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    adj = scipy.sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    adj = ((adj + adj.T) > 0).astype(np.float64).tocsr()
    lap = scipy.sparse.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
    seg = np.linalg.norm(vertices[np.roll(loop, -1)] - vertices[loop], axis=1)
    angle = 2 * np.pi * np.concatenate([[0.0], np.cumsum(seg)[:-1]]) / seg.sum()
    uv = np.zeros((n, 2))
    uv[loop] = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    interior = np.setdiff1d(np.arange(n), loop)
    lap = lap.tocsr()
    a_ii = lap[interior][:, interior].tocsc()
    rhs = -lap[interior][:, loop] @ uv[loop]
    uv[interior] = scipy.sparse.linalg.splu(a_ii).solve(rhs)
    return uv


def _retriangulated(vertices, faces, rng):
    import trimesh

    loop = _boundary_loop(faces)
    uv = _tutte_embedding(vertices, faces, loop)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    # Every other boundary vertex keeps the outline; interior samples come from an even resample.
    keep = loop[::2]
    spacing = np.median(np.linalg.norm(vertices[keep] - vertices[np.roll(keep, -1)], axis=1))
    # Aim at ~0.7x the base's interior vertex count. trimesh's rejection sampler keeps N ~ c A / r^2
    # points for an unknown packing constant c: measure it with one pass, then set r for the target.
    count = int(0.7 * (len(vertices) - len(loop)))
    radius = np.sqrt(mesh.area / count)
    for _ in range(2):
        points, sample_faces = _even_samples(mesh, 4 * count, radius, rng)
        radius *= np.sqrt(len(points) / count)
    sample_faces = np.asarray(sample_faces, np.int64)
    sample_bary = trimesh.triangles.points_to_barycentric(mesh.triangles[sample_faces], points)
    # Drop samples too close to the kept boundary (they would make slivers at the outline).
    dist, _ = scipy.spatial.cKDTree(vertices[keep]).query(points)
    ok = dist > 0.5 * max(spacing, radius)
    boundary_face, boundary_bary = _one_hot_map(faces, len(vertices))
    face_index = np.concatenate([boundary_face[keep], sample_faces[ok]])
    bary = np.concatenate([boundary_bary[keep], sample_bary[ok]])
    points_2d = np.einsum("vkc,vk->vc", uv[faces[face_index]], bary)
    # The Tutte domain is convex, so the Delaunay triangulation of the samples covers exactly the
    # resampled surface: no triangle falls outside the boundary and none needs dropping.
    simplices = scipy.spatial.Delaunay(points_2d).simplices
    a, b, c = (points_2d[simplices[:, k]] for k in range(3))
    area = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    # Qhull does not orient its simplices: make them all counter-clockwise in the domain.
    simplices = np.where((area < 0)[:, None], simplices[:, [0, 2, 1]], simplices)
    new_vertices = np.einsum("vkc,vk->vc", vertices[faces[face_index]], bary)
    # Orient like the base: the Tutte map preserves orientation iff the boundary loop runs CCW in 2-D.
    base_normal_sign = _orientation_sign(vertices, faces, uv)
    if base_normal_sign < 0:
        simplices = simplices[:, [0, 2, 1]]
    return new_vertices, simplices, face_index, bary


def _even_samples(mesh, count: int, radius: float, rng: np.random.Generator):
    import logging

    import trimesh

    # trimesh warns whenever the rejection sampler keeps fewer points than asked for, which is the
    # point of asking for many and letting the radius decide.
    logger = logging.getLogger("trimesh")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        return trimesh.sample.sample_surface_even(mesh, count, radius=radius, seed=rng)
    finally:
        logger.setLevel(level)


def _orientation_sign(vertices, faces, uv) -> float:
    a, b, c = (uv[faces[:, k]] for k in range(3))
    area = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    return float(np.sign(np.sum(area)))


def _shuffled(vertices, faces, rng):
    n = len(vertices)
    perm = rng.permutation(n)  # new vertex i is old vertex perm[i]
    inverse = np.empty(n, np.int64)
    inverse[perm] = np.arange(n)
    new_faces = inverse[faces][rng.permutation(len(faces))]
    roll = rng.integers(0, 3, len(new_faces))  # cyclic corner shift keeps orientation
    idx = (np.arange(3)[None, :] + roll[:, None]) % 3
    new_faces = np.take_along_axis(new_faces, idx, axis=1)
    face_of, bary_of = _one_hot_map(faces, n)
    return vertices[perm], new_faces, face_of[perm], bary_of[perm]


_BUILDERS = {
    "subdivided": _subdivided,
    "decimated": _decimated,
    "retriangulated": _retriangulated,
    "shuffled": _shuffled,
}


def make_variant(
    vertices: Float[Array | np.ndarray, "..."],
    faces: Int[Array | np.ndarray, "..."],
    kind: str,
    seed: int = 0,
) -> TopologyVariant:
    """Remesh a base mesh and keep the exact map from the variant onto the base surface.

    Inputs are annotated loosely so malformed arrays reach the explicit ``ValueError`` checks.

    Args:
        vertices: base rest vertices, ``(V, 3)``.
        faces: base triangles, ``(F, 3)``.
        kind: "subdivided", "decimated", "retriangulated" or "shuffled".
        seed: seeds the random parts (resampling, permutations); same seed, same variant.

    Returns:
        A ``TopologyVariant`` whose vertices equal ``transfer(vertices)``.

    Raises:
        ValueError: for an unknown kind, malformed arrays (shape, NaN, out-of-range faces), or a
            base mesh the kind cannot handle (retriangulation needs a single boundary loop).
    """
    if kind not in _BUILDERS:
        raise ValueError(f"unknown topology variant kind {kind!r}; known: {list(KINDS)}")
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
        raise ValueError(f"vertices must have shape (V >= 3, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices hold NaN or inf")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be a non-empty integer array of shape (F, 3), got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"face indices must lie in [0, {len(v)}), got range [{f.min()}, {f.max()}]")
    f = f.astype(np.int64)
    rng = np.random.default_rng(seed)
    new_v, new_f, face_index, bary = _BUILDERS[kind](v, f, rng)
    return TopologyVariant(
        vertices=np.asarray(new_v, np.float64),
        faces=np.asarray(new_f, np.int32),
        face_index=np.asarray(face_index, np.int32),
        barycentric=np.asarray(bary, np.float64),
        kind=kind,
        base_faces=f.astype(np.int32),
    )
