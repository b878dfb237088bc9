"""Lens × magnification benchmark on pupil-integrated, ray-traced worlds.

    python benchmarks/lenses.py [--quick] [--lenses tessar,double-gauss] [--mags 0.5,1,2]
                                [--seeds 3] [--models thick-lens,thick-lens-noncentral,opencv]
                                [--imaging centroid] [--max-radius-px R]
                                [--cache DIR] [--json FILE [--resume]]
    python benchmarks/calibrate.py --lenses [LIST] [--quick] ...   (the same table)

For each shipped lens (singlet, achromat, double-gauss, tessar) and magnification |β|
(0.5, 1, 2) a rig is built (`build_rig`: 2448 × 2048 px at 3.45 µm, laser plane at 60°
to the axis, the sensor refocused on it through the real lens) and observed with 15 board
views of 11 × 8 corners (0.03 px corner noise, 0.05 px stripe noise) by pupil-integrated
imaging (`imaging="centroid"`: each pixel is the centroid of the bundle filling the
stop, vignetting included, 16 rings unless `--rings`; the lens's own f-number unless
`--f-number`). Each data set is calibrated with every model in `--models` (default:
scheimflux's central thick lens and its non-central thick lens, both with their default
options, and OpenCV's tilted model, `model="opencv", opencv_flags="tilted"`);
`thick-lens-noncentral/profile` is the non-central thick lens with `gauge="profile"`;
`thick-lens-noncentral/released-tilt` is a diagnostic (`RELEASED_TILT`: the tilt
released in the non-central solve), and any other name is passed through to
`calibrate(model=)`.

Error: laser-plane points on a 16 × 13 grid over 5 … 95 % of the sensor, imaged by the
same tracer as the data (pupil centroids; chief rays with `--imaging chief`; noise-free),
reconstructed with each calibration (`stripe_to_camera`); the RMS over all pairs of the
error of their distances, in µm, median over the seeds. Two figures: over the points
inside the convex hull of all detected corners ("covered": where the calibration has
data; the table's main number) and over the whole grid (in brackets: the sensor's
corners, where every model extrapolates its distortion polynomial). A calibration that
fails is NaN, never left out silently. `--max-radius-px R` drops the corners and
stripe pixels farther than R px from the sensor's centre before calibrating (the
vignetted outer field, where a pupil-centroid pixel is not the image of one ray:
docs/noncentral.md); the grid is not cut, so "covered" is then the hull of the corners
kept. `--quick`: tessar, ×0.5, one seed. `--cache`
keeps each seed's observations and the grid; `--json` logs one line per calibration, and
`--resume` takes the calibrations already logged there (so parts of the table can run
in separate processes and be joined).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import time

import cv2
import numpy as np

from scheimflux.calibration import calibrate
from scheimflux.io import read_observations, write_observations
from scheimflux.io._observations import within_radius
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
MODELS = ("thick-lens", "thick-lens-noncentral", "opencv")


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


def _covered(obs, uv) -> np.ndarray:
    """Which pixels lie inside the convex hull of every detected corner of every view: the
    part of the image the calibration data cover (outside it every model extrapolates)."""
    c = np.concatenate([np.asarray(v.corners_px) for v in obs.views])
    c = c[np.all(np.isfinite(c), axis=1)].astype(np.float32)
    hull = cv2.convexHull(c)
    return np.array([cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in uv])


def _pair_error_um(cal, X, uv) -> float:
    """RMS (µm) over all pairs of the error of reconstructed distances; a point that does
    not reconstruct makes the whole figure NaN (never silently dropped)."""
    if len(X) < 2:
        return math.nan
    P = np.asarray(stripe_to_camera(cal.camera, cal.plane, uv).points)
    if not np.all(np.isfinite(P)):
        return math.nan
    i, j = np.triu_indices(len(X), 1)
    d = np.linalg.norm(P[i] - P[j], axis=1) - np.linalg.norm(X[i] - X[j], axis=1)
    return float(np.sqrt(np.mean(d**2)) * 1e3)


#: Named calibrations: `calibrate(**kwargs)`. Any other name is passed as `model=`.
CONFIGS = {
    "thick-lens": dict(),
    "thick-lens-noncentral": dict(model="thick-lens-noncentral"),
    # OpenCV's tilted model creeps along its tilt valley: on the Tessar at x1 and x2 its
    # camera solve took 1300-1500 steps (x1) and more than 2000 (x2), and stopped at 200
    # it was 3-4x worse (docs/benchmarks.md); a comparator is compared converged
    "opencv": dict(model="opencv", opencv_flags="tilted", max_steps=2000),
    # the non-central thick lens with `gauge="profile"` (tilt free, axis point profiled)
    "thick-lens-noncentral/profile": dict(model="thick-lens-noncentral", gauge="profile"),
}


#: Diagnostic (not a library option): the non-central thick lens with the sensor tilt
#: and the axis point released (pixel pitch and f held, `_gauge.distorted_freeze`) in
#: its own solve and the joint solves after it, the central solves before it unchanged.
#: No `freeze=` reaches this: it would also free the tilt in the distortion-free first
#: solve, where the tilt is an exact gauge and the rank check refuses the data.
RELEASED_TILT = "thick-lens-noncentral/released-tilt"


@contextlib.contextmanager
def _released_tilt():
    import importlib

    from scheimflux.calibration.core._gauge import distorted_freeze
    from scheimflux.camera import ThickLensNonCentral

    names = ("scheimflux.calibration.core._camera", "scheimflux.calibration._calibrate")
    mods = [importlib.import_module(m) for m in names]
    orig = [m.least_squares for m in mods]

    def solve(fn, params, data, freeze=(), **kw):
        if isinstance(params.camera, ThickLensNonCentral):
            freeze = distorted_freeze(tuple(freeze))
        return orig[0](fn, params, data, freeze=freeze, **kw)

    try:
        for m in mods:
            m.least_squares = solve
        yield
    finally:
        for m, f in zip(mods, orig):
            m.least_squares = f


def _calibrate(obs, name: str):
    released = name == RELEASED_TILT
    kw = dict(throw=False, **CONFIGS.get("thick-lens-noncentral" if released else name,
                                         dict(model=name)))  # fmt: skip
    t0 = time.perf_counter()
    with _released_tilt() if released else contextlib.nullcontext():
        cal = calibrate(obs, **kw)
    conv = all(f.converged for f in cal.fits.values())
    return cal, conv, time.perf_counter() - t0


def _data_tag(lens_tag, mag, imaging, sampling) -> str:
    """Cache file stem: the world and, for pupil centroids, the quadrature's size (data
    traced with another number of rings is not reused)."""
    tag = f"{lens_tag}-x{mag:g}-{imaging}"
    return tag if imaging == "chief" else f"{tag}-n{sampling.size}"


def _world_data(rig, lens_tag, mag, seed, imaging, sampling, cache):
    """The observations of one seed (from `cache` when there)."""
    path = None
    if cache:
        path = os.path.join(cache, f"{_data_tag(lens_tag, mag, imaging, sampling)}-s{seed}.json")
        if os.path.exists(path):
            return read_observations(path)
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
    if path:
        os.makedirs(cache, exist_ok=True)
        write_observations(path, obs, overwrite=True)
    return obs


def _median(v) -> float:
    v = np.asarray(v, dtype=float)
    return float(np.median(v[np.isfinite(v)])) if np.isfinite(v).any() else math.nan


def _logged(log, rec):
    """The last record of `log` (JSON lines) for the same lens, |β|, seed, imaging and model."""
    if not log or not os.path.exists(log):
        return None
    key = ("lens", "mag", "seed", "imaging", "rings", "model", "max_radius_px")
    found = None
    with open(log) as fh:
        for line in fh:
            r = json.loads(line)
            if all(r.get(k) == rec.get(k) for k in key):
                found = r
    return found


def run_world(lens_name, mag, seeds, models, imaging, f_number, rings, cache=None, log=None,
              resume=False, max_radius_px=None):  # fmt: skip
    """One lens × magnification: per model the medians over the seeds of the error on the
    covered part of the laser plane and on the full-sensor grid, and the flags."""
    lens = load_lens(lens_name)
    if f_number is not None:
        lens = lens.with_f_number(f_number)
    lens_tag = lens_name if f_number is None else f"{lens_name}-f{f_number:g}"
    rig = build_rig(lens, mag, sensor=SENSOR, pixel_pitch_mm=(PITCH_MM, PITCH_MM))
    sampling = pupil_grid(rings)
    grid = cache and os.path.join(cache, f"{_data_tag(lens_tag, mag, imaging, sampling)}-grid.npz")
    if grid and os.path.exists(grid):
        with np.load(grid) as z:
            X, uv = z["X"], z["uv"]
    else:
        X, uv = _grid_points(rig, sampling, imaging)
        if grid:
            os.makedirs(cache, exist_ok=True)
            np.savez(grid, X=X, uv=uv)
    errs = {m: dict(covered=[], full=[]) for m in models}
    flags = {m: "" for m in models}
    for seed in seeds:
        obs = _world_data(rig, lens_tag, mag, seed, imaging, sampling, cache)
        if max_radius_px is not None:
            obs = within_radius(obs, max_radius_px)
        inside = _covered(obs, uv)
        for m in models:
            rec = dict(lens=lens_tag, mag=mag, seed=seed, imaging=imaging, model=m,
                       n_covered=int(inside.sum()), n_full=len(X))  # fmt: skip
            if imaging != "chief":
                rec.update(rings=rings)
            if max_radius_px is not None:
                rec.update(max_radius_px=max_radius_px)
            done = _logged(log, rec) if resume else None
            if done is not None:
                errs[m]["covered"].append(done.get("covered_um", math.nan))
                errs[m]["full"].append(done.get("full_um", math.nan))
                if "error" in done or not done.get("converged", True):
                    flags[m] = "failed" if "error" in done else "not converged"
                print(f"  {lens_tag} ×{mag:g} seed {seed} {m}: from {log}: "
                      f"covered_um={done.get('covered_um')}", flush=True)  # fmt: skip
                continue
            try:
                cal, conv, dt = _calibrate(obs, m)
            except Exception as err:  # noqa: BLE001 - a benchmark cell, not a library path
                print(f"  {lens_tag} ×{mag:g} seed {seed} {m}: failed: {str(err)[:160]}")
                errs[m]["covered"].append(math.nan)
                errs[m]["full"].append(math.nan)
                flags[m] = "failed"
                rec.update(error=str(err)[:300])
            else:
                ec = _pair_error_um(cal, X[inside], uv[inside])
                ef = _pair_error_um(cal, X, uv)
                errs[m]["covered"].append(ec)
                errs[m]["full"].append(ef)
                if not conv:
                    flags[m] = flags[m] or "not converged"
                rec.update(covered_um=ec, full_um=ef, converged=conv, time_s=dt,
                           reproj_px=cal.reprojection_rms_px)  # fmt: skip
                pupil = getattr(cal.camera, "pupil", None)
                if pupil is not None:
                    rec.update(pupil_mm=[float(c) for c in np.asarray(pupil)],
                               lateral_mm=[float(c) for c in np.asarray(cal.camera.lateral)],
                               pivot_mm=[float(c) for c in np.asarray(cal.camera.pivot)])
            print(f"  {lens_tag} ×{mag:g} seed {seed} {m}: "
                  + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                              for k, v in rec.items() if k not in ("lens", "mag", "model",
                                                                   "seed", "imaging", "rings",
                                                                   "max_radius_px")),
                  flush=True)  # fmt: skip
            if log:
                with open(log, "a") as fh:
                    fh.write(json.dumps(rec) + "\n")
    return {
        m: (_median(errs[m]["covered"]), _median(errs[m]["full"]), flags[m]) for m in models
    }


def table(args) -> None:
    """Run the lens × magnification table (arguments of `main`) and print it."""
    lenses = ["tessar"] if args.quick else args.lenses.split(",")
    mags = [0.5] if args.quick else [float(m) for m in args.mags.split(",")]
    seeds = [0] if args.quick else list(range(args.seeds))
    models = [m.strip() for m in args.models.split(",") if m.strip()]

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    print(
        f"{len(lenses)} lens(es) × {len(mags)} magnification(s), seeds {seeds}, imaging "
        f"{args.imaging}, {args.rings} rings"
        + (f", corners within {args.max_radius_px:g} px" if args.max_radius_px else "")
        + f"; load average {load:.1f}; "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n"
    )
    ref = "opencv" if "opencv" in models else None
    label = {"thick-lens": "central", "thick-lens-noncentral": "non-central",
             RELEASED_TILT: "released tilt",
             "thick-lens-noncentral/profile": "nc profile"}  # fmt: skip
    lab = [label.get(m, m)[:20] for m in models]
    cols = "".join(f" {x + ' µm':>25}" for x in lab)
    ratios = "".join(f" {x[:12] + ' / cv':>17}" for m, x in zip(models, lab) if ref and m != ref)
    hdr = f"{'lens':<14} {'|β|':>4}{cols}{ratios} {'time s':>7}"
    print("covered part of the laser plane (full-sensor grid in brackets); medians over seeds")
    print(hdr)
    print("-" * len(hdr))
    any_flag = False
    for name in lenses:
        for mag in mags:
            t0 = time.perf_counter()
            res = run_world(name, mag, seeds, models, args.imaging, args.f_number,
                            args.rings, args.cache, args.json, args.resume,
                            args.max_radius_px)  # fmt: skip
            row = f"{name:<14} {mag:>4g}"
            for m in models:
                cov, full, flag = res[m]
                cell = f"{cov:.3f} [{full:.2f}]" + ("*" if flag else "")
                any_flag = any_flag or bool(flag)
                row += f" {cell:>25}"
            for m in models:
                if ref and m != ref:
                    row += f" {res[m][0] / res[ref][0]:>17.2f}"
            print(row + f" {time.perf_counter() - t0:>7.0f}", flush=True)
    if any_flag:
        print("* a seed did not converge or failed (see the lines above)")


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The table's options other than `--quick` and `--lenses` (shared with
    `benchmarks/calibrate.py --lenses`)."""
    ap.add_argument("--mags", default=",".join(f"{m:g}" for m in MAGS))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--models", default=",".join(MODELS), help="calibrate(model=) names")
    ap.add_argument("--imaging", choices=("centroid", "chief"), default="centroid")
    ap.add_argument("--f-number", type=float, default=None, help="default: each lens's own")
    ap.add_argument("--rings", type=int, default=16, help="pupil quadrature rings")
    ap.add_argument("--max-radius-px", type=float, default=None,
                    help="drop corners and stripe pixels beyond this radius (px) from the "
                         "sensor centre")  # fmt: skip
    ap.add_argument("--cache", metavar="DIR", help="keep/reuse each seed's observations here")
    ap.add_argument("--json", metavar="FILE", help="append one JSON line per calibration")
    ap.add_argument("--resume", action="store_true",
                    help="take calibrations already in --json FILE from it")  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tessar, ×0.5, one seed")
    ap.add_argument("--lenses", default=",".join(LENSES), help="comma-separated lens names")
    add_arguments(ap)
    table(ap.parse_args(argv))


if __name__ == "__main__":
    main()
