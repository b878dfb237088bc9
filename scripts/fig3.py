"""Reproduce the paper's Fig. 3: thick-lens vs pinhole model error against a real lens.

Guo, Cui & Wu (Sensors 2024) §4.1: "the solutions of the object plane coordinates from the
image plane coordinates at β = 0.5, 1, 2 … compared with the position of the imaging point
calculated by the law of refraction". Here, for each |β|:

1. A rig with the shipped double-Gauss lens (f = 99.5 mm, e = −33.1 mm: H lies 33 mm
   behind H′) focused by the Scheimpflug condition on a laser plane at 60° to the axis
   (`build_rig`, the sensor pose refined on real-ray spots).
2. A grid of pixels across the sensor. The **truth** for a pixel is the laser-plane point
   whose real chief ray (through the centre of the stop, Snell's law through every
   surface) lands on that pixel: `rig.laser_points(uv)` (the paraxial guess), then Newton
   on the two in-plane coordinates until `rig.project` returns the pixel (≤ 1e-9 px).
3. **Ideal models** with the rig's paraxial data (`rig.nominal_thick_lens_params()`:
   f, e from the paraxial trace, the sensor at the paraxial Scheimpflug conjugate of the
   laser plane):
   - *thick lens* (paper eq. 12) with those parameters;
   - *pinhole*: the same model with e = 0 — the paper's small-aperture assumption that
     the two principal points coincide (its Fig. 2). The projection centre stays at the
     camera origin H′ with the sensor where it is, so the pixel's ray leaves H′ in the
     direction P′ → H′ (a pinhole at H′ seeing the real sensor), while the real (nodal)
     ray leaves H parallel to it: the two are parallel lines |e| apart along the axis,
     equal on the axis and drifting apart with the field angle.
   Both reconstruct via `stripe_to_camera` onto the rig's laser plane.
4. **Fitted models** (the fair comparison): each model's free parameters fitted by
   Levenberg–Marquardt to the ray-traced correspondences (pixel → 3-D truth, laser plane
   known): thick lens f, e, z0, φ, θ, x0, y0 (dx, dy fixed: the datasheet pitch); pinhole
   `K_h` (α, β, γ, x0, y0, paper eq. 14) with a free pose (rotation, translation) in the
   rig frame, as calibration on boards would give it. Also the best plane-to-plane
   homography: the floor for *any* distortion-free central camera, because pixel →
   laser-plane is a homography for every such camera.

Errors are 3-D distances (µm) between the model's and the true laser-plane point.

    python scripts/fig3.py --out DIR [--grid 33 25] [--betas 0.5 1 2] [--no-fit]

writes DIR/fig3.png and DIR/fig3.json.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import scheimflux as sf
from scheimflux.geometry._transforms import rotation_matrix, rotation_vector
from scheimflux.simulate import build_rig, load_lens, paraxial

THICK_NAMES = ("f", "e", "z0", "phi", "theta", "x0", "y0")


# ------------------------------------------------------------------------ truth


def _plane_basis(n: np.ndarray):
    """Origin (foot of the perpendicular) and orthonormal in-plane basis of n · X = 1."""
    nh = n / np.linalg.norm(n)
    origin = nh / np.linalg.norm(n)
    helper = np.eye(3)[np.argmin(np.abs(nh))]
    e1 = np.cross(nh, helper)
    e1 /= np.linalg.norm(e1)
    return origin, np.stack([e1, np.cross(nh, e1)])


def pixel_grid(rig, nu: int, nv: int, margin: float = 0.0) -> np.ndarray:
    """`nv × nu` pixels spanning the sensor (pixel centres 0 … size − 1), shape (nv, nu, 2)."""
    w, h = rig.sensor_size
    u = np.linspace(margin, w - 1 - margin, nu)
    v = np.linspace(margin, h - 1 - margin, nv)
    return np.stack(np.meshgrid(u, v), axis=-1)


def true_points(rig, uv: np.ndarray, iterations: int = 10, step_mm: float = 1e-4):
    """Laser-plane points whose real chief rays land on pixels `uv` `(N, 2)`.

    Newton on the two in-plane coordinates, Jacobian by central differences of
    `rig.project` (one batch of 5N points per iteration: one compilation).
    **Returns:** `(X (N, 3), residual_px (N,), ok (N,))`.
    """
    uv = np.asarray(uv, dtype=np.float64)
    n = np.asarray(rig.laser_plane)
    _, basis = _plane_basis(n)
    X = np.asarray(rig.laser_points(jnp.asarray(uv)))
    offsets = np.concatenate([np.zeros((1, 3)), step_mm * basis, -step_mm * basis])  # (5, 3)
    ok = np.ones(len(uv), bool)
    res = np.full(len(uv), np.inf)
    for _ in range(iterations):
        batch = (X[None] + offsets[:, None]).reshape(-1, 3)
        p, valid = rig.project(jnp.asarray(batch))
        p = np.asarray(p).reshape(5, -1, 2)
        ok = np.asarray(valid).reshape(5, -1).all(axis=0)
        r = p[0] - uv
        res = np.linalg.norm(r, axis=1)
        if np.all(res[ok] < 1e-10):
            break
        J = np.stack([(p[1] - p[3]), (p[2] - p[4])], axis=-1) / (2 * step_mm)  # (N, 2, 2)
        J = np.where(ok[:, None, None], J, np.eye(2))
        ds = np.linalg.solve(J, -r[..., None])[..., 0]
        X = X + ds @ basis
    return X, res, ok & (res < 1e-6)


# ------------------------------------------------------------------------ models


def thick_lens(params: dict) -> sf.ThickLensScheimpflug:
    return sf.ThickLensScheimpflug(**params)


def pinhole_e0(params: dict) -> sf.ThickLensScheimpflug:
    """The paper's pinhole reduction: the thick lens with e = 0 (centre at H′)."""
    return sf.ThickLensScheimpflug(**{**params, "e": 0.0})


def reconstruct(camera, n, uv) -> np.ndarray:
    return np.asarray(sf.stripe_to_camera(camera, sf.LaserPlane(jnp.asarray(n)), uv).points)


def _thick_points(theta, fixed, n, uv):
    cam = sf.ThickLensScheimpflug(*theta, fixed[0], fixed[1])
    return sf.stripe_to_camera(cam, sf.LaserPlane(n), uv).points


def _pinhole_points(theta, n, uv):
    K = theta[:5]
    R = rotation_matrix(theta[5:8])
    t = theta[8:11]
    n_p = R.T @ n / (1.0 - n @ t)
    X_p = sf.stripe_to_camera(sf.Pinhole(*K), sf.LaserPlane(n_p), uv).points
    return X_p @ R.T + t


def _homography_points(h, origin, basis, uv):
    H = jnp.append(h, 1.0).reshape(3, 3)
    ph = jnp.concatenate([uv, jnp.ones((uv.shape[0], 1))], axis=1) @ H.T
    st = ph[:, :2] / ph[:, 2:]
    return origin + st @ basis


@jax.jit
def _thick_res(theta, fixed, n, uv, X):
    return (_thick_points(theta, fixed, n, uv) - X).ravel()


@jax.jit
def _pinhole_res(theta, n, uv, X):
    return (_pinhole_points(theta, n, uv) - X).ravel()


@jax.jit
def _homography_res(h, origin, basis, uv, X):
    return (_homography_points(h, origin, basis, uv) - X).ravel()


_thick_jac = jax.jit(jax.jacfwd(_thick_res))
_pinhole_jac = jax.jit(jax.jacfwd(_pinhole_res))
_homography_jac = jax.jit(jax.jacfwd(_homography_res))


def levenberg_marquardt(res, jac, x0, iterations: int = 100):
    """Plain LM with Marquardt's diagonal scaling (NumPy driver, JAX residuals)."""
    x = np.asarray(x0, dtype=np.float64)
    r = np.asarray(res(x))
    cost = r @ r
    lam = 1e-3
    for _ in range(iterations):
        J = np.asarray(jac(x))
        A = J.T @ J
        g = J.T @ r
        d = np.diag(A) + 1e-12 * np.max(np.diag(A))
        for _ in range(20):
            step = np.linalg.solve(A + lam * np.diag(d), -g)
            r_new = np.asarray(res(x + step))
            c_new = r_new @ r_new
            if np.isfinite(c_new) and c_new <= cost:
                break
            lam *= 10.0
        else:
            break
        done = cost - c_new <= 1e-14 * cost
        x, r, cost = x + step, r_new, c_new
        lam = max(lam / 10.0, 1e-15)
        if done:
            break
    return x


def _pinhole_init(cam0: sf.ThickLensScheimpflug) -> np.ndarray:
    """Pinhole K_h and pose reproducing the e = 0 model's rays exactly (QR of −K_f)."""
    M = -np.asarray(cam0.K_f)  # forward ray directions ∝ −K_f p̃ (real, inverted image)
    Q, U = np.linalg.qr(M)
    D = np.diag(np.sign(np.diag(U)))
    Q, U = Q @ D, D @ U
    if np.linalg.det(Q) < 0:  # mirror: put it in K (α < 0)
        F = np.diag([-1.0, 1.0, 1.0])
        Q, U = Q @ F, F @ U
    Kinv = U / U[2, 2]
    K = np.linalg.inv(Kinv)
    K /= K[2, 2]
    rv = np.asarray(rotation_vector(jnp.asarray(Q)))
    return np.array([K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2], *rv, 0.0, 0.0, 0.0])


def _dlt(uv, st):
    """Normalised DLT homography pixel → in-plane (s, t), h33 = 1."""

    def norm(p):
        c = p.mean(0)
        s = math.sqrt(2) / np.mean(np.linalg.norm(p - c, axis=1))
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])

    Ta, Tb = norm(uv), norm(st)
    a = np.c_[uv, np.ones(len(uv))] @ Ta.T
    b = np.c_[st, np.ones(len(st))] @ Tb.T
    rows = []
    for (x, y, w), (xp, yp, wp) in zip(a, b):
        rows.append([0, 0, 0, -wp * x, -wp * y, -wp * w, yp * x, yp * y, yp * w])
        rows.append([wp * x, wp * y, wp * w, 0, 0, 0, -xp * x, -xp * y, -xp * w])
    _, _, vt = np.linalg.svd(np.asarray(rows))
    H = np.linalg.inv(Tb) @ vt[-1].reshape(3, 3) @ Ta
    return (H / H[2, 2]).ravel()[:8]


def fit_models(rig, uv, X, nominal):
    """Fit thick lens, pinhole (+pose) and homography to (uv, X); model points for each."""
    n = jnp.asarray(rig.laser_plane)
    uvj, Xj = jnp.asarray(uv), jnp.asarray(X)
    fixed = jnp.asarray([nominal["dx"], nominal["dy"]])
    x0 = np.array([nominal[k] for k in THICK_NAMES])
    th = levenberg_marquardt(
        lambda p: _thick_res(jnp.asarray(p), fixed, n, uvj, Xj),
        lambda p: _thick_jac(jnp.asarray(p), fixed, n, uvj, Xj),
        x0,
    )
    X_thick = np.asarray(_thick_points(jnp.asarray(th), fixed, n, uvj))
    p0 = _pinhole_init(pinhole_e0(nominal))
    ph = levenberg_marquardt(
        lambda p: _pinhole_res(jnp.asarray(p), n, uvj, Xj),
        lambda p: _pinhole_jac(jnp.asarray(p), n, uvj, Xj),
        p0,
    )
    X_pin = np.asarray(_pinhole_points(jnp.asarray(ph), n, uvj))
    origin, basis = _plane_basis(np.asarray(n))
    st = (X - origin) @ basis.T
    h0 = _dlt(uv, st)
    ob = (jnp.asarray(origin), jnp.asarray(basis))
    hh = levenberg_marquardt(
        lambda p: _homography_res(jnp.asarray(p), *ob, uvj, Xj),
        lambda p: _homography_jac(jnp.asarray(p), *ob, uvj, Xj),
        h0,
    )
    X_h = np.asarray(_homography_points(jnp.asarray(hh), *ob, uvj))
    params = {
        "thick_lens": dict(zip(THICK_NAMES, map(float, th))),
        "pinhole": dict(
            zip(
                ("alpha", "beta", "gamma", "x0", "y0", "r1", "r2", "r3", "t1", "t2", "t3"),
                map(float, ph),
            )
        ),  # fmt: skip
    }
    return {"thick_lens": X_thick, "pinhole": X_pin, "homography": X_h}, params


# ------------------------------------------------------------------------ experiment


def _stats(err_um: np.ndarray) -> dict:
    return {"max_um": float(np.max(err_um)), "rms_um": float(np.sqrt(np.mean(err_um**2)))}


def run_beta(beta: float, grid=(33, 25), *, fit: bool = True, refine: bool = True, lens=None):
    """Errors (µm) of the ideal and fitted models for one |β|; see the module docstring."""
    lens = load_lens("double-gauss") if lens is None else lens
    rig = build_rig(lens, magnification=beta, refine=refine)
    nominal = rig.nominal_thick_lens_params()
    g = pixel_grid(rig, *grid)
    uv = g.reshape(-1, 2)
    X, res_px, ok = true_points(rig, uv)
    n = np.asarray(rig.laser_plane)
    ideal = {
        "thick_lens": reconstruct(thick_lens(nominal), n, uv),
        "pinhole": reconstruct(pinhole_e0(nominal), n, uv),
    }
    err = {f"ideal/{k}": 1e3 * np.linalg.norm(v - X, axis=1) for k, v in ideal.items()}
    params = {}
    if fit:
        fitted, params = fit_models(rig, uv[ok], X[ok], nominal)
        for k, v in fitted.items():
            e = np.full(len(uv), np.nan)
            e[ok] = 1e3 * np.linalg.norm(v - X[ok], axis=1)
            err[f"fitted/{k}"] = e
    par = paraxial(rig.lens)
    return {
        "beta": beta,
        "grid": list(grid),
        "uv": uv,
        "valid": ok,
        "truth_residual_px_max": float(np.max(res_px[ok])),
        "errors_um": err,
        "stats": {k: _stats(v[ok]) for k, v in err.items()},
        "nominal": nominal,
        "rig": {
            "z0": float(rig.z0),
            "phi_deg": math.degrees(float(rig.phi)),
            "theta_deg": math.degrees(float(rig.theta)),
            "entrance_pupil_z_camera": float(par.z_principal_image - par.z_entrance_pupil),
            "object_pixel_um": 1e3 * float(rig.dx) / beta,
        },
        "fitted_params": params,
    }


def run(betas=(0.5, 1.0, 2.0), grid=(33, 25), *, fit: bool = True, refine: bool = True):
    return [run_beta(b, grid, fit=fit, refine=refine) for b in betas]


def to_json(results) -> dict:
    out = []
    for r in results:
        out.append({k: v for k, v in r.items() if k not in ("uv", "valid", "errors_um")})
        out[-1]["n_pixels"] = int(np.sum(r["valid"]))
    return {
        "description": "Fig. 3 reproduction: model error (um) on the laser plane vs the "
        "real chief-ray trace through the double-Gauss lens; see docs/fig3.md",
        "results": out,
    }


def plot(results, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncol = len(results)
    fig, axes = plt.subplots(3, ncol, figsize=(4.2 * ncol, 10.5), squeeze=False)
    styles = {
        "ideal/thick_lens": ("C0", "thick lens (paraxial)"),
        "ideal/pinhole": ("C3", "pinhole, e = 0 (paraxial)"),
        "fitted/thick_lens": ("C0", "thick lens, fitted"),
        "fitted/pinhole": ("C3", "pinhole K_h + pose, fitted"),
        "fitted/homography": ("k", "best homography"),
    }
    for j, r in enumerate(results):
        uv, ok = r["uv"], r["valid"]
        x0, y0 = r["nominal"]["x0"], r["nominal"]["y0"]
        rad = np.hypot(uv[:, 0] - x0, uv[:, 1] - y0)
        ax = axes[0, j]
        for k in ("ideal/thick_lens", "ideal/pinhole"):
            c, lab = styles[k]
            ax.scatter(rad[ok], r["errors_um"][k][ok], s=4, c=c, label=lab)
        ax.set_yscale("log")
        ax.set_ylim(bottom=0.05)  # the principal pixel itself is exact for both
        ax.set_title(f"|β| = {r['beta']:g}: ideal models")
        ax.set_xlabel("distance from principal pixel (px)")
        ax.set_ylabel("error on laser plane (µm)")
        ax.legend(fontsize=7)
        ax = axes[1, j]
        for k in ("fitted/thick_lens", "fitted/pinhole", "fitted/homography"):
            if k in r["errors_um"]:
                c, lab = styles[k]
                m = "o" if "thick" in k else ("x" if "pin" in k else ".")
                ax.scatter(rad[ok], r["errors_um"][k][ok], s=6, c=c, marker=m, label=lab)
        ax.set_title(f"|β| = {r['beta']:g}: fitted models")
        ax.set_xlabel("distance from principal pixel (px)")
        ax.set_ylabel("error (µm)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        ax = axes[2, j]
        nu, nv = r["grid"]
        e = np.where(ok, r["errors_um"]["ideal/pinhole"], np.nan).reshape(nv, nu)
        w, h = uv[:, 0].max(), uv[:, 1].max()
        im = ax.imshow(e, extent=(0, w, h, 0), cmap="viridis")
        fig.colorbar(im, ax=ax, label="µm")
        ax.set_title(f"|β| = {r['beta']:g}: ideal pinhole error map")
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def table(results) -> str:
    keys = list(results[0]["stats"])
    lines = [f"{'|β|':>4} " + " ".join(f"{k:>26}" for k in keys)]
    lines.append(f"{'':>4} " + " ".join(f"{'max / rms (µm)':>26}" for _ in keys))
    for r in results:
        cells = [
            f"{r['stats'][k]['max_um']:12.4g} / {r['stats'][k]['rms_um']:<11.4g}" for k in keys
        ]
        lines.append(f"{r['beta']:>4g} " + " ".join(f"{c:>26}" for c in cells))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("fig3_out"))
    ap.add_argument("--betas", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    ap.add_argument("--grid", type=int, nargs=2, default=[33, 25], metavar=("NU", "NV"))
    ap.add_argument("--no-fit", action="store_true", help="skip the fitted models")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    results = run(tuple(args.betas), tuple(args.grid), fit=not args.no_fit)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fig3.json").write_text(json.dumps(to_json(results), indent=2))
    plot(results, args.out / "fig3.png")
    print(table(results))
    print(f"wrote {args.out / 'fig3.png'} and {args.out / 'fig3.json'} "
          f"({time.perf_counter() - t0:.1f} s)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
