"""FrameBandedSolver and the block-tridiagonal solve against dense references."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from jaxtalk.fit import FrameBandedSolver, block_tridiagonal_solve


def _banded_problem(num_frames: int, n: int = 4, m: int = 7, seed: int = 0):
    """A random frame-banded operator (per-frame data rows, pair rows, a damping leaf) and a rhs."""
    rng = np.random.default_rng(seed)
    jac = jnp.asarray(rng.normal(size=(num_frames, m, n)))
    pair_a = jnp.asarray(rng.normal(size=(num_frames - 1, 3, n)))
    pair_b = jnp.asarray(rng.normal(size=(num_frames - 1, 3, n)))

    def fn(y):
        data = jnp.einsum("tmn,tn->tm", jac, y)
        pairs = jnp.einsum("tkn,tn->tk", pair_a, y[:-1]) + jnp.einsum("tkn,tn->tk", pair_b, y[1:])
        return {"data": data, "pairs": pairs}, 0.5 * y

    op = lx.FunctionLinearOperator(fn, jax.ShapeDtypeStruct((num_frames, n), jnp.float64))
    rhs = (
        {
            "data": jnp.asarray(rng.normal(size=(num_frames, m))),
            "pairs": jnp.asarray(rng.normal(size=(num_frames - 1, 3))),
        },
        jnp.asarray(rng.normal(size=(num_frames, n))),
    )
    return op, rhs


@pytest.mark.parametrize("num_frames", [1, 2, 5])
def test_banded_solver_matches_dense_qr(float64, num_frames):
    op, rhs = _banded_problem(num_frames)
    banded = lx.linear_solve(op, rhs, FrameBandedSolver(ridge=0.0))
    dense = lx.linear_solve(op, rhs, lx.QR())
    assert banded.result == lx.RESULTS.successful
    np.testing.assert_allclose(banded.value, dense.value, atol=1e-11, rtol=1e-10)


def test_block_tridiagonal_solve_matches_dense(float64):
    rng = np.random.default_rng(1)
    num_frames, n = 6, 3
    a = rng.normal(size=(num_frames * n, num_frames * n))
    band = np.abs(np.subtract.outer(np.arange(num_frames * n) // n, np.arange(num_frames * n) // n)) <= 1
    sym = 0.5 * (a + a.T) * band
    # Block tridiagonal and positive definite (shifted above its most negative eigenvalue).
    h = sym + (1.0 - np.linalg.eigvalsh(sym).min()) * np.eye(num_frames * n)
    diag = np.stack([h[t * n : (t + 1) * n, t * n : (t + 1) * n] for t in range(num_frames)])
    lower = np.stack([h[(t + 1) * n : (t + 2) * n, t * n : (t + 1) * n] for t in range(num_frames - 1)])
    rhs = rng.normal(size=(num_frames, n))
    x = block_tridiagonal_solve(jnp.asarray(diag), jnp.asarray(lower), jnp.asarray(rhs))
    np.testing.assert_allclose(np.asarray(x).reshape(-1), np.linalg.solve(h, rhs.reshape(-1)), rtol=1e-10)


def test_singular_system_reports_singular_without_ridge(float64):
    # Parameter 0 of every frame never enters the residual: a zero Jacobian column.
    def fn(y):
        return {"data": y[:, 1:] * 2.0}

    op = lx.FunctionLinearOperator(fn, jax.ShapeDtypeStruct((3, 2), jnp.float64))
    rhs = {"data": jnp.ones((3, 1))}
    out = lx.linear_solve(op, rhs, FrameBandedSolver(ridge=0.0), throw=False)
    assert out.result == lx.RESULTS.singular
    # The default ridge keeps the step finite and zero along the null direction (minimum norm).
    out = lx.linear_solve(op, rhs, FrameBandedSolver(), throw=False)
    assert out.result == lx.RESULTS.successful
    np.testing.assert_allclose(out.value, np.stack([np.zeros(3), np.full(3, 0.5)], axis=1), atol=1e-9)


def test_unsupported_leaf_layout_raises(float64):
    def fn(y):
        return {"bad": jnp.concatenate([y, y]).reshape(-1)[None].repeat(5, axis=0)}

    op = lx.FunctionLinearOperator(fn, jax.ShapeDtypeStruct((3, 2), jnp.float64))
    with pytest.raises(ValueError, match="leading axis T=3 or T-1=2"):
        FrameBandedSolver().init(op, {})
