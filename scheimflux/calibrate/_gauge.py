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
weak axis-point valley (8 corner-only views of that scene: not converged in 200 steps).
So the default (`DEFAULT_FREEZE`, tilt held) is NOT changed yet: issue 16 part 1 is
measured here, not solved; the likely fix is a weak prior residual block on the axis
point (or on the tilt) toward its nominal value. `distorted_freeze` and
`solve_with_gauge` (free, fall back to the held gauge on a rank-deficient solve) are
the pieces for it.

`gauge_spectrum` computes these singular values and directions for any solve.
"""

from __future__ import annotations

import dataclasses

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
