"""The rotary table's axis from a ring-gauge scan, in closed form (NumPy).

The gauge points of every frame lie on the laser plane and on a cylinder of the gauge's
radius whose axis keeps its direction while the table turns. A grid of candidate
directions about the laser normal is scored by per-frame circle fits of the known radius
(vectorised over directions), the best minima are refined by Levenberg–Marquardt on the
direction alone, and the per-frame circle centres then give the table axis, the gauge's
eccentricity and the turning sense. This is the start of the stage solve
([`initial_stage`][]); it runs on the host, before any compiled solve.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...geometry._fitting import perpendicular_basis, unit_rows
from ...geometry._stage import RotaryStage


def _direction_grid(normal: np.ndarray, step: float, min_elevation: float) -> np.ndarray:
    """Directions `d` with `d · n̂ ≥ sin(min_elevation)`, about `step` rad apart (a
    hemisphere of axis directions about the laser normal; ±d are the same axis)."""
    u, v = perpendicular_basis(normal[None])
    u, v = u[0], v[0]
    out = []
    for el in np.arange(min_elevation, np.pi / 2 + 1e-9, step):
        k = max(1, int(round(2 * np.pi * np.cos(el) / step)))
        az = (np.arange(k) + 0.5 * (len(out) % 2)) * 2 * np.pi / k
        ring = np.cos(az)[:, None] * u + np.sin(az)[:, None] * v
        out.append(np.cos(el) * ring + np.sin(el) * normal)
    return np.concatenate(out)


@dataclasses.dataclass(frozen=True)
class _Sections:
    """Gauge points grouped by frame, for the section fits (NumPy, camera frame).

    `P` `(N, 3)`: the points minus their mean `mean`, sorted by frame; `starts` `(K,)`:
    where each of the K frames with points begins in `P`; `seg` `(N,)`: the group of each
    point (0 … K−1); `frames` `(K,)`: the frame indices i of the groups; `normal`: unit
    laser-plane normal; `radius`: the gauge radius (mm).
    """

    P: np.ndarray
    mean: np.ndarray
    starts: np.ndarray
    seg: np.ndarray
    frames: np.ndarray
    normal: np.ndarray
    radius: float

    @classmethod
    def of(cls, X, frame, normal, radius) -> _Sections:
        order = np.argsort(frame, kind="stable")
        X, frame = np.asarray(X, dtype=np.float64)[order], np.asarray(frame)[order]
        frames, starts, seg = np.unique(frame, return_index=True, return_inverse=True)
        mean = X.mean(axis=0)
        normal = np.asarray(normal, dtype=np.float64)
        return cls(X - mean, mean, starts, seg, frames, normal / np.linalg.norm(normal), radius)

    def subsample(self, per_frame: int) -> _Sections:
        """At most `per_frame` points per frame, evenly along each arc."""
        ends = np.append(self.starts[1:], len(self.P))
        keep = np.concatenate(
            [
                np.unique(np.linspace(s, e - 1, min(e - s, per_frame)).round().astype(int))
                for s, e in zip(self.starts, ends)
            ]
        )
        return _Sections(
            self.P[keep], self.mean, np.searchsorted(keep, self.starts), self.seg[keep],
            self.frames, self.normal, self.radius,
        )  # fmt: skip


def _section_fits(sec: _Sections, dirs: np.ndarray, iterations: int = 5):
    """For each candidate axis direction, a circle of the known radius per frame.

    The gauge points of frame i lie on a cylinder of radius r: projected along the true
    axis direction they lie on a circle of radius r (its centre moves from frame to frame
    with the eccentricity). For each direction `d` `(D, 3)` the points are projected onto
    the plane ⟂ d and a circle of radius r is fitted to each frame (Kåsa start, then
    Gauss–Newton on the centre). A point's residual, its distance from the cylinder along
    the surface normal, is divided by that normal's length within the laser plane
    (√(1 − (ρ̂·n̂)²)): the distance *within the laser plane*, where the pixel noise acts.
    The plain 3-D distance would favour cylinders nearly tangent to the laser plane,
    which come within a fraction of a micrometre of a whole band of the plane.

    Per-frame sums use `np.add.reduceat` (no BLAS threads: fast on a busy machine).

    **Returns:** `(score, resid, centres, H, (a, b))`: `score` `(D,)` the mean squared
    in-plane residual (mm²; inf where most of the lit surface would face away from the
    camera or a fit failed), `resid` `(D, N)` the in-plane residuals, the centres `(D, K,
    2)` in the basis `a, b` of each direction (about `sec.mean`), and their normal
    matrices `H` `(D, K, 2, 2)`.
    """
    P, seg, r = sec.P, sec.seg, sec.radius

    def ssum(v):  # (D, N) → per-frame sums (D, K)
        return np.add.reduceat(v, sec.starts, axis=1)

    def dot(u, V):  # (D, 3), (N, 3) → (D, N), without BLAS
        return u[:, :1] * V[:, 0] + u[:, 1:2] * V[:, 1] + u[:, 2:] * V[:, 2]

    a, b = perpendicular_basis(dirs)
    x, y = dot(a, P), dot(b, P)  # (D, N)
    cnt = np.diff(np.append(sec.starts, len(P)))
    # Kåsa fit per frame, in coordinates centred on the frame's centroid
    mx, my = ssum(x) / cnt, ssum(y) / cnt  # (D, K)
    xc, yc = x - mx[:, seg], y - my[:, seg]
    z = xc**2 + yc**2
    sxx, sxy, syy = ssum(xc * xc), ssum(xc * yc), ssum(yc * yc)
    sxz, syz = ssum(xc * z), ssum(yc * z)
    with np.errstate(divide="ignore", invalid="ignore"):
        det = sxx * syy - sxy**2
        kx = (syy * sxz - sxy * syz) / det
        ky = (sxx * syz - sxy * sxz) / det
        k = np.hypot(kx, ky)
        # the circle of radius r through the arc, on the side of the Kåsa centre
        cx, cy = mx + r * kx / k, my + r * ky / k
    ok = np.isfinite(cx) & np.isfinite(cy)
    cx, cy = np.where(ok, cx, mx), np.where(ok, cy, my)
    an, bn = (a @ sec.normal)[:, None], (b @ sec.normal)[:, None]
    for it in range(iterations + 1):
        dx, dy = x - cx[:, seg], y - cy[:, seg]
        rho = np.hypot(dx, dy)
        ux, uy = dx / rho, dy / rho
        res = rho - r
        w = 1.0 / np.maximum(1.0 - (ux * an + uy * bn) ** 2, 1e-12)
        wx, wy = w * ux, w * uy
        hxx, hxy, hyy = ssum(wx * ux), ssum(wx * uy), ssum(wy * uy)
        if it == iterations:
            break
        gx, gy = ssum(wx * res), ssum(wy * res)
        with np.errstate(divide="ignore", invalid="ignore"):
            det = hxx * hyy - hxy**2
            sx, sy = (hyy * gx - hxy * gy) / det, (hxx * gy - hxy * gx) / det
        good = np.isfinite(sx) & np.isfinite(sy)
        cx, cy = cx + np.where(good, sx, 0.0), cy + np.where(good, sy, 0.0)
    resid = np.sqrt(w) * res
    score = np.mean(resid**2, axis=1)
    # the lit surface faces the camera (at −mean): outward normal towards it
    cam = -sec.mean - P  # (N, 3)
    facing = np.mean(ux * dot(a, cam) + uy * dot(b, cam) > 0, axis=1)
    valid = (facing > 0.5) & np.all(ok, axis=1) & np.isfinite(score)
    score = np.where(valid, score, np.inf)
    centres = np.stack([cx, cy], axis=-1)
    H = np.stack([np.stack([hxx, hxy], -1), np.stack([hxy, hyy], -1)], -2)
    return score, resid, centres, H, (a, b)


def _refine_direction(sec: _Sections, d: np.ndarray, *, tol: float, max_iter: int = 50):
    """Levenberg–Marquardt on the axis direction alone (the per-frame circle centres are
    solved for each direction: variable projection), finite-difference Jacobian."""
    h = 1e-6
    score, res = _section_fits(sec, d[None])[:2]
    cost, res = float(score[0]), res[0]
    lam = 1e-3
    for _ in range(max_iter):
        a, b = perpendicular_basis(d[None])
        trial = unit_rows(np.stack([d + h * a[0], d + h * b[0]]))
        J = (_section_fits(sec, trial)[1] - res).T / h  # (N, 2)
        JtJ, g = J.T @ J, J.T @ res
        while True:
            step = -np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ)), g)
            new = unit_rows(d + step[0] * a[0] + step[1] * b[0])
            s_new, r_new = _section_fits(sec, new[None])[:2]
            if float(s_new[0]) <= cost:
                d, cost, res = new, float(s_new[0]), r_new[0]
                lam = max(lam / 5.0, 1e-9)
                break
            lam *= 8.0
            if lam > 1e8:
                return d, cost
        if np.hypot(*step) < tol:
            break
    return d, cost


def _fit_cylinder_axis(
    sec: _Sections,
    *,
    coarse_step: float = math.radians(4.0),
    min_elevation: float = math.radians(2.0),
    candidates: int = 2,
    tol: float = 1e-7,
):
    """The axis direction of a cylinder of known radius from its sections by one plane.

    The points (`sec`, camera frame) lie on the laser plane and on the cylinder, which may
    move from frame to frame (an eccentric gauge on a turning table) but keeps its
    direction. A coarse grid of directions (`coarse_step` apart, at least `min_elevation`
    out of the plane; a subsample of the points) scores every direction by the in-plane
    residual of per-frame fixed-radius circle fits ([`_section_fits`][]), vectorised over
    directions; the best `candidates` separated minima are refined on all points
    ([`_refine_direction`][], to `tol` rad).

    **Returns:** `(direction, score)`, the unit direction with `direction · n̂ > 0` and
    its mean squared in-plane residual (mm²).
    """
    coarse = sec.subsample(12)
    dirs = _direction_grid(sec.normal, coarse_step, min_elevation)
    score = np.concatenate(
        [_section_fits(coarse, dirs[k : k + 256], 3)[0] for k in range(0, len(dirs), 256)]
    )
    picked = []
    for j in np.argsort(score):
        if not np.isfinite(score[j]) or len(picked) == candidates:
            break
        if all(abs(dirs[j] @ dirs[p]) < math.cos(3 * coarse_step) for p in picked):
            picked.append(j)
    if not picked:
        raise ValueError(
            "no cylinder of the gauge radius fits the scan with its lit side facing the "
            "camera: check the gauge radius, the laser plane and the camera"
        )
    best = min((_refine_direction(sec, dirs[j], tol=tol) for j in picked), key=lambda t: t[1])
    d = best[0] if best[0] @ sec.normal > 0 else -best[0]
    return d, best[1]


def _straight_line_ms(sec: _Sections) -> float:
    """Mean squared distance of the points from a straight line fitted to each frame."""
    P = sec.P
    cnt = np.diff(np.append(sec.starts, len(P)))
    m = np.add.reduceat(P, sec.starts, axis=0) / cnt[:, None]  # (K, 3) frame centroids
    outer = np.add.reduceat(P[:, :, None] * P[:, None, :], sec.starts, axis=0)
    cov = outer / cnt[:, None, None] - m[:, :, None] * m[:, None, :]
    ev = np.linalg.eigvalsh(cov)  # ascending: off the plane, across the line, along it
    # eigenvalues of an exactly straight stripe round to ±1e-20: never below 0
    return max(float(np.sum(cnt * (ev[:, 0] + ev[:, 1])) / len(P)), 0.0)


def _stage_from_sections(sec: _Sections, d: np.ndarray, delta_omega: float):
    """Table axis and eccentricity from the per-frame section circles along `d`.

    Along the table axis z_m (= ±d), frame i's gauge centre sits at c + rot(−i Δω) e:
    the eccentric gauge circles the table axis against the table's turn. Both senses of
    z_m are tried; the one that fits the centres' motion wins when it fits clearly
    better (an eccentric gauge), else z_m points towards image up (−y_c).
    """
    score, _, centres, H, (a, b) = _section_fits(sec, d[None])
    centres, H, a, b = centres[0], H[0], a[0], b[0]
    # whitened rows Lᵀ (c_f − c − R_f e), H_f = L Lᵀ
    eps = 1e-12 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(2)
    L = np.linalg.cholesky(H + eps)
    ang = -sec.frames * delta_omega
    Rf = np.stack(
        [np.stack([np.cos(ang), -np.sin(ang)], -1), np.stack([np.sin(ang), np.cos(ang)], -1)], -2
    )  # (K, 2, 2)
    fits = {}
    for sense in (1.0, -1.0):
        # coordinates in the basis (a, s b) of z_m = s d: (c_a, s c_b), H → F H F
        F = np.diag([1.0, sense])
        Lt = np.swapaxes(F @ L, 1, 2)
        A = np.concatenate([Lt, Lt @ Rf], axis=2).reshape(-1, 4)
        rhs = np.einsum("kij,kj->ki", Lt, centres @ F).reshape(-1)
        if len(sec.frames) >= 3:
            sol = np.linalg.lstsq(A, rhs, rcond=1e-12)[0]
        else:  # too few frames for the eccentricity
            sol = np.append(np.linalg.lstsq(A[:, :2], rhs, rcond=1e-12)[0], [0.0, 0.0])
        fits[sense] = (float(np.sum((A @ sol - rhs) ** 2)), sol)
    ss = {s: f[0] for s, f in fits.items()}
    from_data = min(ss.values()) < 0.25 * max(ss.values())
    if from_data:
        sense = min(ss, key=ss.get)
    else:
        sense = 1.0 if d @ np.array([0.0, -1.0, 0.0]) >= 0 else -1.0
    sol = fits[sense][1]
    z, bb = sense * d, sense * b
    p = sec.mean + sol[0] * a + sol[1] * bb  # a point on the table axis
    e3 = sol[2] * a + sol[3] * bb
    # measurement frame: origin at the foot of the perpendicular from the camera, x_m
    # towards the camera (the gauge fixing of `gauge_residuals`: t_m_c = (d, 0, 0))
    origin = p - (p @ z) * z
    dist = float(np.linalg.norm(origin))
    if dist < 1e-6:
        raise ValueError("the table axis passes through the camera: degenerate stage scan")
    x_m = -origin / dist
    R_m_c = np.stack([x_m, np.cross(z, x_m), z])
    stage = RotaryStage(R_m_c, np.array([dist, 0.0, 0.0]), delta_omega)
    ecc = np.array([e3 @ R_m_c[0], e3 @ R_m_c[1]])
    return stage, ecc, float(np.sqrt(score[0])), bool(from_data)
