"""Block-sparse normal equations for calibration Jacobians: a lineax linear solver.

A calibration Jacobian has two kinds of columns. *Global* columns (camera, laser plane,
stage) touch every residual; *local* columns (the six pose parameters of one board view)
touch only that view's residuals, so the local columns of different views never share a
row. Columns that share no row can be evaluated together in one Jacobian–vector product
(Curtis, Powell & Reid 1974): all views' k-th pose parameter share one "colour". The
compressed Jacobian `B = J S` then needs `n_global + n_local_per_view` products instead of
`n_global + n_views · n_local_per_view`, and the normal matrix `JᵀJ` is assembled from
`B` block by block, never forming the dense Jacobian.

`BlockNormalCholesky` solves the least-squares systems of optimistix's Gauss–Newton
family through these normal equations and a Cholesky factorisation. It accepts the plain
Jacobian `J` (Gauss–Newton, dogleg) and Levenberg–Marquardt's augmented operator
`[J; D]` (output `(J y, D y)` with a diagonal damping `D`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float, Int


class BlockStructure(eqx.Module):
    """Which columns are global and which belong to which block, and which block each
    residual row belongs to.

    **Fields:**
    - `global_cols`: `(ng,)` column indices of the global parameters.
    - `local_cols`: `(V, nl)` column index of local slot `s` of block `v`.
    - `row_block`: `(N,)` block of each residual row; `V` for rows no block touches.
    - `n_blocks`: V (static).
    """

    global_cols: Int[Array, " ng"]
    local_cols: Int[Array, "V nl"]
    row_block: Int[Array, " N"]
    n_blocks: int = eqx.field(static=True)

    @property
    def n(self) -> int:
        return int(self.global_cols.shape[0] + self.local_cols.size)

    @property
    def n_colours(self) -> int:
        return int(self.global_cols.shape[0] + self.local_cols.shape[1])

    def seeds(self, dtype) -> Float[Array, "c n"]:
        """One tangent per colour: unit vectors on the global columns, then, for each
        local slot, ones on that slot's column of every block."""
        ng, nl = self.global_cols.shape[0], self.local_cols.shape[1]
        S = jnp.zeros((ng + nl, self.n), dtype)
        S = S.at[jnp.arange(ng), self.global_cols].set(1.0)
        slots = jnp.broadcast_to(ng + jnp.arange(nl), self.local_cols.shape)
        return S.at[slots, self.local_cols].set(1.0)

    def colour(self) -> Int[Array, " n"]:
        """The colour (row of `seeds`) of every column."""
        ng, nl = self.global_cols.shape[0], self.local_cols.shape[1]
        c = jnp.zeros(self.n, jnp.int32).at[self.global_cols].set(jnp.arange(ng, dtype=jnp.int32))
        slots = jnp.broadcast_to(ng + jnp.arange(nl, dtype=jnp.int32), self.local_cols.shape)
        return c.at[self.local_cols].set(slots)

    def _split(self, B):
        ng = self.global_cols.shape[0]
        return B[:, :ng], B[:, ng:]

    def _segments(self, x):
        """Sum rows of `x` per block (rows of no block dropped)."""
        return jax.ops.segment_sum(x, self.row_block, self.n_blocks + 1)[: self.n_blocks]

    def normal_matrix(self, B: Float[Array, "N c"]) -> Float[Array, "n n"]:
        """`JᵀJ` from the compressed Jacobian `B = J Sᵀ`."""
        Bg, Bl = self._split(B)
        g, loc = self.global_cols, self.local_cols
        H = jnp.zeros((self.n, self.n), B.dtype)
        H = H.at[g[:, None], g[None, :]].set(Bg.T @ Bg)
        if loc.shape[1]:
            Hgl = self._segments(Bg[:, :, None] * Bl[:, None, :])  # (V, ng, nl)
            Hll = self._segments(Bl[:, :, None] * Bl[:, None, :])  # (V, nl, nl)
            H = H.at[g[None, :, None], loc[:, None, :]].set(Hgl)
            H = H.at[loc[:, :, None], g[None, None, :]].set(jnp.swapaxes(Hgl, 1, 2))
            H = H.at[loc[:, :, None], loc[:, None, :]].set(Hll)
        return H

    def transpose_apply(self, B: Float[Array, "N c"], r: Float[Array, " N"]) -> Float[Array, " n"]:
        """`Jᵀ r` from the compressed Jacobian."""
        Bg, Bl = self._split(B)
        out = jnp.zeros(self.n, B.dtype).at[self.global_cols].set(Bg.T @ r)
        if self.local_cols.shape[1]:
            out = out.at[self.local_cols].set(self._segments(Bl * r[:, None]))
        return out

    def apply(self, B: Float[Array, "N c"], x: Float[Array, " n"]) -> Float[Array, " N"]:
        """`J x` from the compressed Jacobian."""
        Bg, Bl = self._split(B)
        out = Bg @ x[self.global_cols]
        if self.local_cols.shape[1]:
            block = jnp.minimum(self.row_block, self.n_blocks - 1)
            xl = x[self.local_cols][block]  # (N, nl): the row's own block's values
            out = out + jnp.where(self.row_block < self.n_blocks, jnp.sum(Bl * xl, axis=1), 0.0)
        return out

    def compressed(self, mv, dtype) -> Float[Array, "N c"]:
        """`B = J Sᵀ` from a Jacobian–vector product `mv` (one call per colour)."""
        return jax.vmap(mv, out_axes=1)(self.seeds(dtype))


def _flat(structure, what: str):
    leaves = jax.tree.leaves(structure)
    if len(leaves) != 1 or len(leaves[0].shape) != 1:
        raise ValueError(f"BlockNormalCholesky needs a flat vector {what}, got {structure}")
    return leaves[0]


class BlockNormalCholesky(lx.AbstractLinearSolver):
    """Least squares `min |A x − b|` through block-assembled normal equations.

    `A` is `J` or `[J; D]` (D diagonal, as in Levenberg–Marquardt's damped step), `J`
    with the column/row structure of `structure`. The normal matrix `AᵀA` is formed
    from `n_colours` Jacobian–vector products and factorised by Cholesky; a singular
    (not positive definite) matrix is reported as `RESULTS.singular`.
    """

    structure: BlockStructure

    def init(self, operator, options):
        del options
        in_struct = _flat(operator.in_structure(), "input")
        out = operator.out_structure()
        augmented = isinstance(out, tuple) and len(out) == 2
        if augmented:
            out_r, out_d = out
            if jax.tree.structure(out_d) != jax.tree.structure(in_struct) or (
                out_d.shape != in_struct.shape
            ):
                raise ValueError("BlockNormalCholesky: the damping block must match the input")
        else:
            out_r = out
        out_r = _flat(out_r, "output")
        s = self.structure
        if in_struct.shape[0] != s.n or out_r.shape[0] != s.row_block.shape[0]:
            raise ValueError(
                f"BlockNormalCholesky: operator {out_r.shape} × {in_struct.shape} does not "
                f"match the block structure ({s.row_block.shape[0]} rows, {s.n} columns)"
            )
        dtype = in_struct.dtype
        outs = jax.vmap(operator.mv, out_axes=1)(s.seeds(dtype))
        if augmented:
            B, Bd = outs
            d = Bd[jnp.arange(s.n), s.colour()]  # the diagonal of D
        else:
            B, d = outs, jnp.zeros(s.n, dtype)
        H = s.normal_matrix(B) + jnp.diag(d * d)
        factor, _ = jsp.linalg.cho_factor(H)
        return factor, B, d, augmented

    def compute(self, state, vector, options):
        del options
        factor, B, d, augmented = state
        if augmented:
            r, z = vector
            rhs = self.structure.transpose_apply(B, r) + d * z
        else:
            rhs = self.structure.transpose_apply(B, vector)
        s = self.structure
        x = jsp.linalg.cho_solve((factor, False), rhs)
        # One step of iterative refinement with the normal-equation residual computed
        # from J (not from the rounded JᵀJ): forming JᵀJ squares the condition number,
        # and the weakly determined directions of a calibration (cond(JᵀJ) ~ 1e11)
        # would otherwise carry ~1e-5 relative error from step to step.
        ax = s.transpose_apply(B, s.apply(B, x)) + d * d * x
        x = x + jsp.linalg.cho_solve((factor, False), rhs - ax)
        ok = jnp.all(jnp.isfinite(x))
        result = lx.RESULTS.where(ok, lx.RESULTS.successful, lx.RESULTS.singular)
        return jnp.where(ok, x, 0.0), result, {}

    def transpose(self, state, options):
        raise NotImplementedError("BlockNormalCholesky does not support transposed solves")

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


def block_layout(unravel, local_path: str | None) -> tuple[np.ndarray, np.ndarray]:
    """`(global_cols, local_cols)` of the flat state vector.

    `local_path` names the sub-tree of per-block parameters (leaves with a leading block
    axis, e.g. `"board_poses"`); every other free scalar is global. Returns an empty
    `(V, 0)` local layout when the sub-tree is absent or frozen.
    """
    n = int(sum(int(np.prod(s, dtype=int)) for s in unravel.shapes))
    index = unravel(np.arange(n))
    local = None
    if local_path is not None:
        node = index
        for name in local_path.split("."):
            node = getattr(node, name, None)
            if node is None:
                break
        local = node
    leaves = [np.asarray(x) for x in jax.tree.leaves(local)] if local is not None else []
    if not leaves:
        return np.arange(n), np.zeros((1, 0), dtype=np.int64)
    V = leaves[0].shape[0] if leaves[0].ndim else 0
    if V == 0 or any(x.ndim == 0 or x.shape[0] != V for x in leaves):
        raise ValueError(f"the leaves under {local_path!r} need one common leading block axis")
    local_cols = np.concatenate([x.reshape(V, -1) for x in leaves], axis=1)
    mask = np.ones(n, bool)
    mask[local_cols.ravel()] = False
    return np.nonzero(mask)[0], local_cols


def row_probes(local_cols: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """The two tangents `(2, n)` of [`detect_rows`][]: a random value `u_s` on local slot
    `s` of every block, then `ρ_v u_s` with a distinct `ρ_v` per block."""
    V, nl = local_cols.shape
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.5, 1.5, nl) * rng.choice([-1.0, 1.0], nl)
    rho = 1.0 + np.arange(V, dtype=float) / max(V, 1)
    t = np.zeros((2, n))
    t[0, local_cols] = u[None, :]
    t[1, local_cols] = rho[:, None] * u[None, :]
    return t


def rows_from_probes(a, b, n_blocks: int):
    """The block of every residual row from `a = J t1`, `b = J t2` ([`row_probes`][]).

    A row that depends on block v only gives `b / a = ρ_v`; rows with `a = 0` touch no
    block (block `n_blocks`). Traceable (jit-compatible): returns `(rows, ok)`, `ok`
    False when some row mixes blocks (no block structure).
    """
    V = n_blocks
    rho = 1.0 + jnp.arange(V, dtype=a.dtype) / max(V, 1)
    scale = jnp.max(jnp.abs(a)) if a.size else jnp.zeros((), a.dtype)
    touched = jnp.abs(a) > 1e-12 * jnp.maximum(scale, 1e-300)
    ratio = jnp.where(touched, b / jnp.where(touched, a, 1.0), 0.0)
    block = jnp.rint((ratio - 1.0) * max(V, 1)).astype(jnp.int32)
    good = (block >= 0) & (block < V) & (jnp.abs(ratio - rho[jnp.clip(block, 0, V - 1)]) < 1e-6)
    ok = jnp.all(good | ~touched)
    return jnp.where(touched, block, V).astype(jnp.int32), ok


def detect_rows(jvp, global_cols, local_cols, n, dtype, seed: int = 0):
    """The block of every residual row, from two Jacobian–vector products.

    Tangent 1 puts a random value `u_s` on local slot `s` of every block, tangent 2 the
    values `ρ_v u_s` with a distinct `ρ_v` per block ([`row_probes`][]). A row that
    depends on block v only gives `(J t2) / (J t1) = ρ_v`; rows with `J t1 = 0` touch no
    block. Returns the row blocks, or None when some row mixes blocks (no block
    structure). (The calibration's solver does the same inside its compiled start
    program, `_solve._normal_detect`.)
    """
    del global_cols
    t = row_probes(np.asarray(local_cols), n, seed)
    a, b = jvp(jnp.asarray(t, dtype))
    rows, ok = rows_from_probes(jnp.asarray(a), jnp.asarray(b), local_cols.shape[0])
    return np.asarray(rows, dtype=np.int64) if bool(ok) else None
