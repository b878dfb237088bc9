"""The block normal-equations solver against dense linear algebra."""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from scheimflux.calibrate._linear import (
    BlockNormalCholesky,
    BlockStructure,
    block_layout,
    detect_rows,
)
from scheimflux.calibrate._solve import free_spec, least_squares, split


def _random_block_jacobian(rng, V=4, ng=3, nl=2, rows_per_block=5, free_rows=3):
    """A dense J with the block pattern, plus its structure (columns shuffled)."""
    n = ng + V * nl
    perm = rng.permutation(n)
    global_cols, local_cols = perm[:ng], perm[ng:].reshape(V, nl)
    row_block = np.concatenate([np.repeat(np.arange(V), rows_per_block), np.full(free_rows, V)])
    rng.shuffle(row_block)
    J = np.zeros((len(row_block), n))
    for r, b in enumerate(row_block):
        J[r, global_cols] = rng.standard_normal(ng)
        if b < V:
            J[r, local_cols[b]] = rng.standard_normal(nl)
    s = BlockStructure(
        jnp.asarray(global_cols, jnp.int32),
        jnp.asarray(local_cols, jnp.int32),
        jnp.asarray(row_block, jnp.int32),
        V,
    )
    return J, s


def test_structure_products_equal_dense():
    rng = np.random.default_rng(0)
    J, s = _random_block_jacobian(rng)
    B = s.compressed(lambda t: jnp.asarray(J) @ t, jnp.float64)
    assert B.shape == (J.shape[0], s.n_colours)
    np.testing.assert_allclose(s.normal_matrix(B), J.T @ J, rtol=1e-13, atol=1e-13)
    r = rng.standard_normal(J.shape[0])
    x = rng.standard_normal(J.shape[1])
    np.testing.assert_allclose(s.transpose_apply(B, jnp.asarray(r)), J.T @ r, atol=1e-12)
    np.testing.assert_allclose(s.apply(B, jnp.asarray(x)), J @ x, atol=1e-12)


@pytest.mark.parametrize("damping", [None, 0.3])
def test_solver_equals_lstsq(damping):
    rng = np.random.default_rng(1)
    J, s = _random_block_jacobian(rng, V=5, rows_per_block=7)
    n = J.shape[1]
    b = rng.standard_normal(J.shape[0])
    Jx = jnp.asarray(J)
    if damping is None:
        op = lx.MatrixLinearOperator(Jx)
        vec = jnp.asarray(b)
        A, rhs = J, b
    else:
        op = lx.FunctionLinearOperator(
            lambda y: (Jx @ y, jnp.sqrt(damping) * y), jax.ShapeDtypeStruct((n,), jnp.float64)
        )
        vec = (jnp.asarray(b), jnp.zeros(n))
        A = np.vstack([J, np.sqrt(damping) * np.eye(n)])
        rhs = np.concatenate([b, np.zeros(n)])
    sol = lx.linear_solve(op, vec, BlockNormalCholesky(s))
    ref = np.linalg.lstsq(A, rhs, rcond=None)[0]
    np.testing.assert_allclose(sol.value, ref, rtol=1e-10, atol=1e-12)


def test_solver_reports_singular():
    rng = np.random.default_rng(2)
    J, s = _random_block_jacobian(rng)
    J[:, int(s.global_cols[0])] = 0.0  # a column no residual sees
    sol = lx.linear_solve(
        lx.MatrixLinearOperator(jnp.asarray(J)),
        jnp.ones(J.shape[0]),
        BlockNormalCholesky(s),
        throw=False,
    )
    assert sol.result != lx.RESULTS.successful


def test_detect_rows_recovers_blocks_and_rejects_mixed_rows():
    rng = np.random.default_rng(3)
    J, s = _random_block_jacobian(rng, V=6)
    gc, lc = np.asarray(s.global_cols), np.asarray(s.local_cols)
    rows = detect_rows(lambda T: T @ jnp.asarray(J).T, gc, lc, J.shape[1], jnp.float64)
    np.testing.assert_array_equal(rows, np.asarray(s.row_block))
    J[0, lc[0]] = 1.0
    J[0, lc[1]] = 1.0  # row 0 now touches two blocks
    assert detect_rows(lambda T: T @ jnp.asarray(J).T, gc, lc, J.shape[1], jnp.float64) is None


class _Toy(eqx.Module):
    g: jax.Array
    board_poses: jax.Array  # (V, 2): per-view parameters


def _toy_residuals(p, data):
    a, y = data  # a: (V, K, 3) features, y: (V, K)

    def view(pose, av, yv):
        pred = (
            av @ p.g
            + pose[0] * av[:, 0] ** 2
            + pose[1] * av[:, 1] * av[:, 2]
            + 0.1 * jnp.sin(p.g[1] * pose[1]) * av[:, 0]
        )
        return pred - yv

    return jax.vmap(view)(p.board_poses, a, y).reshape(-1)


def test_least_squares_block_equals_dense():
    rng = np.random.default_rng(4)
    V, K = 6, 9
    truth = _Toy(jnp.array([0.5, 1.2, -0.3]), jnp.asarray(rng.normal(size=(V, 2))))
    a = jnp.asarray(rng.normal(size=(V, K, 3)))
    y = jnp.zeros((V, K))
    y = -_toy_residuals(truth, (a, y)).reshape(V, K) + 1e-3 * rng.normal(size=(V, K))
    start = _Toy(truth.g + 0.1, truth.board_poses + 0.1)
    fits = [least_squares(_toy_residuals, start, (a, y), blocks=b) for b in ("board_poses", None)]
    for f in fits:
        assert f.converged
    np.testing.assert_allclose(fits[0].params.g, fits[1].params.g, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(
        fits[0].params.board_poses, fits[1].params.board_poses, rtol=1e-9, atol=1e-12
    )
    # and it is the optimum: the remaining Gauss–Newton step is a negligible fraction of
    # each parameter's standard deviation
    x, unravel, static = split(fits[0].params, free_spec(fits[0].params))
    f = lambda v: _toy_residuals(eqx.combine(unravel(v), static), (a, y))  # noqa: E731
    J, r = jax.jacfwd(f)(x), f(x)
    cov = np.linalg.inv(np.asarray(J.T @ J))
    step = cov @ np.asarray(J.T @ r)
    sigma = np.sqrt(np.diag(cov) * float(r @ r) / (len(r) - len(x)))
    assert np.max(np.abs(step) / sigma) < 1e-3


def test_block_layout_orders_local_columns_by_block():
    p = _Toy(jnp.zeros(3), jnp.zeros((4, 2)))
    _, unravel, _ = split(p, free_spec(p))
    gc, lc = block_layout(unravel, "board_poses")
    np.testing.assert_array_equal(gc, [0, 1, 2])
    np.testing.assert_array_equal(lc, 3 + np.arange(8).reshape(4, 2))
    gc, lc = block_layout(unravel, None)
    assert lc.shape == (1, 0) and len(gc) == 11
