"""STM (Sparse-To-Mesh): landmark displacements -> dense vertex displacements on any mesh topology.

Four stages (FreeTalk section 3.2):

1. Static mesh features ``f_i`` from a DiffusionNet encoder on ``[xyz | normal]`` of the neutral
   mesh, computed ONCE per mesh (:func:`stm_mesh_features`) and reused for every frame.
2. Per frame, landmark features: a GCN (3 layers) on the fixed 68-landmark graph over the
   displacements, concatenated with a sinusoidal encoding of the landmark index and projected
   (equation 12); and the global displacement vector ``g_t`` (the 3N displacements, stacked).
3. Cross-attention vertex -> landmarks (queries from ``f_i``, keys/values from the landmark
   features, equations 13-14) gives ``c_{t,i}``.
4. A DiffusionNet decoder maps ``[f_i | g_t | c_{t,i}]`` to the displacement of vertex i. Its first
   linear map is applied block by block (``fuse_*``), which is the same function as one linear map
   of the concatenation but computes the global block once per frame rather than per vertex.

The per-mesh half of the fusion (the mesh-feature block of the decoder's first linear map and the
cross-attention queries) is computed once per mesh; the per-frame half (GCN, global vector, keys,
values and the attention itself) and the decoder run frame by frame (``lax.map``), sharing the mesh's
operators: on a CPU one frame's working set stays in cache (see :func:`_decode`). The model is intrinsic
except for its xyz/normal input, and it never assumes a vertex count or order: the same parameters
run on any mesh (a different V compiles a new program).

Units: public functions take vertices and displacements in metres; inside, positions are multiplied
by ``config.position_scale`` and displacements by ``config.displacement_scale``. The mesh operators
are computed on the scaled positions (see :func:`prepare_mesh`).
"""

from __future__ import annotations

import functools
import os
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.face import LANDMARK_EDGES
from jaxtalk.geometry.diffusionnet import DiffusionNet, DiffusionOperators, max_degree, to_diffusion_operators
from jaxtalk.geometry.operators import compute_operators, vertex_normals
from jaxtalk.models.freetalk.config import STMConfig
from jaxtalk.models.freetalk.loss import motion_loss
from jaxtalk.nn import GraphConv, dot_product_attention, normalized_adjacency, sinusoidal_embedding
from jaxtalk.nn.precision import compute_in
from jaxtalk.types import Array, Bool, Float, Int, PRNGKeyArray

__all__ = [
    "STMMesh",
    "SparseToMesh",
    "MeshContext",
    "prepare_mesh",
    "prepare_meshes",
    "stack_meshes",
    "check_landmark_motion",
    "init_params",
    "stm_mesh_features",
    "stm_decode",
    "apply",
    "loss",
    "make_loss_fn",
]

PyTree = Any


class STMMesh(NamedTuple):
    """A neutral mesh ready for STM: scaled positions, normals and DiffusionNet operators.

    With a leading mesh axis (from :func:`stack_meshes`) it describes a padded batch of meshes.

    Attributes:
        vertices: ``(V, 3)`` neutral positions in metres.
        normals: ``(V, 3)`` unit vertex normals.
        ops: DiffusionNet operators, computed on ``position_scale * vertices``.
        valid: ``(V,)`` True on real vertices (False on padding).
    """

    vertices: Float[Array, "*m verts 3"]
    normals: Float[Array, "*m verts 3"]
    ops: DiffusionOperators
    valid: Bool[Array, "*m verts"]

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[-2])


def prepare_mesh(
    vertices: Float[np.ndarray, "verts 3"] | Float[Array, "verts 3"],
    faces: Int[np.ndarray, "faces 3"] | Int[Array, "faces 3"],
    config: STMConfig,
    *,
    num_vertices: int | None = None,
    degree: int | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
) -> STMMesh:
    """Precompute everything STM needs for one neutral mesh (host side, float64 then float32).

    Args:
        vertices: ``(V, 3)`` neutral mesh in metres.
        faces: ``(F, 3)`` triangles.
        config: STM configuration (``position_scale``, ``num_eigenpairs``).
        num_vertices: pad to this many vertices (zero-mass padding, see
            :func:`jaxtalk.geometry.diffusionnet.to_diffusion_operators`).
        degree: pad the gradient one-ring width to this.
        cache_dir: disk cache for the operators (keyed by the mesh).

    Returns:
        An :class:`STMMesh`.

    Raises:
        ValueError: malformed or defective mesh, or fewer vertices than ``num_eigenpairs + 1``.
        EigenDecompositionError: the eigensolve failed.
    """
    ops, normals, n = _operators(vertices, faces, config, cache_dir)
    return _assemble(vertices, ops, normals, n, num_vertices, degree)


def _operators(vertices, faces, config: STMConfig, cache_dir):
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
    if v.shape[0] <= config.num_eigenpairs:
        raise ValueError(
            f"mesh has {v.shape[0]} vertices; STM needs more than num_eigenpairs={config.num_eigenpairs}"
        )
    scaled = v * config.position_scale
    ops = compute_operators(scaled, f, config.num_eigenpairs, cache_dir=cache_dir)
    return ops, vertex_normals(scaled, f), v.shape[0]


def _assemble(vertices, ops, normals, n: int, num_vertices: int | None, degree: int | None) -> STMMesh:
    total = n if num_vertices is None else int(num_vertices)
    dops = to_diffusion_operators(ops, num_vertices=total, degree=degree)
    pad = ((0, total - n), (0, 0))
    return STMMesh(
        vertices=jnp.asarray(np.pad(np.asarray(vertices, np.float64), pad), jnp.float32),
        normals=jnp.asarray(np.pad(normals, pad), jnp.float32),
        ops=dops,
        valid=jnp.asarray(np.arange(total) < n),
    )


def prepare_meshes(
    meshes: list[tuple[Any, Any]], config: STMConfig, *, cache_dir: str | os.PathLike[str] | None = None
) -> list[STMMesh]:
    """Prepare several meshes padded to a common vertex count and one-ring width (for training).

    Args:
        meshes: ``(vertices (V_m, 3), faces (F_m, 3))`` pairs.
        config: STM configuration.
        cache_dir: disk cache for the operators.

    Returns:
        One :class:`STMMesh` per input, all with the same padded shapes (ready for
        :func:`stack_meshes`).

    Raises:
        ValueError: as :func:`prepare_mesh`, or an empty list.
    """
    if not meshes:
        raise ValueError("prepare_meshes needs at least one mesh")
    parts = [_operators(v, f, config, cache_dir) for v, f in meshes]
    total = max(n for _, _, n in parts)
    degree = max(max_degree(ops) for ops, _, _ in parts)
    return [_assemble(v, ops, normals, n, total, degree) for (v, _), (ops, normals, n) in zip(meshes, parts)]


def stack_meshes(meshes: list[STMMesh]) -> STMMesh:
    """Stack meshes that were prepared with the same ``num_vertices`` and ``degree`` on a mesh axis.

    Args:
        meshes: from :func:`prepare_mesh` with common padding.

    Returns:
        An :class:`STMMesh` whose arrays have a leading axis ``len(meshes)``.

    Raises:
        ValueError: empty list or differing padded shapes.
    """
    if not meshes:
        raise ValueError("stack_meshes needs at least one mesh")
    shapes = {tuple(a.shape for a in jax.tree.leaves(m)) for m in meshes}
    if len(shapes) != 1:
        raise ValueError(
            "meshes must share padded shapes (prepare them with the same num_vertices and degree); "
            f"got {len(shapes)} different shape sets"
        )
    return jax.tree.map(lambda *xs: jnp.stack(xs), *meshes)


def check_landmark_motion(
    displacements: Any, num_landmarks: int
) -> Float[Array, "frames landmarks 3"] | Float[Array, "batch frames landmarks 3"]:
    """Validate a landmark displacement sequence: ``(T, N, 3)`` or ``(B, T, N, 3)``, finite.

    A flat ``(T, 3N)`` sequence (the ATS layout) is reshaped to ``(T, N, 3)``.

    Args:
        displacements: the sequence (metres).
        num_landmarks: N.

    Returns:
        The sequence as a float32 JAX array.

    Raises:
        ValueError: wrong shape (naming it), no frames, or NaN/inf values.
    """
    if isinstance(displacements, jax.core.Tracer):
        return displacements
    arr = np.asarray(displacements)
    if arr.ndim == 2 and arr.shape[1] == 3 * num_landmarks:
        arr = arr.reshape(arr.shape[0], num_landmarks, 3)
    if arr.ndim not in (3, 4) or arr.shape[-2:] != (num_landmarks, 3):
        raise ValueError(
            f"landmark displacements must have shape (frames, {num_landmarks}, 3) or "
            f"(batch, frames, {num_landmarks}, 3), got {arr.shape}"
        )
    if arr.shape[-3] == 0:
        raise ValueError("landmark displacement sequence has no frames")
    if not np.issubdtype(arr.dtype, np.floating) or not np.all(np.isfinite(arr)):
        raise ValueError("landmark displacements must be finite floats (got NaN/inf or a non-float dtype)")
    return jnp.asarray(arr, jnp.float32)


class _LandmarkEncoder(nn.Module):
    """``l~_{t,j} = phi([GCN(Delta L_t)_j | PE(j)])`` for one frame (equation 12)."""

    config: STMConfig

    @nn.compact
    def __call__(self, disp: Array) -> Array:
        cfg = self.config
        h = disp
        if cfg.uses_gcn:
            adjacency = normalized_adjacency(LANDMARK_EDGES, cfg.num_landmarks)
            for i in range(cfg.gcn_layers):
                h = GraphConv(cfg.gcn_hidden, adjacency, name=f"gcn_{i}")(h)
                if i < cfg.gcn_layers - 1:
                    h = nn.gelu(h)
        index = sinusoidal_embedding(jnp.arange(cfg.num_landmarks), cfg.index_encoding_dim, max_period=100.0)
        return nn.Dense(cfg.attention_dim, name="phi")(jnp.concatenate([h, index.astype(h.dtype)], axis=-1))


class _VertexLandmarkAttention(nn.Module):
    """Cross-attention vertex -> landmarks (equations 13-14), split into a per-mesh and a per-frame part.

    The queries come from the static mesh features, so :meth:`queries` runs once per mesh; per frame
    only the 68 keys/values and the ``V x 68`` attention itself are computed. The attention's output
    projection and the decoder's fuse block for ``c_{t,i}`` are two linear maps in a row; they are
    one map here (``out``: heads x head_dim -> decoder width), the same function class with one
    ``V x d x d`` product less per frame.
    """

    config: STMConfig

    def setup(self) -> None:
        cfg = self.config
        heads = (cfg.attention_heads, cfg.attention_dim // cfg.attention_heads)
        self.query = nn.DenseGeneral(heads, name="query")
        self.key = nn.DenseGeneral(heads, name="key")
        self.value = nn.DenseGeneral(heads, name="value")
        self.out = nn.DenseGeneral(cfg.decoder_width, axis=(-2, -1), use_bias=False, name="out")

    def queries(self, features: Array) -> Array:
        """``(V, heads, head_dim)`` queries of the mesh features (per mesh)."""
        return self.query(features)

    def __call__(self, queries: Array, landmarks: Array) -> Array:
        """``W c_{t,i}``, ``(V, decoder_width)``, for one frame's landmark features ``(N, attention_dim)``."""
        return self.out(dot_product_attention(queries, self.key(landmarks), self.value(landmarks)))


class _VertexMLP(nn.Module):
    """The supplement's decoder substitution: ``layers`` ReLU layers of ``width`` then a linear map to
    3, applied to every vertex on its own (no mesh operator, so neighbours never exchange features)."""

    width: int
    layers: int

    @nn.compact
    def __call__(self, x: Array) -> Array:
        h = x
        for i in range(self.layers):
            h = nn.Dense(self.width, name=f"mlp_{i}")(nn.relu(h) if i else h)
        return nn.Dense(3, name="linear_out")(nn.relu(h))


class MeshContext(NamedTuple):
    """The per-mesh half of STM's fusion, computed once and reused by every frame.

    Attributes:
        base: ``(V, decoder_width)``, the fuse block of the mesh features ``f_i`` (with its bias).
        queries: ``(V, heads, head_dim)`` cross-attention queries, or None without cross-attention.
    """

    base: Float[Array, "verts width"]
    queries: Float[Array, "verts heads head_dim"] | None


class SparseToMesh(nn.Module):
    """The STM network. ``mesh_features`` and ``mesh_context`` run once per mesh; ``fuse_frame`` and
    ``decode_fused`` run per frame (``decode_fused`` also takes frames stacked ``(V, T, width)``;
    ``decode_frame``: one frame end to end).

    Attributes:
        config: static :class:`STMConfig`.
    """

    config: STMConfig

    def setup(self) -> None:
        cfg = self.config
        self.encoder = DiffusionNet(cfg.encoder_config(), name="encoder")
        # The decoder's first linear map over [f_i | g_t | c_t,i], applied block by block: the block
        # of f_i is static (computed once per mesh), the block of the global vector g_t is the same
        # for every vertex (computed once per frame, not once per vertex).
        self.fuse_features = nn.Dense(cfg.decoder_width, name="fuse_features")
        if cfg.uses_global:
            self.fuse_global = nn.Dense(cfg.decoder_width, use_bias=False, name="fuse_global")
        if cfg.uses_attention:
            self.landmarks = _LandmarkEncoder(cfg, name="landmarks")
            self.cross_attention = _VertexLandmarkAttention(cfg, name="cross_attention")
        if cfg.decoder == "mlp":
            self.decoder = _VertexMLP(cfg.decoder_width, 2 * cfg.decoder_blocks, name="decoder")
        else:
            self.decoder = DiffusionNet(cfg.decoder_config(), name="decoder")

    def mesh_features(self, vertices: Array, normals: Array, ops: DiffusionOperators) -> Array:
        """``f_i = E_M([x_i | n_i])``, ``(V, mesh_feature_dim)``."""
        x = jnp.concatenate([vertices * self.config.position_scale, normals], axis=-1)
        return self.encoder(x, ops)

    def mesh_context(self, features: Array) -> MeshContext:
        """The per-mesh part of the fusion (see :class:`MeshContext`)."""
        queries = self.cross_attention.queries(features) if self.config.uses_attention else None
        return MeshContext(self.fuse_features(features), queries)

    def fuse_frame(self, context: MeshContext, disp: Array) -> Array:
        """The decoder's input ``W [f_i | g_t | c_t,i]`` (V, decoder_width) of one frame (model units)."""
        cfg = self.config
        h = context.base
        if cfg.uses_global:
            h = h + self.fuse_global(disp.reshape(1, -1))
        if cfg.uses_attention:
            h = h + self.cross_attention(context.queries, self.landmarks(disp))
        return h

    def decode_fused(self, fused: Array, ops: DiffusionOperators) -> Array:
        """The decoder on fused inputs ``(V, [*frames,] width)`` -> displacements."""
        return self.decoder(fused) if self.config.decoder == "mlp" else self.decoder(fused, ops)

    def decode_frame(self, features: Array, disp: Array, ops: DiffusionOperators) -> Array:
        """Vertex displacements (model units) of one frame from landmark displacements (model units)."""
        return self.decode_fused(self.fuse_frame(self.mesh_context(features), disp), ops)

    def __call__(self, vertices: Array, normals: Array, ops: DiffusionOperators, disp: Array) -> Array:
        return self.decode_frame(self.mesh_features(vertices, normals, ops), disp, ops)


def init_params(config: STMConfig, key: PRNGKeyArray, mesh: STMMesh | None = None) -> PyTree:
    """Initial STM parameters. Their shapes do not depend on the mesh, which only drives the trace: the
    same key gives the same parameters whatever mesh traces them.

    Args:
        config: static configuration.
        key: PRNG key.
        mesh: a prepared mesh (single, no leading axis) to trace with; None: a sphere just large enough
            for the config's eigenbasis.

    Returns:
        The ``{"params": ...}`` variables of :class:`SparseToMesh`.
    """
    return _init(config, key, _tracing_mesh(config) if mesh is None else mesh)


@functools.lru_cache(maxsize=8)
def _tracing_mesh(config: STMConfig) -> STMMesh:
    """The smallest icosphere with more vertices than the eigenbasis has pairs, prepared for ``config``."""
    import trimesh

    level = 1
    while 10 * 4**level + 2 <= config.num_eigenpairs + 1:
        level += 1
    sphere = trimesh.creation.icosphere(level, radius=0.1)
    return prepare_mesh(np.asarray(sphere.vertices), np.asarray(sphere.faces), config)


@functools.partial(jax.jit, static_argnames="config")
def _init(config: STMConfig, key: PRNGKeyArray, mesh: STMMesh) -> PyTree:
    # Module level with a static config: compiled once per configuration and mesh shape.
    disp = jnp.zeros((config.num_landmarks, 3))
    return SparseToMesh(config).init(key, mesh.vertices, mesh.normals, mesh.ops, disp)


def _check_mesh(mesh: STMMesh) -> None:
    if not isinstance(mesh, STMMesh):
        raise ValueError(f"mesh must be an STMMesh from prepare_mesh, got {type(mesh).__name__}")
    if mesh.vertices.ndim != 2:
        raise ValueError(f"expected a single mesh (vertices (V, 3)), got vertices of shape {mesh.vertices.shape}")


@functools.partial(jax.jit, static_argnames="config")
def _mesh_features(params, config: STMConfig, mesh: STMMesh):
    model = SparseToMesh(config)
    forward = compute_in(config.compute_dtype, model.apply)
    return forward(params, mesh.vertices, mesh.normals, mesh.ops, method=SparseToMesh.mesh_features)


def stm_mesh_features(params: PyTree, config: STMConfig, mesh: STMMesh) -> Float[Array, "verts features"]:
    """Static per-vertex features of a neutral mesh (run once per mesh; jitted).

    Args:
        params: STM variables.
        config: static configuration.
        mesh: from :func:`prepare_mesh`.

    Returns:
        ``(V, mesh_feature_dim)``.

    Raises:
        ValueError: not a single prepared mesh.
    """
    _check_mesh(mesh)
    return _mesh_features(params, config, mesh)


def _decode(params, config: STMConfig, features, disp, ops):
    # disp (T, N, 3) metres -> (T, V, 3) metres; features, mesh context and operators shared by all frames.
    model = SparseToMesh(config)
    forward = compute_in(config.compute_dtype, model.apply)
    context = forward(params, features, method=SparseToMesh.mesh_context)

    def frame(d: Array) -> Array:
        fused = forward(params, context, d * config.displacement_scale, method=SparseToMesh.fuse_frame)
        return forward(params, fused, ops, method=SparseToMesh.decode_fused)

    # Frame by frame (lax.map), not all frames at once: one frame's working set (the V x 68 x heads
    # attention logits, 6 MB at 5.9k vertices; the decoder's (V, C) features and one-ring gathers)
    # stays in cache, where 25 frames at once (the (V, T C) layout with its wide eigenbasis matmuls)
    # stream hundreds of MB through memory per pass (the measurement: docs/design-decisions.md).
    return jax.lax.map(frame, disp) / config.displacement_scale


_decode_jit = jax.jit(_decode, static_argnames="config")


def stm_decode(
    params: PyTree,
    config: STMConfig,
    features: Float[Array, "verts features"],
    displacements: Any,
    mesh: STMMesh,
) -> Float[Array, "frames verts 3"]:
    """Vertex displacements for a landmark displacement sequence on a mesh with precomputed features.

    Args:
        params: STM variables.
        config: static configuration.
        features: ``(V, mesh_feature_dim)`` from :func:`stm_mesh_features` on ``mesh``.
        displacements: ``(T, N, 3)`` landmark displacements in metres (``(T, 3N)`` accepted).
        mesh: the prepared mesh.

    Returns:
        ``(T, V, 3)`` vertex displacements in metres; the animated mesh is ``mesh.vertices + out``.

    Raises:
        ValueError: a landmark sequence of the wrong shape or with NaN/inf, or features that do not
            match the mesh.
    """
    _check_mesh(mesh)
    disp = check_landmark_motion(displacements, config.num_landmarks)
    if disp.ndim != 3:
        raise ValueError(f"stm_decode takes one sequence (frames, {config.num_landmarks}, 3), got {disp.shape}")
    if features.shape != (mesh.num_vertices, config.mesh_feature_dim):
        raise ValueError(
            f"features must have shape ({mesh.num_vertices}, {config.mesh_feature_dim}) for this mesh, "
            f"got {features.shape}"
        )
    return _decode_jit(params, config, features, disp, mesh.ops)


def apply(
    params: PyTree, config: STMConfig, mesh: STMMesh, displacements: Any
) -> Float[Array, "frames verts 3"]:
    """Mesh features then per-frame decoding: ``STM(M, (Delta L_t)_t) = (Delta V_t)_t``.

    Args:
        params: STM variables.
        config: static configuration.
        mesh: from :func:`prepare_mesh`.
        displacements: ``(T, N, 3)`` landmark displacements in metres.

    Returns:
        ``(T, V, 3)`` vertex displacements in metres.

    Raises:
        ValueError: as :func:`stm_decode`.
    """
    return stm_decode(params, config, stm_mesh_features(params, config, mesh), displacements, mesh)


def loss(
    params: PyTree,
    config: STMConfig,
    batch: dict[str, Any],
    key: PRNGKeyArray | None = None,
    *,
    meshes: STMMesh,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """Motion loss of STM on a batch of windows, each on one of a stack of padded meshes.

    Args:
        params: STM variables.
        config: static configuration.
        batch: ``"mesh"`` ``(B,)`` int mesh index, ``"landmarks"`` ``(B, T, N, 3)`` landmark
            displacements (metres), ``"vertices"`` ``(B, T, V, 3)`` vertex displacements (metres,
            padding rows ignored), optional ``"mask"`` ``(B, T)``.
        key: unused (the loss is deterministic); accepted for the training loop's signature.
        meshes: :func:`stack_meshes` output (leading mesh axis M, common padded V): the training
            set's meshes, which ``batch["mesh"]`` indexes (:func:`make_loss_fn` binds them).

    Returns:
        ``(loss, metrics)`` in model units (``displacement_scale`` x metres).
    """
    del key
    model = SparseToMesh(config)
    forward = compute_in(config.compute_dtype, model.apply)
    mesh_idx = jnp.asarray(batch["mesh"], jnp.int32)
    picked = jax.tree.map(lambda a: a[mesh_idx], meshes)
    features = jax.vmap(
        lambda m: forward(params, m.vertices, m.normals, m.ops, method=SparseToMesh.mesh_features)
    )(picked)
    landmarks = jnp.asarray(batch["landmarks"], jnp.float32)
    pred = jax.vmap(lambda f, d, ops: _decode(params, config, f, d, ops))(features, landmarks, picked.ops)
    target = jnp.asarray(batch["vertices"], jnp.float32)
    mask = jnp.asarray(batch["mask"], bool) if "mask" in batch else None
    s = config.displacement_scale
    return motion_loss(
        pred * s,
        target * s,
        mask,
        picked.valid,
        velocity_weight=config.velocity_weight,
        acceleration_weight=config.acceleration_weight,
    )


def make_loss_fn(config: STMConfig, meshes: STMMesh):
    """``loss_fn(params, batch, key)`` for :func:`jaxtalk.train.train` with the meshes bound.

    Args:
        config: static configuration.
        meshes: stacked training meshes.

    Returns:
        The loss function.
    """
    return functools.partial(_bound_loss, config, meshes)


def _bound_loss(config: STMConfig, meshes: STMMesh, params: PyTree, batch: dict[str, Any], key: PRNGKeyArray):
    return loss(params, config, batch, key, meshes=meshes)
