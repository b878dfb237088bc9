"""Is pupil-centroid imaging the image of rays? The object points that image to one pixel.

    python benchmarks/raxels.py [--lens tessar] [--mag 0.5] [--depths -2,-1,0,1,2]
                                [--rings 8] [--grid 11x9]

For pixels on a grid over the sensor of `build_rig(lens, mag)` (the `benchmarks/lenses.py`
rig), the object points at several depths (mm along the line of sight, 0 on the laser
plane) that image exactly to the pixel are found by Newton's method on the tracer, once by
chief rays and once by pupil centroids (`simulate._pupil`, vignetting included). A camera
model that maps a pixel to a ray (central or not) can be exact only if those points lie
on a line. Printed per pixel (sorted by distance from the axis point): the points'
largest distance from their fitted line (µm: "bend", depth dependence a ray cannot
describe), the line's shortest distance from the optical axis ("skew", µm: zero for a
line that meets it), where it passes the axis (mm), the bundle's least transmitted share
over the depths (1: no vignetting), and how far and at what angle the centroid's line
lies from the chief ray's (µm at the in-focus point, µrad).
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks.lenses import PITCH_MM, SENSOR  # noqa: E402
from scheimflux.simulate import build_rig, load_lens  # noqa: E402
from scheimflux.simulate._pupil import _image_one, pupil_grid  # noqa: E402


def _solver(image):
    """Newton on the two offsets across the line of sight: the point at a given depth
    whose image (`image(X) -> (uv, transmitted share)`) is the target pixel."""

    def solve(uv_t, X0, e1, e2):
        def r(ab):
            return image(X0 + ab[0] * e1 + ab[1] * e2)[0] - uv_t

        ab = jnp.zeros(2)
        for _ in range(8):
            ab = ab - jnp.linalg.solve(jax.jacfwd(r)(ab), r(ab))
        X = X0 + ab[0] * e1 + ab[1] * e2
        return X, jnp.max(jnp.abs(r(ab))), image(X)[1]

    return jax.jit(jax.vmap(solve))


def _line(P):
    """Fitted line of points `(k, 3)`: bend (max distance, mm), skew distance from the z
    axis (mm), z where it passes the axis, point and unit direction."""
    c = P.mean(0)
    d = np.linalg.svd(P - c)[2][0]
    d = d * np.sign(d[2])
    perp = (P - c) - np.outer((P - c) @ d, d)
    n = np.cross(d, [0.0, 0.0, 1.0])
    nn = np.linalg.norm(n)
    skew = abs(c @ n) / nn if nn > 1e-12 else 0.0
    zc = c[2] - (c[:2] @ d[:2]) / (d[:2] @ d[:2]) * d[2] if nn > 1e-12 else np.nan
    return np.linalg.norm(perp, axis=1).max(), skew, zc, c, d


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="tessar")
    ap.add_argument("--mag", type=float, default=0.5)
    ap.add_argument("--depths", default="-2,-1,0,1,2", help="mm along the line of sight")
    ap.add_argument("--rings", type=int, default=8, help="pupil quadrature rings")
    ap.add_argument("--grid", default="11x9", help="pixels across x down")
    args = ap.parse_args(argv)
    rig = build_rig(load_lens(args.lens), args.mag, sensor=SENSOR,
                    pixel_pitch_mm=(PITCH_MM, PITCH_MM))  # fmt: skip
    sampling = pupil_grid(args.rings)
    depths = np.array([float(t) for t in args.depths.split(",")])
    if 0.0 not in depths or len(depths) < 3:
        raise SystemExit("--depths needs 0 and at least three depths")
    nx, ny = (int(k) for k in args.grid.split("x"))
    w, h = rig.sensor_size
    g = np.stack(np.meshgrid(np.linspace(0.03, 0.97, nx) * (w - 1),
                             np.linspace(0.03, 0.97, ny) * (h - 1)), -1).reshape(-1, 2)  # fmt: skip
    Xf = np.asarray(rig.laser_points(g))
    d0 = Xf / np.linalg.norm(Xf, axis=1, keepdims=True)
    e1 = np.cross(d0, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(d0, e1)
    imagers = {
        "chief": lambda X: (rig._project_one(X)[0], jnp.ones(())),
        "centroid": lambda X: _image_one(rig, X, sampling)[::2],
    }
    found = {}
    for name, image in imagers.items():
        solve = _solver(image)
        P = np.zeros((len(g), len(depths), 3))
        res = np.zeros((len(g), len(depths)))
        frac = np.zeros((len(g), len(depths)))
        for k, t in enumerate(depths):
            X, r, f = solve(*(jnp.asarray(a) for a in (g, Xf + t * d0, e1, e2)))
            P[:, k], res[:, k], frac[:, k] = np.asarray(X), np.asarray(r), np.asarray(f)
        found[name] = (P, res, frac)
    k0 = int(np.argmin(np.abs(depths)))
    rad = np.hypot(g[:, 0] - float(rig.x0), g[:, 1] - float(rig.y0))
    print(f"{args.lens} ×{args.mag:g}, depths {args.depths} mm, {sampling.size} pupil rays")
    print(f"{'r px':>6} {'u':>6} {'v':>6} | chief: {'bend µm':>8} {'skew µm':>8} {'axis mm':>8}"
          f" | centroid: {'bend µm':>8} {'skew µm':>8} {'axis mm':>8} {'transm.':>7}"
          f" | {'offset µm':>9} {'µrad':>6}")  # fmt: skip
    for i in np.argsort(rad):
        cells = []
        lines = {}
        for name in imagers:
            P, res, frac = found[name]
            ok = np.isfinite(P[i]).all(1) & (res[i] < 1e-6)
            if ok.sum() < 3 or not ok[k0]:
                break
            bend, skew, zc, _, d = _line(P[i][ok])
            lines[name] = d
            cell = f"{bend * 1e3:8.4f} {skew * 1e3:8.3f} {zc:8.3f}"
            cells.append(cell + (f" {frac[i][ok].min():7.3f}" if name == "centroid" else ""))
        if len(cells) < 2:
            print(f"{rad[i]:6.0f} {g[i, 0]:6.0f} {g[i, 1]:6.0f} | not found at every depth")
            continue
        off = np.linalg.norm(found["centroid"][0][i, k0] - found["chief"][0][i, k0]) * 1e3
        ang = np.arccos(min(1.0, abs(lines["centroid"] @ lines["chief"]))) * 1e6
        print(f"{rad[i]:6.0f} {g[i, 0]:6.0f} {g[i, 1]:6.0f} |        {cells[0]} |"
              f"           {cells[1]} | {off:9.3f} {ang:6.0f}")  # fmt: skip


if __name__ == "__main__":
    main()
