"""Graph convolution: the normalised adjacency of a 3-node path by hand, the layer, and its errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.nn import GraphConv, normalized_adjacency

from test_nn_support import random_params


S6 = 1 / np.sqrt(6)
# Path 0 - 1 - 2 with self-loops: degrees (2, 3, 2), entry (i, j) = 1 / sqrt(d_i d_j).
PATH_WITH_LOOPS = np.array([[1 / 2, S6, 0], [S6, 1 / 3, S6], [0, S6, 1 / 2]])
# Without self-loops: degrees (1, 2, 1).
PATH_NO_LOOPS = np.array([[0, 1 / np.sqrt(2), 0], [1 / np.sqrt(2), 0, 1 / np.sqrt(2)], [0, 1 / np.sqrt(2), 0]])


def test_normalized_adjacency_of_a_path_by_hand():
    np.testing.assert_allclose(normalized_adjacency(np.array([[0, 1], [1, 2]]), 3), PATH_WITH_LOOPS, rtol=1e-6)
    np.testing.assert_allclose(
        normalized_adjacency(np.array([[0, 1], [1, 2]]), 3, self_loops=False), PATH_NO_LOOPS, rtol=1e-6
    )


def test_normalized_adjacency_ignores_direction_duplicates_and_explicit_self_edges():
    edges = [(1, 0), (0, 1), (2, 1), (1, 2), (1, 2), (2, 2)]
    np.testing.assert_allclose(normalized_adjacency(edges, 3), PATH_WITH_LOOPS, rtol=1e-6)
    # An isolated node without self-loops has degree 0: a zero row and column, no NaN.
    a = normalized_adjacency(np.array([[0, 1]]), 3, self_loops=False)
    assert np.all(np.isfinite(a))
    np.testing.assert_array_equal(a[2], 0.0)
    np.testing.assert_array_equal(a[:, 2], 0.0)
    np.testing.assert_allclose(normalized_adjacency(np.zeros((0, 2), int), 2), np.eye(2))


def test_graph_conv_by_hand_with_leading_axes(key):
    adjacency = normalized_adjacency(np.array([[0, 1], [1, 2]]), 3)
    layer = GraphConv(2, adjacency)
    x = jax.random.normal(key, (4, 5, 3, 6))  # (batch, frames, nodes, features)
    params = random_params(layer, x)
    p = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params["params"])
    expected = np.einsum("ij,bfjc,cd->bfid", PATH_WITH_LOOPS, np.asarray(x, np.float64), p["linear"]["kernel"])
    np.testing.assert_allclose(layer.apply(params, x), expected + p["bias"], atol=1e-5)
    # Node 0 and node 2 are not neighbours: a change at node 2 reaches node 0 only via a second layer.
    delta = layer.apply(params, x.at[..., 2, :].add(1.0)) - layer.apply(params, x)
    np.testing.assert_array_equal(delta[..., 0, :], 0.0)
    assert np.abs(delta[..., 1, :]).max() > 0


def test_graph_conv_is_hashable_and_compares_by_value():
    a = normalized_adjacency(np.array([[0, 1]]), 2)
    assert GraphConv(4, a) == GraphConv(4, a.copy())
    assert hash(GraphConv(4, a)) == hash(GraphConv(4, a.copy()))
    assert GraphConv(4, a) != GraphConv(4, np.eye(2, dtype=np.float32))


def test_graph_errors(key):
    with pytest.raises(ValueError, match=r"\[0, 3\)"):
        normalized_adjacency(np.array([[0, 3]]), 3)
    with pytest.raises(ValueError, match="num_edges, 2"):
        normalized_adjacency(np.array([[0, 1, 2]]), 3)
    with pytest.raises(ValueError, match="integer"):
        normalized_adjacency(np.array([[0.5, 1.0]]), 3)
    with pytest.raises(ValueError, match="num_nodes"):
        normalized_adjacency(np.array([[0, 1]]), 0)
    layer = GraphConv(2, normalized_adjacency(np.array([[0, 1]]), 2))
    with pytest.raises(ValueError, match="2 nodes but the input has 3"):
        jax.eval_shape(layer.init, key, jnp.zeros((3, 4)))
