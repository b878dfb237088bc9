"""The thick lens's gauge: what the images cannot determine, and a frozen set that costs
nothing.

Without distortion the thick-lens pixel rays are a 3×3 projective map `K_f`, seen only up
to a rotation (absorbed by the board poses) and a scale: five numbers for the seven lens
parameters left once the pixel pitch is known (datasheet). Two combinations are then
exactly unobservable: one along (f, e, z0) and the sensor tilt against the axis point
(φ, θ against x0, y0). Holding f and the tilt (nominal initialisation) or f and the
axis point (closed form) fixes them, and any value gives the same rays.

Distortion in the untilted image plane is radial about the optical axis: it ties the axis
point, and with it the tilt, to the data. The tilt is then no longer a gauge, and holding
it at a rounded nominal value biases what is measured (a 1° error moved noise-free
pairwise distances by 0.05 µm on a 50 mm double Gauss at ×0.5, 1600 × 1200 px; the
issue's 75 mm telephoto: 0.19 µm). The singular values of the column-scaled Jacobian
with only the pixel pitch frozen show one null direction, along (f, z0, e) (exact: any f
gives the same rays), and next to it the axis point against the boards' translations
(eigenvalues of the scaled JᵀJ 3e-14 – 1e-12: determined only through the distortion's
centre); the tilt has no part in either (docs/noncentral.md lists them). Holding the
axis point is no gauge either: held at the sensor centre 29 px from the true axis it
biased noise-free distances by 0.28 µm. Freeing both (pitch and `f` held,
`distorted_freeze`) is the exact gauge, but Levenberg–Marquardt then creeps along the
weak, curved axis-point valley (8 corner-only views of that scene: not converged in 200
steps).

`gauge="profile"` (`calibrate`, `calibrate_camera`; not the default) frees the tilt and
places the axis point by variable projection (`profile_axis_point`): every inner solve
holds `(x0, y0)` at run time (the same compiled program), and outer steps use the
profile's gradient and Gauss–Newton Hessian from `least_squares(..., release=...)`
(`_solve.Released`, a QR of the Jacobian: formed from `JᵀJ` the Schur complement loses
every digit along this direction). The profile is not convex (three basins on the
50 mm scene), so y0 is placed first, x0 scanned across the sensor, and a trust-region
quasi-Newton steps on both coordinates finish. Noise free it makes a nominal tilt ±1° off change
distances by ≤ 2e-5 µm (target 0.005 µm); on noisy 8-view data it converged and kept
the axis point on the sensor, but its distance errors were slightly larger than the
held gauge's (0.034–0.051 against 0.027–0.045 µm, 3 seeds) at 2.4× the compiled time,
so the held gauge stays the default (docs/noncentral.md).

`gauge_spectrum` computes these singular values and directions for any solve.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._solve import RankDeficientError, free_spec, jacobian, parameter_labels

PIXEL_PITCH = ("camera.dx", "camera.dy")
#: The exact gauge of the distortion-free thick lens, per initialisation.
IDEAL_GAUGE = {
    "nominal": ("camera.f", "camera.phi", "camera.theta"),
    "closed-form": ("camera.f", "camera.x0", "camera.y0"),
}
#: The exact gauge once distortion is fitted: the scale along (f, e, z0).
DISTORTED_GAUGE = ("camera.f",)
_RELEASED = ("camera.phi", "camera.theta", "camera.x0", "camera.y0")
#: The axis point: the weakest determined direction once f is held (against the boards'
#: translations), placed by a profile of the cost (`profile_axis_point`).
AXIS_POINT = ("camera.x0", "camera.y0")
#: What `gauge="profile"` holds in its solves: the pixel pitch and f (compile time).
GAUGE_HELD = PIXEL_PITCH + DISTORTED_GAUGE
#: The gauges of the thick lens with distortion.
GAUGES = ("held", "profile")


def ideal_freeze(how: str) -> tuple[str, ...]:
    """Pixel pitch and the distortion-free gauge for an initialisation (`DEFAULT_FREEZE`)."""
    return PIXEL_PITCH + IDEAL_GAUGE[how]


def distorted_freeze(freeze: tuple[str, ...]) -> tuple[str, ...]:
    """The default frozen set for the solve with distortion: `freeze` without the tilt
    and the axis point, which distortion makes observable (pixel pitch and f remain)."""
    return tuple(p for p in freeze if p not in _RELEASED)


@dataclasses.dataclass(frozen=True)
class GaugeSpectrum:
    """Singular values of a solve's column-scaled Jacobian and its weakest directions.

    **Fields:**
    - `labels`: the free parameters, in the Jacobian's column order.
    - `singular_values`: relative to the largest, descending.
    - `directions`: for the `k` smallest singular values, `(relative singular value,
      [(label, component), ...])` with the components of the unit direction above 0.1,
      largest first (the system parameters and board poses alike).
    - `frozen`: the paths held fixed.
    """

    labels: tuple[str, ...]
    singular_values: np.ndarray
    directions: list
    frozen: tuple[str, ...]

    def format(self) -> str:
        """The weakest directions, one line each."""
        lines = [f"frozen: {', '.join(self.frozen) or '(none)'}"]
        for s, comps in self.directions:
            names = ", ".join(f"{lab} {c:+.2f}" for lab, c in comps)
            lines.append(f"  sigma/sigma_max = {s:.2e}: {names}")
        return "\n".join(lines)


def gauge_spectrum(fn, params, data, freeze=PIXEL_PITCH, *, k: int = 4) -> GaugeSpectrum:
    """Singular values of `fn`'s Jacobian at `params` with `freeze` held (column-scaled).

    **Arguments:**
    - `fn`, `params`, `data`: a residual function and where to linearise it (e.g.
      `camera_residuals`, a solved `Fit.params`, `make_data(obs)`).
    - `freeze`: the paths held fixed (default: the pixel pitch only, so every gauge
      freedom of the lens shows).
    - `k`: how many of the weakest directions to describe.

    **Returns:** a [`GaugeSpectrum`][]. A relative singular value at rounding level
    (≲ 1e-7, i.e. an eigenvalue of the scaled JᵀJ ≲ 1e-14) is a combination the data
    cannot see: a gauge to fix. One well above it is determined, and fixing it biases.
    """
    spec = free_spec(params, tuple(freeze))
    J = np.asarray(jacobian(fn, params, data, spec))
    labels = tuple(parameter_labels(params, spec))
    norms = np.linalg.norm(J, axis=0)
    J = J / np.where(norms > 0, norms, 1.0)
    _, s, Vt = np.linalg.svd(J, full_matrices=False)
    s_rel = s / s[0]
    dirs = []
    for i in range(1, min(k, len(s)) + 1):
        v = Vt[-i]
        order = np.argsort(-np.abs(v))[:6]
        comps = [(labels[j], float(v[j])) for j in order if abs(v[j]) > 0.1]
        dirs.append((float(s_rel[-i]), comps))
    return GaugeSpectrum(labels, s_rel, dirs, tuple(freeze))


def solve_with_gauge(solve, held: tuple[str, ...], released: tuple[str, ...]):
    """`solve(released)`; where the data cannot determine what it releases (a
    `RankDeficientError`: a lens with too little distortion over the boards to see the
    tilt), `solve(held)` instead.

    **Returns:** `(fit, freeze)`: the solve's result and the frozen set it used.
    """
    if tuple(released) == tuple(held):
        return solve(held), tuple(held)
    try:
        return solve(released), tuple(released)
    except RankDeficientError:
        return solve(held), tuple(held)


@dataclasses.dataclass(frozen=True)
class AxisProfile:
    """Where the profile of the cost placed the axis point (`profile_axis_point`).

    **Fields:**
    - `value`: the axis point `(x0, y0)` (px).
    - `sigma`: its standard deviations (px) from the profile's curvature (the Schur
      complement of the normal matrix) at the residuals' assumed σ.
    - `converged`: the last Newton step was below the tolerance (and the last inner
      solve converged).
    - `at_bound`: a coordinate is held at the edge of the search's bounds (the sensor)
      because the profile still falls beyond it: that value is a bound, not the data's
      optimum.
    - `iterations`: the outer (Newton) iterations; `steps`: Levenberg–Marquardt steps of
      all its inner solves together; `costs`: the accepted inner costs, in order.
    """

    value: tuple[float, float]
    sigma: tuple[float, float]
    converged: bool
    at_bound: bool
    iterations: int
    steps: int
    costs: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        return {
            "axis_point_px": [float(v) for v in self.value],
            "sigma_px": [float(v) for v in self.sigma],
            "converged": bool(self.converged),
            "at_bound": bool(self.at_bound),
            "iterations": int(self.iterations),
            "lm_steps": int(self.steps),
        }


def _get(p, path):
    for n in path.split("."):
        p = getattr(p, n)
    return p


def _with_axis_point(params, value):
    for path, v in zip(AXIS_POINT, value):
        old = _get(params, path)
        params = eqx.tree_at(
            lambda t, _p=path: _get(t, _p), params, jnp.asarray(v, dtype=jnp.result_type(old))
        )
    return params


def reduced_axis_point(fit):
    """The profile's gradient and Gauss–Newton Hessian with respect to the axis point at
    an inner optimum (px; cost ½|r|², r in units of σ): `fit.released` of a solve that
    held the axis point and released it (`least_squares`'s `release`).

    **Returns:** `(g, S)`: shapes (2,) and (2, 2).
    """
    rel = fit.released
    if rel is None or tuple(rel.labels) != AXIS_POINT:
        raise ValueError("the solve did not hold and release the axis point")
    return np.asarray(rel.gradient, np.float64), np.asarray(rel.hessian, np.float64)


def _step(g, S, fixed):
    """The Newton step −S⁻¹g over the coordinates not `fixed` (those held: 0)."""
    f = ~np.asarray(fixed, bool)
    step = np.zeros(2)
    if f.any():
        step[f] = -np.linalg.solve(S[np.ix_(f, f)], g[f])
    return step


def profile_axis_point(
    solve,
    fit,
    *,
    bounds: tuple[tuple[float, float], tuple[float, float]],
    scan: int = 9,
    tol_px: float = 1e-3,
    tol_sigma: float = 1e-3,
    max_iterations: int = 10,
    radius_px: float | None = None,
):
    """Place the axis point `(x0, y0)` at the minimum of the cost profile.

    Variable projection: `solve(params)` re-solves every other free parameter with the
    axis point held at its value in `params` (a run-time hold: one compiled program),
    and returns a `Fit` whose `released` holds the profile's gradient (`J_pᵀ r`, the
    envelope theorem) and Gauss–Newton Hessian (the Schur complement of `JᵀJ`, from a
    QR factorisation: `_solve.Released`) there. Along this direction (the axis point
    against the boards' translations; relative singular value ~1e-7 – 1e-6 of the
    column-scaled Jacobian) Levenberg–Marquardt with the axis point free creeps along a
    curved valley; with it held each inner solve is well conditioned and, warm-started
    from the nearest solved point, takes a few steps.

    1. The profile is not convex: on the 50 mm ×0.5 scene of `tests/test_gauge.py` it
       has a second minimum 570 px from the lowest (cost 0.19 against 0.063 σ², noise
       free), which Newton steps from a start 1° off in tilt reach. So x0 is first
       scanned at `scan` points across its bounds (y0 at its start value), in order of
       distance from the start.
    2. From the lowest point, trust-region quasi-Newton steps on both coordinates: the
       Gauss–Newton Schur complement of the first point, updated by BFGS from the
       gradients' changes (the profile's curvature is not the Gauss–Newton one: the
       inner optimum moves nonlinearly with the axis point); steps kept inside
       `bounds` (a coordinate at a bound whose step points outward is held there).

    **Arguments:**
    - `solve`: `params -> Fit` with the axis point held and released.
    - `fit`: the inner solve at the start.
    - `bounds`: `((x_lo, x_hi), (y_lo, y_hi))` (px), e.g. the sensor.
    - `scan`: points of the x0 scan (0: none).
    - `tol_px`, `tol_sigma`: stop when the step is below `max(tol_px, tol_sigma · σ)`
      in both coordinates (σ: the axis point's standard deviation at the residuals'
      assumed noise, from the Schur complement).
    - `max_iterations`: inner solves after the scan at most.
    - `radius_px`: the trust region's initial radius (default: the scan's spacing, or a
      quarter of the bounds' larger extent).

    **Returns:** `(fit, profile)`: the inner solve at the optimum and an
    [`AxisProfile`][].
    """
    lo = np.array([b[0] for b in bounds], dtype=np.float64)
    hi = np.array([b[1] for b in bounds], dtype=np.float64)
    state = {"steps": int(fit.steps), "costs": [float(fit.cost)], "iterations": 0}

    def run(f):
        # an axis point far from the data's (a scan point at the sensor's edge) can put
        # the inner solve where the data do not determine it (measured: z0 against e on
        # the Tessar ×0.5 data at x0 = 1835 px): no profile value there, not a failure
        try:
            trial = solve(f)
        except RankDeficientError:
            return None
        state["steps"] += int(trial.steps)
        return trial

    # y0 first (x0 held at its start): a start 1° off in φ is hundreds of px off in y0,
    # and the x0 scan at a wrong y0 finds a wrong x0
    fit, *_ = _quasi_newton(run, fit, lo, hi, np.array([False, True]), tol_px, 1e-2, 4, None)
    evaluated = [fit]
    if scan:
        y = _axis(fit)[1]
        x_start = _axis(fit)[0]
        for x in sorted(np.linspace(lo[0], hi[0], scan), key=lambda v: abs(v - x_start)):
            near = min(evaluated, key=lambda f: abs(_axis(f)[0] - x))
            trial = run(_with_axis_point(near.params, (x, y)))
            if trial is not None:
                evaluated.append(trial)
        fit = min(evaluated, key=lambda f: f.cost if np.isfinite(f.cost) else np.inf)
        state["costs"].append(float(fit.cost))
    if radius_px is None:
        radius_px = (hi[0] - lo[0]) / max(scan - 1, 1) if scan else 0.25 * np.max(hi - lo)
    fit, sigma, converged, at_bound, iterations = _quasi_newton(
        run, fit, lo, hi, np.ones(2, bool), tol_px, tol_sigma, max_iterations, radius_px,
        state["costs"],
    )  # fmt: skip
    return fit, AxisProfile(
        tuple(float(v) for v in _axis(fit)),
        tuple(float(v) for v in sigma),
        converged,
        at_bound,
        iterations,
        state["steps"],
        tuple(state["costs"]),
    )


def _axis(fit) -> np.ndarray:
    return np.array([float(_get(fit.params, path)) for path in AXIS_POINT])


def _quasi_newton(solve, fit, lo, hi, active, tol_px, tol_sigma, max_iterations, radius,
                  costs=None):  # fmt: skip
    """Trust-region quasi-Newton steps on the `active` coordinates of the axis point
    (the others held): the Gauss–Newton Schur complement at the start, updated by BFGS
    from the changes of the profile's gradient; a coordinate at a bound whose step
    points outward is held there. `solve` returning None (no profile value there) is
    treated as a rise of the cost: a smaller step. Stops when both the model's step and
    the Gauss–Newton step are below `max(tol_px, tol_sigma · σ)`.

    **Returns:** `(fit, σ, converged, at_bound, iterations)`.
    """
    costs = [] if costs is None else costs
    p = _axis(fit)
    g, S = reduced_axis_point(fit)
    B = S.copy()
    if radius is None:
        radius = 0.25 * float(np.max(hi - lo))
    iterations, converged, at_bound = 0, False, False
    held = ~np.asarray(active, bool)
    while True:
        sigma = np.sqrt(np.clip(np.diag(np.linalg.pinv(S)), 0.0, None))
        fixed = held.copy()
        step = _step(g, B, fixed)
        out = ((p <= lo) & (step < 0)) | ((p >= hi) & (step > 0))
        if out.any():
            fixed |= out
            step = _step(g, B, fixed)
        gn = _step(g, S, fixed)
        tol = np.maximum(tol_px, tol_sigma * sigma)
        if np.all(np.abs(step) <= tol) and np.all(np.abs(gn) <= tol):
            converged, at_bound = bool(fit.converged), bool(out.any())
            break
        if iterations >= max_iterations:
            at_bound = bool(out.any())
            break
        n = float(np.linalg.norm(step))
        if n > radius:
            step = step * (radius / n)
        p_new = np.clip(p + step, lo, hi)
        step = p_new - p
        predicted = -(g @ step + 0.5 * step @ B @ step)
        trial = solve(_with_axis_point(fit.params, p_new))
        iterations += 1
        actual = -np.inf if trial is None else float(fit.cost) - float(trial.cost)
        if trial is not None and np.isfinite(trial.cost) and actual >= 0.0:
            rho = actual / predicted if predicted > 0 else 1.0
            if rho > 0.75 and float(np.linalg.norm(step)) >= 0.99 * radius:
                radius *= 2.0
            elif rho < 0.25:
                radius = max(0.25 * float(np.linalg.norm(step)), tol_px)
            g_new, S = reduced_axis_point(trial)
            B = _bfgs(B, step, g_new - g)
            p, fit, g = p_new, trial, g_new
            costs.append(float(fit.cost))
        else:  # the cost rose: a smaller step from the same point
            radius = max(0.25 * float(np.linalg.norm(step)), tol_px)
    return fit, sigma, converged, at_bound, iterations


def _bfgs(B, s, y):
    """The BFGS update of a 2×2 Hessian model (skipped where the curvature `sᵀy` is not
    positive)."""
    sy = float(s @ y)
    Bs = B @ s
    sBs = float(s @ Bs)
    if sy <= 1e-12 * float(np.linalg.norm(s) * np.linalg.norm(y)) or sBs <= 0:
        return B
    return B - np.outer(Bs, Bs) / sBs + np.outer(y, y) / sy


def profile_notes(profile: AxisProfile | None) -> tuple[str, ...]:
    """The quality warnings of a profile that stopped at the sensor's edge or did not
    converge (the held value's bias is then not in the stated uncertainty)."""
    if profile is None:
        return ()
    x, y = profile.value
    sx, sy = profile.sigma
    where = f"({x:.1f}, {y:.1f}) px (σ {sx:.3g}, {sy:.3g} px)"
    notes = []
    if profile.at_bound:
        notes.append(
            f"the gauge profile held the axis point at the sensor's edge, {where}: the "
            "data's optimum lies beyond it (weakly determined; distances may carry a bias "
            "of that direction)"
        )
    if not profile.converged:
        notes.append(
            f"the gauge profile of the axis point did not converge in {profile.iterations} "
            f"Newton steps; it stopped at {where}"
        )
    return tuple(notes)
