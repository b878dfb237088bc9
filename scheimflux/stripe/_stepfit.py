"""Centres of a line that crosses an albedo edge: a Gaussian-times-step profile fit.

Brightness is albedo x irradiance: a laser line over an albedo step at `e` (a checker
edge under the line) records, along the scan line, before the optics' blur,

    E(y) = A(y) · (ambient + L · G0(y - c)),      A(y) = a1 + (a2 - a1) H(y - e),

which is not symmetric about the line centre `c`: Steger's centre is pulled towards the
brighter side by up to a few pixels. Blurred by a Gaussian of std `b` (the lens), with
`G0` of std `s0` and `s² = s0² + b²`, the product has a closed form because the product
of two Gaussians is a Gaussian:

    I(y) = α + β Φ((y - e) / b) + G_s(y - c) · (γ + δ Φ((m(y) - e) / √v)),
    m(y) = c + (y - c) s0² / s²,    v = s0² b² / s²,

(`G_s` unnormalised, `Φ` the normal CDF). For fixed nonlinear parameters `(e, c, s, b)`
the model is linear in `(α, β, γ, δ)`, which are eliminated by linear least squares
(variable projection); Levenberg-Marquardt on the four nonlinear ones, from a few
starting edge positions, runs vectorised over all scan lines that need it. A fit is
accepted only when its residual is at the noise, the laser is bright on both sides of the
edge, the width is the line's own, and the centre's standard error is small: what cannot
be fitted stays refused.
"""

from __future__ import annotations

import math

import numpy as np

from ._kernels import FWHM_PER_SIGMA

# Accepted standard error of a fitted centre (px): the covariance of the fit with the
# residual's own noise level. Laser-on profiles of the dimmed board reach 0.03-0.06 with
# width and blur held; 0.1 keeps the line's RMS within 0.05 px (a minority of centres).
MAX_SIGMA_C = 0.1
# Accepted residual RMS over the noise estimate: for ~21 samples and 8 parameters the
# 99.9 % point of sqrt(chi²_13 / 13) is 1.6; shot noise on the bright side adds to it.
MAX_RESIDUAL = 2.0
_ITER = 14
# Accepted centres whose profile asymmetry exceeds this are re-measured by the
# Gaussian-times-step fit (kept as they are when that fit is refused).
ASYMMETRY_REFIT = 0.05


_NP = 5  # nonlinear parameters: e, c, s, b, k


def _design(y, p):
    """The two basis profiles (n, m) of the linear parameters at nonlinear ones p (n, 5)."""
    from scipy.special import ndtr  # here, not at import: SciPy is slow to import

    e, c, s, b, k = (p[:, i : i + 1] for i in range(_NP))
    t = y - c
    ee = e - c
    s0sq = np.maximum(s * s - b * b, 0.25 * s * s)
    ratio = s0sq / (s * s)
    kg = k * np.exp(-0.5 * (t / s) ** 2)
    step = ndtr((t - ee) / b)
    inner = ndtr((t * ratio - ee) / (b * np.sqrt(ratio)))
    return 1.0 + kg, step + kg * inner


def _project(F1, F2, data):
    """Linear least squares for (α, β) per scan line: coefficients (n, 2), residual."""
    a11 = np.einsum("nm,nm->n", F1, F1)
    a12 = np.einsum("nm,nm->n", F1, F2)
    a22 = np.einsum("nm,nm->n", F2, F2)
    r1 = np.einsum("nm,nm->n", F1, data)
    r2 = np.einsum("nm,nm->n", F2, data)
    a22 = a22 + 1e-9 * (a11 + a22)
    det = a11 * a22 - a12 * a12
    det = np.where(det > 0, det, np.inf)
    alpha = (a22 * r1 - a12 * r2) / det
    beta = (a11 * r2 - a12 * r1) / det
    return np.stack([alpha, beta], 1), data - alpha[:, None] * F1 - beta[:, None] * F2


def _residual(y, p, data):
    return _project(*_design(y, p), data)[1]


def _jacobian(y, p, data, r, free, h=1e-4):
    J = np.zeros(r.shape + (_NP,))
    for i in range(_NP):
        if not free[i]:
            continue
        q = p.copy()
        q[:, i] += h
        J[:, :, i] = (_residual(y, q, data) - r) / h
    return J


def _lm(y, data, p, lo, hi, free, iters):
    """Levenberg-Marquardt on the projected residual, vectorised over the rows; the
    parameters stay within [lo, hi]. Returns the parameters and the costs."""
    n = p.shape[0]
    lam = np.full(n, 1e-2)
    fixed = np.diag((~free).astype(np.float64))
    r = _residual(y, p, data)
    cost = np.einsum("nm,nm->n", r, r)
    for _ in range(iters):
        J = _jacobian(y, p, data, r, free)
        JtJ = np.einsum("nmi,nmj->nij", J, J)
        g = np.einsum("nmi,nm->ni", J, r)
        diag = np.einsum("nii->ni", JtJ) + 1e-12
        A = JtJ + fixed + (lam[:, None] * diag)[:, :, None] * np.eye(_NP)
        q = np.clip(p - np.linalg.solve(A, g[..., None])[..., 0], lo, hi)
        r_new = _residual(y, q, data)
        cost_new = np.einsum("nm,nm->n", r_new, r_new)
        better = cost_new < cost
        p = np.where(better[:, None], q, p)
        r = np.where(better[:, None], r_new, r)
        cost = np.where(better, cost_new, cost)
        lam = np.where(better, lam * 0.3, lam * 10.0)
    return p, cost


def fit_step_profiles(data, y, c0, s_line, noise, blur=None, init=None):
    """Fit the Gaussian-times-step profile to each row of `data`.

    **Arguments:**
    - `data`: (n, m) profiles along the scan line (grey levels), sampled at rows `y`.
    - `y`: (n, m) their scan coordinates.
    - `c0`: (n,) starting centres (Steger's, pulled by the edge but within ~2 px).
    - `s_line`: the line's std along the scan line (px; scalar or (n,)), from its
      symmetric centres.
    - `noise`: the image's noise std (grey levels).
    - `blur`: None (the edge blur `b` and the width `s` are fitted), or (n,) values of
      `b`; with it, `s` and `b` are held at `s_line` and `blur` (better determined
      centres when both are known from neighbouring fits).
    - `init`: optional (n, 5) parameters `(e, c, s, b, k)` of an earlier fit to start
      from (its `e`, `c`, `k`).

    **Returns:** `(c, ok, sigma_c, params)`: fitted centres (n,), which fits are
    accepted, the centres' standard errors, and all parameters (n, 5) `(e, c, s, b, k)`.
    """
    n, m = data.shape
    if n == 0:
        return np.zeros(0), np.zeros(0, bool), np.zeros(0), np.zeros((0, _NP))
    data = data.astype(np.float64)
    s_line = np.broadcast_to(np.asarray(s_line, np.float64), (n,))
    # k (laser over ambient light) from the peak over the flanks
    flank = np.minimum(data[:, :3].mean(1), data[:, -3:].mean(1))
    k0 = np.clip(data.max(1) / np.maximum(flank, 1e-6) - 1.0, 0.05, 1e3)
    free = np.array([True, True, blur is None, blur is None, True])
    b0 = np.full(n, 0.8) if blur is None else np.asarray(blur, np.float64)
    lo = np.stack([y[:, 0], c0 - 3.0, 0.6 * s_line, np.full(n, 0.3), np.full(n, 1e-3)], 1)
    hi = np.stack([y[:, -1], c0 + 3.0, 1.6 * s_line, np.full(n, 2.5), np.full(n, 1e4)], 1)
    if blur is not None:
        lo[:, 2] = hi[:, 2] = s_line
        lo[:, 3] = hi[:, 3] = b0
    p0 = np.stack([c0, c0, s_line, b0, k0], 1)
    if init is not None:
        p0[:, 0], p0[:, 1], p0[:, 4] = init[:, 0], init[:, 1], init[:, 4]
    best, best_cost = _lm(y, data, p0, lo, hi, free, _ITER)
    # Other starting edge positions only where the first fit is poor (cost well above
    # the noise's): the edge on the other side of the centre, or farther out.
    poor = np.flatnonzero(best_cost > 1.5 * m * max(noise, 1e-9) ** 2)
    for start in (-1.2, 1.2):
        if poor.size == 0:
            break
        p = p0[poor].copy()
        p[:, 0] = c0[poor] + start * s_line[poor]
        q, cost = _lm(y[poor], data[poor], p, lo[poor], hi[poor], free, _ITER)
        take = cost < best_cost[poor]
        best[poor[take]] = q[take]
        best_cost[poor[take]] = cost[take]

    e, c, s, b, k = best.T
    coef, r = _project(*_design(y, best), data)
    var = np.einsum("nm,nm->n", r, r) / max(m - _NP - 2, 1)
    # Covariance of the nonlinear parameters (variable projection: the Jacobian of the
    # projected residual), scaled by the fit's own residual variance.
    J = _jacobian(y, best, data, r, free)
    JtJ = np.einsum("nmi,nmj->nij", J, J) + np.diag((~free).astype(np.float64))
    cond_ok = np.linalg.cond(JtJ) < 1e12
    cov = np.linalg.inv(np.where(cond_ok[:, None, None], JtJ, np.eye(_NP)))
    sigma_c = np.sqrt(np.clip(cov[:, 1, 1] * var, 0.0, None))
    alpha, beta = coef.T
    ok = (
        np.isfinite(best_cost)
        & cond_ok
        & (np.sqrt(var) <= MAX_RESIDUAL * max(noise, 1e-9))
        & (sigma_c <= MAX_SIGMA_C)
        & (alpha > 0)
        & (alpha + beta > 0)
        & ((s > lo[:, 2] * 1.01) & (s < hi[:, 2] * 0.99) | (blur is not None))
        & (np.abs(c - c0) < 2.95)
    )
    return c, ok, np.where(ok, sigma_c, np.inf), best


def profile_window(s_line: float) -> int:
    """Half-length (rows) of the profile window: the line and a flank on each side."""
    return int(math.ceil(3.0 * s_line)) + 3


def _local_median(x: np.ndarray, ok: np.ndarray, values: np.ndarray, reach: float = 150.0):
    """Median of `values[ok]` over the entries within `reach` scan lines of each `x`
    (sorted), the global median where a window holds fewer than 5."""
    xs, vs = x[ok], values[ok]
    out = np.full(x.size, float(np.median(vs)))
    lo = np.searchsorted(xs, x - reach)
    hi = np.searchsorted(xs, x + reach)
    count = hi - lo
    i = np.flatnonzero(count >= 5)
    if i.size == 0:
        return out
    # all windows at once: each window's values (inf beyond its end) sorted along a row
    span = np.arange(int(count[i].max()))
    idx = lo[i, None] + span[None, :]
    win = np.where(span[None, :] < count[i, None], vs[np.minimum(idx, vs.size - 1)], np.inf)
    win.sort(axis=1)
    c = count[i]
    a = np.take_along_axis(win, ((c - 1) // 2)[:, None], axis=1)[:, 0]
    b = np.take_along_axis(win, (c // 2)[:, None], axis=1)[:, 0]
    out[i] = np.where(c % 2 == 1, a, (a + b) / 2)
    return out


def refit_steps(gather, shape, lines, valid, saturated, coarse, width, noise):
    """Centres with an albedo edge under the line, from the Gaussian-times-step fit.

    Candidates: scan lines with the line's coarse support, between its first and last
    accepted centre, that the per-centre tests refused, and accepted ones whose profile
    is noticeably asymmetric. A candidate whose fit is accepted takes the fitted centre
    (and becomes valid); a refused fit leaves a refused centre refused and an accepted
    Steger centre as it was.

    `noise`: the noise of the profiles (grey levels), or a function without arguments
    that returns it (called only where there is a candidate to fit).

    **Returns:** `(y, valid, sigma)`: centres, validity and the fitted centres' standard
    errors (inf where not fitted).
    """
    none = np.full(lines.y.shape, np.inf)
    cand = coarse.support & ~saturated
    if lines.asym is not None:  # (NaN: asymmetric)
        cand &= ~valid | ~(np.abs(lines.asym) <= ASYMMETRY_REFIT)
    else:
        cand &= ~valid
    # only inside the line (between its first and last accepted centre)
    span = np.flatnonzero(valid)
    if span.size < 2:
        return lines.y, valid, none
    cand[: span[0]] = False
    cand[span[-1] + 1 :] = False
    idx = np.flatnonzero(cand)
    if idx.size == 0:
        return lines.y, valid, none
    ny = np.abs(np.nan_to_num(lines.ny[idx], nan=1.0)) if lines.ny is not None else 1.0
    s_scan = (width / FWHM_PER_SIGMA) / np.maximum(ny, 0.5)
    c0 = np.where(np.isfinite(lines.y[idx]), lines.y[idx], coarse.centre[idx])
    half = profile_window(float(np.max(s_scan)))
    rows = np.rint(c0)[:, None].astype(np.intp) + np.arange(-half, half + 1)[None, :]
    inside = (rows[:, 0] >= 0) & (rows[:, -1] <= shape[0] - 1)
    rows = np.clip(rows, 0, shape[0] - 1)
    data = gather(rows, idx[:, None]).astype(np.float64)
    yy = rows.astype(np.float64)
    if callable(noise):
        noise = float(noise())
    c, ok, sig, params = fit_step_profiles(data, yy, c0, s_scan, noise)
    ok &= inside
    if np.count_nonzero(ok) >= 5:
        # Second pass: width and edge blur change slowly along the line (the blur across
        # a Scheimpflug field), so the accepted fits' local medians hold them; with them
        # fixed the centre is better determined and more fits pass.
        s_ratio = _local_median(idx, ok, params[:, 2] / s_scan)
        b_loc = _local_median(idx, ok, params[:, 3])
        c2, ok2, sig2, _ = fit_step_profiles(
            data, yy, c0, s_scan * s_ratio, noise, blur=b_loc, init=params
        )
        ok2 &= inside
        c = np.where(ok2, c2, c)
        sig = np.where(ok2, sig2, sig)
        ok = ok | ok2
    y = lines.y.copy()
    y[idx[ok]] = c[ok]
    valid = valid.copy()
    valid[idx[ok]] = True
    sigma = none.copy()
    sigma[idx[ok]] = sig[ok]
    return y, valid, sigma
