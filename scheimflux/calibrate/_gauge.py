"""The thick lens's gauge: what the images cannot determine, and a frozen set that costs
nothing.

Without distortion the thick-lens pixel rays are a 3×3 projective map `K_f`, seen only up
to a rotation (absorbed by the board poses) and a scale: five numbers for the seven lens
parameters left once the pixel pitch is known (datasheet). Two combinations are then
exactly unobservable: one along (f, e, z0) and the sensor tilt against the axis point
(φ, θ against x0, y0). Holding f and the tilt (nominal initialisation) or f and the
axis point (closed form) fixes them, and any value gives the same rays
(`IDEAL_GAUGE`, `DEFAULT_FREEZE`).

Distortion in the untilted image plane is radial about the optical axis: it ties the axis
point, and with it the tilt, to the data. The tilt is then no longer a gauge, and holding
it at a rounded nominal value biases what is measured (a 1° error moved noise-free
pairwise distances by 0.05 µm on a 50 mm double Gauss at ×0.5, 1600 × 1200 px); so does
holding the axis point (0.28 µm at the sensor centre, 29 px from the true axis). Only
the pixel pitch and f are held by default (`GAUGE_HELD`: the (f, e, z0) direction is at
the rounding level of the column-scaled Jacobian's singular values).

What remains weakest is the axis point's x against the boards' x translations, with
the tilt following it (relative singular value ~4e-7 on that scene, at the solver's rank
threshold): Levenberg–Marquardt with it free creeps for hundreds of steps and stops on
rounding noise, short of the optimum. `profile_solve` places it instead: solves with x0
held (well conditioned) on a grid across the sensor, then parabolic steps to the
minimum of the cost profile, which need not be convex (that scene's profile has two
minima, 0.14 µm apart in distances). A nominal tilt off by 1° or 3° then changes
noise-free distances by ~1e-11 µm (docs/noncentral.md, tests/test_gauge.py).

`gauge_spectrum` computes the singular values and weakest directions for any solve.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._solve import free_spec, jacobian, parameter_labels

PIXEL_PITCH = ("camera.dx", "camera.dy")
#: The exact gauge of the distortion-free thick lens, per initialisation.
IDEAL_GAUGE = {
    "nominal": ("camera.f", "camera.phi", "camera.theta"),
    "closed-form": ("camera.f", "camera.x0", "camera.y0"),
}
#: The exact gauge once distortion is fitted: the scale along (f, e, z0).
DISTORTED_GAUGE = ("camera.f",)
#: What the default calibration with distortion holds: the pixel pitch (datasheet) and
#: the exact gauge. Everything else is the data's.
GAUGE_HELD = PIXEL_PITCH + DISTORTED_GAUGE
#: The weakest direction left (the axis point against the boards' translations, with
#: the tilt): solved by a profile of the cost, not by Levenberg–Marquardt.
PROFILED = "camera.x0"


def ideal_freeze(how: str) -> tuple[str, ...]:
    """Pixel pitch and the distortion-free gauge for an initialisation (`DEFAULT_FREEZE`)."""
    return PIXEL_PITCH + IDEAL_GAUGE[how]


def start_holds(how: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The run-time holds of the two solves before the profile, on top of `GAUGE_HELD`:
    the ideal camera (the distortion at zero, the ideal gauge and e at their start
    values) and the distorted camera (the ideal gauge still held)."""
    gauge = tuple(p for p in IDEAL_GAUGE[how] if p not in DISTORTED_GAUGE)
    return gauge + ("camera.e", "camera.distortion"), gauge


@dataclasses.dataclass(frozen=True)
class GaugeProfile:
    """The 1-D profile that placed the profiled parameter at the data's optimum.

    **Fields:**
    - `path`: the profiled parameter (`PROFILED`).
    - `values`, `costs`: where the cost (0.5 Σ r², r in units of σ, every other free
      parameter re-solved) was evaluated, in order of evaluation.
    - `value`: the optimum (the parabola's vertex through the best three).
    - `sigma`: the value's standard deviation from the profile's curvature
      (`1 / √(d²cost/dx²)`, at the residuals' σ), or `nan` when not resolved.
    - `converged`: the vertex moved less than `tol` (and every solve converged).
    - `steps`: Levenberg–Marquardt steps of all the profile's solves together.
    - `at_bound`: the profile still fell at a bound of the search (`value` is that
      bound, not the data's optimum).
    """

    path: str
    values: tuple[float, ...]
    costs: tuple[float, ...]
    value: float
    sigma: float
    converged: bool
    steps: int
    at_bound: bool = False


def _vertex(x, c):
    """Vertex and curvature (d²c/dx²) of the parabola through three points."""
    A = np.stack([np.asarray(x) ** 2, np.asarray(x), np.ones(3)], axis=1)
    a, b, _ = np.linalg.solve(A, np.asarray(c))
    return (-b / (2 * a) if a > 0 else np.nan), 2 * a


def profile_solve(
    solve: Callable[[object], object],
    params,
    *,
    path: str = PROFILED,
    grid,
    bounds: tuple[float, float] = (-np.inf, np.inf),
    tol_sigma: float = 1e-3,
    tol_abs: float = 1e-6,
    max_refinements: int = 12,
):
    """Place the scalar parameter `path` at the minimum of the cost profile.

    `solve(params)` re-solves everything else with `path` held at its value in `params`
    (a `Fit`). Along the weakest direction of a calibration (eigenvalue ~1e-14 of the
    column-scaled `JᵀJ`, at the limit of what float64 normal equations resolve)
    Levenberg–Marquardt with the parameter free creeps for hundreds of steps and its
    stopping test fires on rounding noise, not at the optimum. With the parameter held
    each solve is well conditioned (tens of steps). The profile (the cost as a function
    of the held value) need not have one minimum only: a real lens is not the model, and
    on the 50 mm ×0.5 scene of `tests/test_gauge.py` it has two, 570 px apart (costs
    0.19 and 0.063, in units of σ²). So the profile is first evaluated on `grid` (in
    order of distance from the start, each solve started from the nearest solved
    point), extended outward while its minimum lies at an end, then refined by parabolic
    steps through the best three points until the vertex moves less than `tol_sigma` of
    its statistical σ (or `tol_abs`).

    **Arguments:**
    - `solve`: `params -> Fit` with `path` held (run-time hold: one compiled program).
    - `params`: the start.
    - `path`: a scalar parameter path, e.g. `"camera.x0"`.
    - `grid`: the values of the first scan (at least three, evenly spaced).
    - `bounds`: the range searched: where the profile still falls at a bound, the
      value stays there (`at_bound`).
    - `tol_sigma`, `tol_abs`: the refinement's stopping test.
    - `max_refinements`: solves after the scan at most.

    **Returns:** `(fit, profile)`: the solve at the optimum and a [`GaugeProfile`][].
    """
    names = path.split(".")

    def get(p):
        for n in names:
            p = getattr(p, n)
        return p

    def at(x, start):
        return eqx.tree_at(get, start, jnp.asarray(x, dtype=jnp.result_type(get(start))))

    evaluated: list[tuple[float, object]] = []

    def evaluate(x):
        start = min(evaluated, key=lambda e: abs(e[0] - x))[1].params if evaluated else params
        fit = solve(at(x, start))
        evaluated.append((float(x), fit))
        return fit

    grid = np.sort(np.asarray(grid, dtype=np.float64))
    if grid.size < 3:
        raise ValueError("the profile's grid needs at least three values")
    spacing = float(np.min(np.diff(grid)))
    x_c = float(get(params))
    for x in sorted(grid, key=lambda v: abs(v - x_c)):
        evaluate(float(x))
    lo, hi = (float(b) for b in bounds)
    value, sigma, converged, at_bound = x_c, float("nan"), False, False
    for _ in range(max_refinements):
        pts = sorted(evaluated, key=lambda e: e[0])
        xs = np.array([e[0] for e in pts])
        cs = np.array([e[1].cost for e in pts])
        i = int(np.argmin(cs))
        if i == 0 or i == len(pts) - 1:  # the minimum is not bracketed: step outward
            x = float(np.clip(xs[i] + (spacing if i else -spacing), lo, hi))
            if x == xs[i]:  # at the bound already
                value, converged, at_bound = x, True, True
                break
            evaluate(x)
            continue
        v, curv = _vertex(xs[i - 1 : i + 2], cs[i - 1 : i + 2])
        if not np.isfinite(v):
            break
        sigma = 1.0 / np.sqrt(curv)
        value = float(np.clip(v, lo, hi))
        if np.min(np.abs(xs - value)) <= max(tol_sigma * sigma, tol_abs):
            converged = True
            break
        evaluate(value)
    best_x, best = min(evaluated, key=lambda e: e[1].cost)
    if converged and abs(best_x - value) > max(tol_sigma * sigma, tol_abs):
        best = evaluate(value)
        best_x = value
    ok = converged and all(e[1].converged for e in evaluated[-3:])
    profile = GaugeProfile(
        path,
        tuple(e[0] for e in evaluated),
        tuple(float(e[1].cost) for e in evaluated),
        float(best_x),
        float(sigma),
        bool(ok),
        int(sum(e[1].steps for e in evaluated)),
        at_bound,
    )
    return best, profile


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
