"""Lens × magnification benchmark on pupil-integrated, ray-traced worlds.

    python benchmarks/lenses.py [--quick] [--lenses tessar,double-gauss] [--mags 0.5,1,2]
                                [--seeds 3] [--models thick-lens,opencv] [--imaging centroid]

For each shipped lens (singlet, achromat, double-gauss, tessar) and magnification |β|
(0.5, 1, 2) a rig is built (`build_rig`: 2448 × 2048 px at 3.45 µm, laser plane at 60°
to the axis, the sensor refocused on it through the real lens) and observed with 15 board
views of 11 × 8 corners (0.03 px corner noise, 0.05 px stripe noise) by pupil-integrated
imaging (`imaging="centroid"`: each pixel is the centroid of the bundle filling the
stop, vignetting included; the lens's own f-number unless `--f-number`). Each data set
is calibrated with every model in `--models` (default: scheimflux's thick lens with its
default options, and OpenCV's tilted model, `model="opencv", opencv_flags="tilted"`);
another model name (e.g. a non-central camera) is passed through to `calibrate(model=)`.

Error: laser-plane points on a 16 × 13 grid over 5 … 95 % of the sensor, imaged by the
same tracer as the data (pupil centroids; chief rays with `--imaging chief`; noise-free),
reconstructed with each calibration (`stripe_to_camera`); the RMS over all pairs of the
error of their distances, in µm, median over the seeds. Points outside the boards'
coverage are included (that is where the models extrapolate). `--quick`: tessar, ×0.5, one seed.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from scheimflux.calibrate import calibrate
from scheimflux.reconstruct._reconstruct import stripe_to_camera
from scheimflux.simulate import build_rig, load_lens, simulate_observations
from scheimflux.simulate._pupil import pupil_grid, pupil_points
from scheimflux.simulate._scenes import trace_points
from scheimflux.targets._board import Checkerboard

SENSOR = (2448, 2048)
PITCH_MM = 0.00345
CORNER_NOISE = 0.03
STRIPE_NOISE = 0.05
LENSES = ("singlet", "achromat", "double-gauss", "tessar")
MAGS = (0.5, 1.0, 2.0)
MODELS = ("thick-lens", "opencv")


def _board(magnification: float) -> Checkerboard:
    """11 × 8 inner corners spanning ~65 % of the object field's width."""
    field_mm = SENSOR[0] * PITCH_MM / magnification
    square = round(0.65 * field_mm / 12.0, 3)
    return Checkerboard(11, 8, square)


def _grid_points(rig, sampling, imaging):
    """Laser-plane truth points over the sensor and their pixels, imaged like the data
    (pupil centroids, or chief rays for `--imaging chief`)."""
    w, h = rig.sensor_size
    g = np.stack(
        np.meshgrid(np.linspace(0.05, 0.95, 16) * (w - 1), np.linspace(0.05, 0.95, 13) * (h - 1)),
        -1,
    ).reshape(-1, 2)
    X = np.asarray(rig.laser_points(g))
    if imaging == "chief":
        uv, ok = trace_points(rig, X)
    else:
        uv, ok, _, _ = pupil_points(rig, X, sampling)
    return X[ok], uv[ok]


def _pair_error_um(cal, X, uv) -> float:
    P = np.asarray(stripe_to_camera(cal.camera, cal.plane, uv).points)
    i, j = np.triu_indices(len(X), 1)
    d = np.linalg.norm(P[i] - P[j], axis=1) - np.linalg.norm(X[i] - X[j], axis=1)
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d**2)) * 1e3) if len(d) else math.nan


def _calibrate(obs, model: str):
    kw = dict(throw=False)
    if model == "opencv":
        kw.update(model="opencv", opencv_flags="tilted")
    elif model != "thick-lens":
        kw.update(model=model)
    t0 = time.perf_counter()
    cal = calibrate(obs, **kw)
    conv = all(f.converged for f in cal.fits.values())
    return cal, conv, time.perf_counter() - t0


def run_world(lens_name, mag, seeds, models, imaging, f_number, rings):
    lens = load_lens(lens_name)
    if f_number is not None:
        lens = lens.with_f_number(f_number)
    rig = build_rig(lens, mag, sensor=SENSOR, pixel_pitch_mm=(PITCH_MM, PITCH_MM))
    sampling = pupil_grid(rings)
    X, uv = _grid_points(rig, sampling, imaging)
    errs = {m: [] for m in models}
    flags = {m: "" for m in models}
    for seed in seeds:
        obs, _ = simulate_observations(
            rig,
            _board(mag),
            n_views=15,
            corner_noise_px=CORNER_NOISE,
            stripe_noise_px=STRIPE_NOISE,
            stage_scan=False,
            seed=seed,
            imaging=imaging,
            pupil=sampling,
        )
        for m in models:
            try:
                cal, conv, _ = _calibrate(obs, m)
            except Exception as err:  # noqa: BLE001 - a benchmark cell, not a library path
                print(f"  {lens_name} ×{mag:g} seed {seed} {m}: failed: {str(err)[:120]}")
                errs[m].append(math.nan)
                flags[m] = " (failed)"
                continue
            errs[m].append(_pair_error_um(cal, X, uv))
            if not conv:
                flags[m] = " (not converged)"
    def median(v):
        v = np.asarray(v, dtype=float)
        return float(np.median(v[np.isfinite(v)])) if np.isfinite(v).any() else math.nan

    return {m: (median(errs[m]), flags[m]) for m in models}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tessar, ×0.5, one seed")
    ap.add_argument("--lenses", default=",".join(LENSES))
    ap.add_argument("--mags", default=",".join(f"{m:g}" for m in MAGS))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--models", default=",".join(MODELS), help="calibrate(model=) names")
    ap.add_argument("--imaging", choices=("centroid", "chief"), default="centroid")
    ap.add_argument("--f-number", type=float, default=None, help="default: each lens's own")
    ap.add_argument("--rings", type=int, default=8, help="pupil quadrature rings")
    args = ap.parse_args(argv)
    lenses = ["tessar"] if args.quick else args.lenses.split(",")
    mags = [0.5] if args.quick else [float(m) for m in args.mags.split(",")]
    seeds = [0] if args.quick else list(range(args.seeds))
    models = [m.strip() for m in args.models.split(",") if m.strip()]

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    print(
        f"{len(lenses)} lens(es) × {len(mags)} magnification(s), seeds {seeds}, imaging "
        f"{args.imaging}, {args.rings} rings; load average {load:.1f}\n"
    )
    hdr = f"{'lens':<14} {'|β|':>4} " + " ".join(f"{m + ' µm':>16}" for m in models)
    if "thick-lens" in models and "opencv" in models:
        hdr += f" {'thick/opencv':>12}"
    print(hdr + f" {'time s':>7}")
    print("-" * (len(hdr) + 8))
    for name in lenses:
        for mag in mags:
            t0 = time.perf_counter()
            res = run_world(name, mag, seeds, models, args.imaging, args.f_number, args.rings)
            row = f"{name:<14} {mag:>4g} " + " ".join(
                f"{res[m][0]:>16.4f}" if not res[m][1] else f"{res[m][0]:>8.4f}{res[m][1]:>8.8}"
                for m in models
            )
            if "thick-lens" in res and "opencv" in res:
                row += f" {res['thick-lens'][0] / res['opencv'][0]:>12.2f}"
            print(row + f" {time.perf_counter() - t0:>7.0f}", flush=True)


if __name__ == "__main__":
    main()
