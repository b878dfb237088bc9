"""The block normal-equations solver against dense linear algebra."""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from scheimflux.calibration.core._linear import (
    BlockNormalCholesky,
    BlockStructure,
    block_layout,
    detect_rows,
)
from scheimflux.calibration.core._solve import free_spec, least_squares, split


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
    # The reference is independent of the block solver: optimistix's Levenberg–Marquardt
    # with its default (dense QR) linear solver on the flattened problem, solved to 1e-12,
    # and SciPy's MINPACK LM. Agreement is judged in units of each parameter's σ (from
    # the dense JᵀJ at the reference): two solvers stopped at the optimum agree to far
    # below σ, whatever their stopping rules.
    import optimistix as optx
    import scipy.optimize

    rng = np.random.default_rng(4)
    V, K = 6, 9
    truth = _Toy(jnp.array([0.5, 1.2, -0.3]), jnp.asarray(rng.normal(size=(V, 2))))
    a = jnp.asarray(rng.normal(size=(V, K, 3)))
    y = jnp.zeros((V, K))
    y = -_toy_residuals(truth, (a, y)).reshape(V, K) + 1e-3 * rng.normal(size=(V, K))
    start = _Toy(truth.g + 0.1, truth.board_poses + 0.1)
    block = least_squares(_toy_residuals, start, (a, y), blocks="board_poses")
    assert block.converged

    def flat(p):
        return jnp.concatenate([p.g, p.board_poses.reshape(-1)])

    def unflat(v):
        return _Toy(v[:3], v[3:].reshape(V, 2))

    def res(v, args):
        return _toy_residuals(unflat(v), args)

    sol = optx.least_squares(
        res, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12), flat(start), (a, y), max_steps=500
    )
    assert sol.result == optx.RESULTS.successful
    ref = np.asarray(sol.value)
    mp = scipy.optimize.least_squares(
        lambda v: np.asarray(res(jnp.asarray(v), (a, y))), np.asarray(flat(start)),
        method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
    )  # fmt: skip
    J = np.asarray(jax.jacfwd(res)(jnp.asarray(ref), (a, y)))
    r = np.asarray(res(jnp.asarray(ref), (a, y)))
    cov = np.linalg.inv(J.T @ J)
    sigma = np.sqrt(np.diag(cov) * float(r @ r) / (len(r) - len(ref)))
    assert np.max(np.abs(mp.x - ref) / sigma) < 1e-6  # the two dense references agree
    got = np.asarray(flat(block.params))
    assert np.max(np.abs(got - ref) / sigma) < 1e-3
    # the dense fit and the block fit also reach the same cost to float64 noise
    assert block.cost == pytest.approx(0.5 * float(r @ r), rel=1e-9)
    # and the start was far from the optimum in these units (the test can fail)
    assert np.max(np.abs(np.asarray(flat(start)) - ref) / sigma) > 100


def test_block_layout_orders_local_columns_by_block():
    p = _Toy(jnp.zeros(3), jnp.zeros((4, 2)))
    _, unravel, _ = split(p, free_spec(p))
    gc, lc = block_layout(unravel, "board_poses")
    np.testing.assert_array_equal(gc, [0, 1, 2])
    np.testing.assert_array_equal(lc, 3 + np.arange(8).reshape(4, 2))
    gc, lc = block_layout(unravel, None)
    assert lc.shape == (1, 0) and len(gc) == 11
