"""Levenberg–Marquardt on a parameter pytree: freezing, scaling, status and timing.

The free leaves of the pytree are flattened into one vector, scaled so that every column
of the initial Jacobian has unit norm (a unitless state), and solved with optimistix's
Levenberg–Marquardt using autodiff Jacobians. The damped Gauss–Newton systems go through
`BlockNormalCholesky`: the board poses' columns of different views share no residual,
so one Jacobian–vector product serves the same pose parameter of every view and the
normal equations are assembled block by block (26 products instead of 110 for 15 views,
and no dense QR of a 20 000 × 110 matrix per step). Everything that changes between
solves of the same shape travels as array arguments, so a second calibration with the
same number of views and points reuses the compiled solver.

(One module, longer than most: `least_squares`, its start and end programs, the rank
check, the released parameters' profile and `refine` all work on the same flattened,
column-scaled state vector and its block structure.)
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from ..._export import exported_jit
from ._linear import (
    BlockStructure,
    block_layout,
    row_probes,
    rows_from_probes,
)
from ._lm import BlockLevenbergMarquardt, result_message

#: XLA compiler options for programs a calibration runs once or a few times (a solve's
#: start and end, the residual summaries, the axis warning): LLVM's backend at -O0 and
#: without its expensive passes. Their run is milliseconds either way, their compile
#: time is most of a cold calibration's (docs/compile-time.md); the Levenberg–Marquardt
#: loop, run for every step, keeps XLA's default optimisation.
ONE_SHOT = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


class RankDeficientError(ValueError):
    """The data cannot determine the free parameters together (a null direction of the
    column-scaled Jacobian); the message names the parameters involved, `.nulls` holds
    the directions (`null_directions`' list; empty where not known)."""

    def __init__(self, message: str, nulls=()):
        super().__init__(message)
        self.nulls = list(nulls)


# An eigenvalue of the column-scaled JᵀJ below this fraction of the largest is a null
# direction. JᵀJ is known to ~1e-16 relative (float64), so exact gauge freedoms show as
# ~1e-16; the weakest real directions of a calibration (the boards' common depth
# against the magnification) are ~1e-11.
RANK_RTOL = 1e-13


def null_directions(H, labels, *, rtol: float = RANK_RTOL, top: int = 5):
    """The null directions of a normal matrix `H` (column-scaled to unit diagonal).

    **Returns:** a list of `(relative eigenvalue, [(label, component), ...])`, the
    components of each direction's unit vector above 0.1, largest first.
    """
    H = np.asarray(H, dtype=np.float64)
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    lam, V = np.linalg.eigh(H / np.outer(d, d))
    big = max(float(lam[-1]), 1e-300)
    out = []
    for k in np.flatnonzero(lam < rtol * big):
        v = V[:, k]
        order = np.argsort(-np.abs(v))[:top]
        comps = [(labels[i], float(v[i])) for i in order if abs(v[i]) > 0.1]
        out.append((float(lam[k] / big), comps))
    return out


def _only_distortion(components) -> bool:
    return all(".distortion." in lab for lab, _ in components)


def _check_rank(H, params, spec) -> None:
    # A null direction within the distortion coefficients alone (e.g. OpenCV's rational
    # k1..k6 on a mildly distorting lens: numerator and denominator trade off) leaves the
    # projection and every other parameter determined; `fit_diagnostics` reports it.
    # Any other null direction is refused.
    nulls = [n for n in null_directions(H, parameter_labels(params, spec))
             if not _only_distortion(n[1])]  # fmt: skip
    if nulls:
        lam, comps = nulls[0]
        names = ", ".join(f"{lab} ({c:+.2f})" for lab, c in comps)
        # the system parameters (not the per-view poses) in every null direction
        others = sorted(
            {lab for _, cs in nulls for lab, _ in cs if not lab.startswith("board_poses")}
            - {lab for lab, _ in comps}
        )
        more = f"; the others also involve {', '.join(others)}" if others else ""
        raise RankDeficientError(
            f"the data do not determine these free parameters together: {names} "
            f"(a null direction of the scaled Jacobian, eigenvalue {lam:.1e} × max; "
            f"{len(nulls)} such direction(s){more}); freeze one of them",
            nulls,
        )


class NotConvergedError(RuntimeError):
    """Levenberg–Marquardt did not converge; `.fit` holds the last iterate."""

    def __init__(self, message: str, fit: Fit):
        super().__init__(message)
        self.fit = fit


@dataclasses.dataclass(frozen=True)
class Released:
    """The cost's profile over parameters held in a solve (`least_squares`'s `release`)
    at its solution: the cost `c(p) = min_q ½|r(p, q)|²` with the solved parameters `q`
    re-optimised.

    **Fields:**
    - `labels`: the released parameters.
    - `gradient`: `dc/dp = J_pᵀ (I − P_q) r` (physical units): the envelope theorem's
      `J_pᵀ r`, with the projection `P_q` onto the solved parameters' columns removing,
      to first order, what the solve left of its own optimum.
    - `hessian`: the Gauss–Newton Hessian of the profile, `J_pᵀ (I − P_q) J_p` (the
      Schur complement of `JᵀJ`), from a QR factorisation of the column-scaled `J_q`:
      along the weakest directions of a calibration (relative eigenvalues ~1e-13 of the
      scaled `JᵀJ`) the Schur complement formed from `JᵀJ` loses every digit.
    """

    labels: tuple[str, ...]
    gradient: np.ndarray
    hessian: np.ndarray


def _dense_jacobian(structure, B: np.ndarray) -> np.ndarray:
    """The Jacobian `J` (rows × state vector) from the compressed one and its structure."""
    gc = np.asarray(structure.global_cols)
    lc = np.asarray(structure.local_cols)
    rows = np.asarray(structure.row_block)
    J = np.zeros((B.shape[0], gc.size + lc.size), B.dtype)
    J[:, gc] = B[:, : gc.size]
    for v in range(structure.n_blocks):
        m = rows == v
        J[np.ix_(m, lc[v])] = B[m][:, gc.size :]
    return J


def _released(structure, B, r, free, reported, labels) -> Released | None:
    """[`Released`][] for the parameters reported free but held in the solve (`labels`:
    the state vector's names, or a callable giving them)."""
    ip = np.flatnonzero(reported & ~free)
    if ip.size == 0:
        return None
    labels = labels() if callable(labels) else labels
    B = np.asarray(B)
    J = _dense_jacobian(structure, B)
    iq = np.flatnonzero(free)
    col = np.linalg.norm(J, axis=0)
    d = np.where(col > 0, 1.0 / np.where(col > 0, col, 1.0), 1.0)
    Q, _ = np.linalg.qr(J[:, iq] * d[iq])
    Jp = J[:, ip]
    P = Jp - Q @ (Q.T @ Jp)
    return Released(tuple(labels[i] for i in ip), P.T @ r, P.T @ P)


@dataclasses.dataclass(frozen=True)
class Fit:
    """The outcome of one least-squares solve.

    **Fields:**
    - `params`: the solved pytree (frozen leaves untouched).
    - `converged`: whether optimistix reported success, or the solve reached its step
      limit within `AT_OPTIMUM_SIGMA` of the optimum (`stats["remaining_step_sigma"]`,
      [`remaining_step_sigma`][]).
    - `message`: optimistix's result message ("" when converged).
    - `steps`: number of Levenberg–Marquardt steps (accepted and rejected).
    - `residuals`: the final (weighted, unitless) residual vector.
    - `initial_cost`, `cost`: 0.5 · sum of squared residuals before and after.
    - `time_s`: wall time of the solve (including compilation on first use).
    - `free_mask`: the filter spec used (True on free leaves).
    - `scale`: the per-parameter column scale D of the initial Jacobian.
    - `normal_matrix`, `labels`, `n_observations`: `JᵀJ` at the solution over the free
      parameters (physical units), their names, the residuals of non-zero weight.
    - `result`, `stats`: optimistix's `Solution.result` and `Solution.stats` (None and
      empty for a fit read back from a file).
    - `released`: for a solve with `release`, the profile of the cost over the
      released parameters at the solution ([`Released`][]); else None.
    """

    params: eqx.Module
    converged: bool
    message: str
    steps: int
    residuals: jax.Array
    initial_cost: float
    cost: float
    time_s: float
    free_mask: object
    scale: jax.Array
    normal_matrix: np.ndarray | None = None  # JᵀJ at the solution (physical units)
    labels: tuple[str, ...] = ()  # the free parameters, in the order of its rows
    n_observations: int = 0  # residuals with non-zero weight
    result: optx.RESULTS | None = None  # optimistix's result of the solve
    stats: dict = dataclasses.field(default_factory=dict)  # optimistix's `Solution.stats`
    released: Released | None = None  # the profile over the released parameters

    @property
    def rms(self) -> float:
        r = np.asarray(self.residuals)
        return float(np.sqrt(np.mean(r**2))) if r.size else 0.0


_FREEZE_ALIASES = {"stage.R_m_c": "stage.T_m_c.rotvec", "stage.t_m_c": "stage.T_m_c.translation"}


def _is_module(node) -> bool:
    return dataclasses.is_dataclass(node) and not isinstance(node, type)


def free_spec(params, freeze: Sequence[str] = ()):
    """Filter spec with True on inexact-array leaves, False under each frozen path.

    Paths are attribute names joined by dots, e.g. `"camera.dx"`, `"board_poses"`,
    `"stage.T_m_c.translation"` (`"stage.R_m_c"` and `"stage.t_m_c"` name the stage's
    rotation and translation). A path into a block that `params` does not hold yet
    (e.g. the stage during the camera solve) is skipped; unknown names raise
    `ValueError` listing the names there.
    """
    spec = jax.tree.map(eqx.is_inexact_array, params)
    for path in freeze:
        path = _FREEZE_ALIASES.get(path, path)
        node = params
        for name in path.split("."):
            if node is None:
                break
            names = [f.name for f in dataclasses.fields(node)] if _is_module(node) else []
            if name not in names:
                raise ValueError(
                    f"cannot freeze {path!r}: no parameter {name!r} there"
                    + (f" (there: {', '.join(names)})" if names else "")
                )
            node = getattr(node, name)
        if node is None:
            continue

        def where(tree, _path=path):
            n = tree
            for name in _path.split("."):
                n = getattr(n, name)
            return n

        spec = eqx.tree_at(where, spec, replace=jax.tree.map(lambda _: False, node))
    return spec


def parameter_labels(params, spec) -> list[str]:
    """Names of the free scalars, in the order of the flattened state vector."""
    free, _ = eqx.partition(params, spec)
    labels = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(free)[0]:
        name = "".join(
            f".{p.name}" if hasattr(p, "name") else f"[{getattr(p, 'idx', getattr(p, 'key', p))}]"
            for p in path
        ).lstrip(".")
        if np.ndim(leaf) == 0:
            labels.append(name)
        else:
            labels.extend(f"{name}{list(ix)}" for ix in np.ndindex(np.shape(leaf)))
    return labels


def _unscaled(x, args):
    fn, unravel, static, data = args
    return fn(eqx.combine(unravel(x), static), data)


def _scaled(y, args):
    fn, unravel, static, data, x0, scale = args
    return fn(eqx.combine(unravel(x0 + y * scale), static), data)


@eqx.filter_jit
def _jacobian(x, args):
    return jax.jacfwd(_unscaled)(x, args)


class _Unravel:
    """Rebuild the free pytree from the flat vector; equal (and hashing equal) for equal
    structures, so jitted solvers are reused across solves of the same shape."""

    def __init__(self, tree):
        leaves, self.treedef = jax.tree.flatten(tree)
        self.shapes = tuple(tuple(np.shape(x)) for x in leaves)
        self.dtypes = tuple(str(jnp.result_type(x)) for x in leaves)
        self._key = (self.treedef, self.shapes, self.dtypes)

    def __eq__(self, other):
        return isinstance(other, _Unravel) and self._key == other._key

    def __hash__(self):
        return hash(self._key)

    def export_key(self) -> str:
        return repr(self._key)

    def __call__(self, flat):
        out, i = [], 0
        for shape in self.shapes:
            n = int(np.prod(shape, dtype=int))
            out.append(flat[i : i + n].reshape(shape))
            i += n
        return jax.tree.unflatten(self.treedef, out)


def split(params, spec):
    """`(x0, unravel, static)`: the free leaves as a flat vector and how to rebuild."""
    free, static = eqx.partition(params, spec)
    x0, _ = ravel_pytree(free)
    return x0, _Unravel(free), static


def _split_host(params, spec):
    """[`split`][] with the state vector as a NumPy array (no device program)."""
    free, static = eqx.partition(params, spec)
    leaves = [np.asarray(x) for x in jax.tree.leaves(free)]
    dtype = np.result_type(*leaves) if leaves else np.float64
    x0 = np.concatenate([np.ravel(x).astype(dtype) for x in leaves] or [np.zeros(0, dtype)])
    return x0, _Unravel(free), static


def jacobian(fn: Callable, params, data, spec):
    """Jacobian of `fn(params, data)` w.r.t. the free parameters (physical units)."""
    x0, unravel, static = split(params, spec)
    return _jacobian(x0, (fn, unravel, static, data))


def observed_pixels(data) -> tuple:
    """The observed pixel arrays of the residual data (`CalibrationData`): corners,
    stripe and gauge pixels, and the table target's corners and stripe where present."""
    out = (data.corners, data.stripe, data.gauge)
    if getattr(data, "table", None) is not None:
        out += (data.table.corners, data.table.stripe)
    return out


def own_pixel_gains(fn: Callable, params, data):
    """`|∂r_i/∂p_i|²` of every residual of `fn(params, data)` for its own observed pixel
    (traceable; see `metrology.pixel_noise_gains`): every residual of the joint problems
    depends on one observed pixel, so one JVP with every u tangent 1 gives each
    residual's own `∂r_i/∂u_i`, one more its `∂r_i/∂v_i`."""
    pix = observed_pixels(data)

    def res(p):
        return fn(params, eqx.tree_at(observed_pixels, data, p))

    out = jnp.zeros(())
    for axis in (0, 1):
        tan = tuple(jnp.zeros_like(p).at[..., axis].set(1.0) for p in pix)
        out = out + jax.jvp(res, (pix,), (tan,))[1] ** 2
    return out


@exported_jit
def _linearised(x, args, gains: bool):
    fn, unravel, static, data = args
    J, r = jax.jacfwd(lambda v: (_unscaled(v, args),) * 2, has_aux=True)(x)
    a = own_pixel_gains(fn, eqx.combine(unravel(x), static), data) if gains else None
    return r, J, a


def linearised(fn: Callable, params, data, spec, *, pixel_gains: bool = False):
    """`(r, J, a)`: the residuals `fn(params, data)`, their Jacobian w.r.t. the free
    parameters (physical units) and, with `pixel_gains`, each residual's gain from the
    noise of its own observed pixel, `a_i = |∂r_i/∂p_i|²` (else None; see
    `metrology.pixel_noise_gains`), as NumPy float64 arrays.

    One exported program, so a process after the first with the same shapes neither
    traces nor compiles it (the residuals op by op took seconds for a joint problem). It
    is compiled with XLA's full optimisation: without the expensive passes (as the
    solver's one-off programs) it ran 2-3x slower (2.3-3.0 s against 0.9-1.5 s for
    49026 residuals × 68 parameters).
    """
    x0, unravel, static = split(params, spec)
    r, J, a = _linearised(x0, (fn, unravel, static, data), bool(pixel_gains))
    f64 = lambda v: None if v is None else np.asarray(v, dtype=np.float64)  # noqa: E731
    return f64(r), f64(J), f64(a)


def levenberg_marquardt(structure: BlockStructure, rtol: float, atol: float, mask=None):
    """Levenberg–Marquardt with the block normal-equations solver
    ([`BlockLevenbergMarquardt`][], on optimistix's public extension points).

    Convergence is judged on RMS changes (of the unit-scaled state and of the residuals,
    in units of their noise σ): with a max-norm a single weakly determined direction,
    whose Gauss–Newton step is only known to ~1e-5 of its (statistically irrelevant)
    size, keeps the solve stepping long after the cost has stopped changing. `mask`
    (1 free, 0 held; default all free) keeps held components out of that RMS.
    """
    if mask is None:
        mask = jnp.ones(structure.n)
    return BlockLevenbergMarquardt(structure, mask, rtol, atol)


@exported_jit(compiler_options=ONE_SHOT)
def _normal_at(x, args, structure: BlockStructure, z):
    """Residual, block normal matrix, `J z` twice to check the structure against:
    from the compressed Jacobian and the rows' blocks, and directly (forward mode only:
    no reverse pass, which would double the program), and the compressed Jacobian `B`."""
    r, jvp = jax.linearize(lambda v: _unscaled(v, args), x)
    JT = jax.vmap(jvp, out_axes=1)(jnp.concatenate([z[None], structure.seeds(x.dtype)]))
    B = JT[:, 1:]
    return r, structure.normal_matrix(B), structure.apply(B, z), JT[:, 0], B


@exported_jit(compiler_options=ONE_SHOT)
def _normal_detect(x, args, global_cols, local_cols, probes, z):
    """`_normal_at` with the rows' blocks found in the same program.

    One batch of Jacobian–vector products serves the two row probes
    ([`row_probes`][]), the check vector `z` and the compressed Jacobian (its seeds
    depend on the columns only), so a solve's start and end are one compiled program.

    **Returns:** `(r, JᵀJ, J z from the structure, J z, B, row blocks, ok)`; `ok`
    False when some row mixes blocks (then the normal matrix is not valid and the caller
    goes dense).
    """
    V = local_cols.shape[0]
    seeds = BlockStructure(global_cols, local_cols, jnp.zeros((1,), jnp.int32), V).seeds(x.dtype)
    tangents = jnp.concatenate([probes.astype(x.dtype), z[None], seeds])
    r, jvp = jax.linearize(lambda v: _unscaled(v, args), x)
    JT = jax.vmap(jvp, out_axes=1)(tangents)
    rows, ok = rows_from_probes(JT[:, 0], JT[:, 1], V)
    structure = BlockStructure(global_cols, local_cols, rows, V)
    B = JT[:, 3:]
    return r, structure.normal_matrix(B), structure.apply(B, z), JT[:, 2], B, rows, ok


def _dense(n: int, n_rows: int) -> BlockStructure:
    """All columns global: dense normal equations."""
    return BlockStructure(
        jnp.arange(n, dtype=jnp.int32),
        jnp.zeros((1, 0), jnp.int32),
        jnp.zeros(n_rows, jnp.int32),
        0,
    )


def _normal_equations(x, args, layout, z):
    """`(structure, r, JᵀJ, J z from the structure, J z, B)` at `x`: block structure where
    the rows split by block (`layout` = `(global_cols, local_cols)`, or a
    `BlockStructure` to reuse), dense normal equations otherwise."""
    if isinstance(layout, BlockStructure):
        return (layout, *_normal_at(x, args, layout, z))
    global_cols, local_cols = layout
    n = x.shape[0]
    if local_cols.shape[1]:
        gc = jax.device_put(np.asarray(global_cols, np.int32))
        lc = jax.device_put(np.asarray(local_cols, np.int32))
        probes = jax.device_put(np.asarray(row_probes(local_cols, n), x.dtype))
        r, H, Bz, Jz, B, rows, ok = _normal_detect(x, args, gc, lc, probes, z)
        if bool(ok):
            return BlockStructure(gc, lc, rows, int(local_cols.shape[0])), r, H, Bz, Jz, B
    n_rows = eqx.filter_eval_shape(_unscaled, x, args).shape[0]
    structure = _dense(n, n_rows)
    return (structure, *_normal_at(x, args, structure, z))


def block_structure(fn, params, data, spec, blocks: str | None = "board_poses"):
    """The `BlockStructure` of `fn`'s Jacobian at `params`, and `(x0, unravel, static)`.

    Columns under `blocks` are local to their block (leading axis); rows are assigned to
    blocks by two probing Jacobian–vector products. Falls back to all-global columns
    (dense normal equations) where the rows do not split by block.
    """
    x0, unravel, static = split(params, spec)
    z = jnp.zeros_like(x0)
    structure, *_ = _normal_equations(
        x0, (fn, unravel, static, data), block_layout(unravel, blocks), z
    )
    return structure, (x0, unravel, static)


def least_squares(
    fn: Callable,
    params,
    data,
    *,
    freeze: Sequence[str] = (),
    spec=None,
    hold: Sequence[str] = (),
    release: Sequence[str] = (),
    blocks: str | None = "board_poses",
    max_steps: int = 200,
    rtol: float = 1e-5,
    atol: float = 1e-5,
    throw: bool = True,
    check_rank: bool = True,
) -> Fit:
    """Minimise `0.5 |fn(params, data)|²` over the free leaves of `params`.

    **Arguments:**
    - `fn`: a module-level (hashable) function `(params, data) -> residual vector`.
    - `params`: initial parameter pytree (`eqx.Module`).
    - `data`: pytree of arrays passed to `fn`.
    - `freeze`: dotted paths of leaves or sub-trees to hold fixed (or give `spec`).
    - `hold`: further paths held fixed *at run time*: they stay in the compiled state
      vector with a column scale of zero, so a solve that holds them (e.g. the ideal
      camera before its distortion is freed) runs the same compiled program as the
      solve that frees them. The `Fit` reports them as frozen.
    - `release`: paths of `hold` that the `Fit` reports as free (its `free_mask`,
      `normal_matrix`, `labels`): held during the solve (their value placed by the
      caller, e.g. at the minimum of a profile), free for the covariance, so that their
      own uncertainty is not hidden. The rank check is on the solved parameters.
    - `blocks`: the sub-tree of per-view parameters (leading view axis) whose columns
      are local to their view's residuals; the normal equations are assembled block by
      block (`BlockNormalCholesky`). None: dense normal equations.
    - `rtol`, `atol`: stop when the RMS change of the unit-scaled state and of the
      residuals (units of σ) fall below `atol + rtol·|value|`: 1e-5 σ is far below
      any statistical meaning, and above the float64 noise of the residuals along the
      weakest directions (which would otherwise keep LM stepping on rounding noise).
    - `throw`: raise `NotConvergedError` when LM fails (the error carries the `Fit`).
    - `check_rank`: raise `RankDeficientError`, naming the parameters, when the free
      parameters are not determined together at the solution (see [`null_directions`][]).

    **Returns:** a `Fit`.
    """
    if spec is None:
        spec = free_spec(params, freeze)
    t0 = time.perf_counter()
    # Host-side work (the state vector, checks, scaling, the solution's pytree) is
    # NumPy: every eager jax.numpy call on a new shape is one more XLA program to trace
    # and compile (docs/compile-time.md); the device sees the solver programs only.
    x0_h, unravel, static = _split_host(params, spec)
    x0 = jax.device_put(x0_h)
    args0 = (fn, unravel, static, data)
    layout = block_layout(unravel, blocks)
    z = jax.device_put(np.random.default_rng(1).standard_normal(x0_h.shape).astype(x0_h.dtype))
    structure, r0, H, Bz, Jz, _ = _normal_equations(x0, args0, layout, z)
    r0, H, Bz, Jz = (np.asarray(a) for a in (r0, H, Bz, Jz))
    if not np.all(np.isfinite(H)):
        raise ValueError("the Jacobian is not finite at the initial parameters")
    if not np.all(np.isfinite(r0)):
        bad = int(np.sum(~np.isfinite(r0)))
        raise ValueError(f"{bad} residuals are not finite at the initial parameters")
    # the compressed Jacobian and the rows' blocks (from which JᵀJ is assembled) must
    # rebuild J z for a random z exactly (to rounding): a row given to the wrong block
    # would not
    if not np.allclose(Bz, Jz, rtol=1e-8, atol=1e-10 * float(np.max(np.abs(Jz)))):
        raise RuntimeError("internal error: the block Jacobian does not match J")
    col = np.sqrt(np.diag(H))
    scale = np.where(col > 0, 1.0 / np.where(col > 0, col, 1.0), 1.0)
    free, spec_free = np.ones(x0_h.shape, bool), spec
    reported, spec_reported, scale_reported = free, spec, scale
    if hold:
        free, spec_free = _held(params, spec, hold)
        kept = tuple(h for h in hold if h not in tuple(release))
        reported, spec_reported = _held(params, spec, kept) if kept else (reported, spec)
        scale = np.where(free, scale, 0.0)
    args = (fn, unravel, static, data, x0, jax.device_put(scale))
    solver = levenberg_marquardt(structure, rtol, atol, jax.device_put(free.astype(x0_h.dtype)))
    value, result, num_steps = _lm_solve(
        jax.device_put(np.zeros_like(x0_h)), args, solver, max_steps
    )
    result = jax.tree.unflatten(_RESULT_TREE, [result])
    stats = {"num_steps": num_steps, "max_steps": max_steps}
    # residuals and JᵀJ at the solution (for the covariance): the start's program again
    # (rows re-detected; the start's structure if they no longer split the same way)
    x_end_h = x0_h + np.asarray(value) * scale
    x_end = jax.device_put(x_end_h)
    end = _normal_equations(x_end, args0, layout if structure.n_blocks else structure, z)
    if end[0].n_blocks != structure.n_blocks:
        end = _normal_equations(x_end, args0, structure, z)
    end_structure, r, H_all, _, _, B_end = end
    r_h = np.asarray(r)
    H_all = np.asarray(H_all)
    H_end = H_all[np.ix_(free, free)]
    H_reported = H_all[np.ix_(reported, reported)]
    if check_rank:
        # judged at the solution: a degeneracy only at the start (a sensor tilt or the
        # rational terms at exactly zero, where their derivatives are those of the
        # principal point and of k1) is not one of the data; at the start only if the
        # solve broke down
        H_start = H[np.ix_(free, free)]
        _check_rank(H_end if np.all(np.isfinite(H_end)) else H_start, params, spec_free)
    elapsed = time.perf_counter() - t0
    finite = bool(np.all(np.isfinite(r_h)))
    ok = bool(result == optx.RESULTS.successful) and finite
    message = result_message(result, finite)
    if finite and result == optx.RESULTS.nonlinear_max_steps_reached:
        # at the step limit: converged if the optimum is closer than a tiny fraction of
        # every parameter's σ (what the state-change test misses along weak valleys)
        gap = remaining_step_sigma(end_structure, B_end, r_h, free)
        stats["remaining_step_sigma"] = gap
        if gap <= AT_OPTIMUM_SIGMA:
            ok, message = True, ""
    fit = Fit(
        params=eqx.combine(jax.device_put(unravel(x_end_h)), static),
        converged=bool(ok),
        message=message,
        steps=int(num_steps),
        residuals=r,
        initial_cost=float(0.5 * np.sum(r0**2)),
        cost=float(0.5 * np.sum(r_h**2)),
        time_s=elapsed,
        free_mask=spec_reported,
        scale=jax.device_put(scale_reported[np.flatnonzero(reported)]),
        normal_matrix=H_reported,
        labels=tuple(parameter_labels(params, spec_reported)),
        n_observations=int(np.count_nonzero(r_h)),
        result=result,
        stats=stats,
        released=_released(
            end_structure,
            B_end,
            r_h,
            free,
            reported,
            lambda: parameter_labels(params, spec),
        ),
    )
    if throw and not ok:
        raise NotConvergedError(f"Levenberg–Marquardt did not converge: {message}", fit)
    return fit


_RESULT_TREE = jax.tree.structure(optx.RESULTS.successful)

#: A solve stopped by its step limit counts as converged when the Gauss–Newton step that
#: remains moves no free parameter by more than this fraction of its σ.
AT_OPTIMUM_SIGMA = 1e-3


def remaining_step_sigma(structure, B, r, free) -> float:
    """The largest |δᵢ| / σᵢ of the Gauss–Newton step `δ = −(JᵀJ)⁻¹ Jᵀ r` over the free
    parameters, σᵢ = √((JᵀJ)⁻¹)ᵢᵢ (residuals in units of their σ): how far the solution
    is from the optimum of the linearised problem, in each parameter's own uncertainty.

    Levenberg–Marquardt's convergence test is on the change of the unit-column-scaled
    state. Along a weak valley of the cost (a flat direction with eigenvalue ~1e-13 of the
    scaled `JᵀJ`, e.g. few board views) the steps stay large in those units while the cost
    changes by 1e-10 and the parameters by 1e-5 σ: the test never passes at the optimum.
    Measured on 3 views at ×1 with a ring-gauge scan: 300 steps, remaining step 1.5e-5 σ,
    distances 0.016 µm RMS against the ray tracer. Computed on the host (dense `J`, the
    eigendecomposition of the scaled `JᵀJ`); `inf` where `JᵀJ` is singular.
    """
    J = _dense_jacobian(structure, np.asarray(B))[:, np.flatnonzero(free)]
    col = np.linalg.norm(J, axis=0)
    if not np.all(col > 0):
        return math.inf
    Js = J / col
    lam, V = np.linalg.eigh(Js.T @ Js)
    if not lam[0] > RANK_RTOL * lam[-1]:
        return math.inf
    step = -V @ ((V.T @ (Js.T @ np.asarray(r))) / lam)
    sigma = np.sqrt(np.einsum("ik,k->i", V**2, 1.0 / lam))
    return float(np.max(np.abs(step) / sigma))


@exported_jit
def _lm_solve(y0, args, solver, max_steps: int):
    """The Levenberg–Marquardt loop (optimistix's `least_squares` on `_scaled`):
    `(solution, optimistix result code, number of steps)`, arrays only (an exported
    program's outputs)."""
    sol = optx.least_squares(_scaled, solver, y0, args, max_steps=max_steps, throw=False)
    return sol.value, sol.result._value, sol.stats["num_steps"]


def _held(params, spec, hold: Sequence[str]):
    """`(free, spec_free)`: which scalars of the state vector of `spec` are free once the
    paths `hold` are held too, and the filter spec of those."""
    not_held = free_spec(params, hold)
    spec_free = jax.tree.map(lambda a, b: bool(a) and bool(b), spec, not_held)
    free_p, _ = eqx.partition(params, spec)
    flags, _ = eqx.partition(spec_free, spec)
    flags = jax.tree.map(lambda p, f: np.full(np.shape(p), f), free_p, flags)
    return np.concatenate(
        [np.ravel(x) for x in jax.tree.leaves(flags)] or [np.zeros(0, bool)]
    ).astype(bool), spec_free


def refine(
    fn: Callable,
    params,
    data,
    *,
    freeze: Sequence[str] = (),
    spec=None,
    max_steps: int = 200,
    rtol: float = 1e-10,
    atol: float = 1e-10,
):
    """Pure, differentiable re-solve of `fn` from `params` (typically an optimum).

    Unlike `least_squares` this has no Python-side checks, so it can be traced: the
    derivative of the solution w.r.t. `data` (e.g. an observed corner) comes from
    optimistix's implicit adjoint, i.e. the implicit function theorem at the optimum.

    At the default tolerances (1e-10, near the rounding floor of the unscaled state)
    Levenberg–Marquardt takes 30–50 steps even from the optimum (measured: 34 from it,
    47 after a 0.05 px change of one corner), hence the default of 200: reaching
    `max_steps` raises.
    """
    if spec is None:
        spec = free_spec(params, freeze)
    x0, unravel, static = split(params, spec)
    sol = optx.least_squares(
        _unscaled,
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        x0,
        (fn, unravel, static, data),
        max_steps=max_steps,
    )
    return eqx.combine(unravel(sol.value), static)
