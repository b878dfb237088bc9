"""Monte Carlo checks of the measured values' uncertainty with fresh calibrations (slow).

Each repeat draws new noise on every ray-traced pixel (corners, board stripes, gauge scan,
the measured profiles), calibrates from scratch (the production solver) and measures with
`measure_stripes`. Checked against the **ray-traced truth**, not the repeats' mean: ±U
(k = 2) must cover the truth in ≥ 95 % of the repeats (binomial bound), and the stated u
(its random part) must lie within a factor 1.5 of the repeats' spread (issue 15's
targets). The default model on 8 views is the case that must pass; the 4-view
`distortion="none"` case is a strict xfail: there the model error of the undistorted
central camera biases the step by +0.135 µm noise-free (docs/metrology.md, "Where the
bias came from"; measured: spread 0.104 µm, stated u 0.0445 µm, mean +0.187 µm from the
truth), and the xfail fails once the targets are met, so whoever fixes it sees it.
No fast reduced version: one fresh calibration of this scene compiles for minutes and
re-solves in ~10 s (idle 2 cores), beyond the default suite's budget; the propagation
itself is checked fast in tests/test_metrology_chain.py and test_metrology_calcov.py.
"""

import dataclasses
import os

import numpy as np
import pytest

from scheimflux.calibration import calibrate
from scheimflux.io import View
from scheimflux.metrology import Steps, measure_points, measure_stripes
from scheimflux.simulate import paper_rig, simulate_observations, step_gauge
from scheimflux.targets import Checkerboard

SIGMA_CORNER, SIGMA_STRIPE = 0.03, 0.05
# more repeats (a tighter check of the coverage) and other noise draws by environment:
# SCHEIMFLUX_MC_REPEATS=100 SCHEIMFLUX_MC_SEED=7 pytest -m slow tests/test_metrology_mc.py
REPEATS = int(os.environ.get("SCHEIMFLUX_MC_REPEATS", "30"))
SEED = int(os.environ.get("SCHEIMFLUX_MC_SEED", "21"))
SOURCES_RANDOM = ("calibration", "stripe_noise", "fit_residual")


def _noisy_observations(obs, truth, rng):
    """Fresh pixel noise on the ray-traced corners, board stripes and (if any) gauge scan."""
    views = [
        View(c + SIGMA_CORNER * rng.standard_normal(c.shape),
             s + SIGMA_STRIPE * rng.standard_normal(np.shape(s)))
        for c, s in zip(truth.corners_px, truth.stripe_px)
    ]
    stage = obs.stage
    if stage is not None:
        stage = dataclasses.replace(
            stage, frames=[f + SIGMA_STRIPE * rng.standard_normal(f.shape) for f in truth.scan_px]
        )
    return dataclasses.replace(obs, views=views, stage=stage)


def _check_against_truth(name, err, u_all, u_random):
    """Coverage of the truth by ±U (U = 2 u, all sources) and the spread against the
    random part of u (calibration, stripe noise, fit: the frozen-parameter term is one
    fixed offset across the repeats, whose nominal values are the same)."""
    n = len(err)
    if n < 10:
        pytest.fail(f"{n} repeats cannot check a spread or a coverage (SCHEIMFLUX_MC_REPEATS)")
    spread = np.std(err, ddof=1)
    covered = int(np.sum(np.abs(err) <= 2 * u_all))
    ratio = spread / np.median(u_random)
    print(f"{name}: spread {spread * 1e3:.4f} µm, stated u (random part) "
          f"{np.median(u_random) * 1e3:.4f} µm, u {np.median(u_all) * 1e3:.4f} µm, mean error "
          f"{np.mean(err) * 1e3:+.4f} µm, truth within ±U in {covered} of {n}")
    # n samples know a σ to ±1/√(2(n−1)) (13 % for 30): factor 1.5 is > 3 such σ
    assert 1 / 1.5 < ratio < 1.5, name
    # 95 % coverage expected; the bound is the binomial(n, 0.95) 2.5 % quantile
    assert covered >= int(binom_lower(n, 0.95, 0.025)), name


def binom_lower(n, p, alpha):
    """Largest k with P(X < k) <= alpha for X ~ Binomial(n, p)."""
    from math import comb

    cdf, k = 0.0, 0
    while k <= n:
        nxt = cdf + comb(n, k) * p**k * (1 - p) ** (n - k)
        if nxt > alpha:
            return k
        cdf, k = nxt, k + 1
    return n


@pytest.mark.slow
def test_step_and_cylinder_uncertainty_vs_monte_carlo_of_re_calibrations():
    """The default calibration (distortion model, 8 views of an 11 × 8 × 0.3 mm board, a
    ring-gauge scan for the stage): per repeat fresh noise on every ray-traced pixel
    (corners, board stripes, gauge scan, measured profiles), a fresh calibration, then two
    step heights (camera frame) and a bearing radius (measurement frame) with
    `measure_stripes`. Runtime measured at load 11–20 on 2 cores: 568 s for the first
    repeat (compiles), 65–225 s for each further one (≈ 1 h for 30); 415 s for all 30 at
    load 2–4 after the calibration programs shrank; 2653 s at load 16–27 with a warm
    compilation cache (docs/metrology.md)."""
    from scheimflux.calibration import diagnostics
    from scheimflux.metrology import Cylinder, group_covariance
    from scheimflux.simulate import BEARING_RADII_MM, gauge_scan

    rig = paper_rig(refine=False)
    obs, truth = simulate_observations(rig, Checkerboard(11, 8, 0.3), n_views=8, seed=0)
    profs = step_gauge(rig, (1.0, 2.0), step_px=4.0)
    exact = [float(measure_points(p.points_c, Steps(), labels=p.labels).values[0])
             for p in profs]
    scan = gauge_scan(rig, truth.stage, BEARING_RADII_MM[0], n_frames=36, points_per_frame=60)
    cpx = np.concatenate([f.px_true for f in scan.frames])
    cfi = np.concatenate([np.full(len(f.px_true), f.index, float) for f in scan.frames])
    rng = np.random.default_rng(SEED)
    out = {name: ([], [], []) for name in ("step 1 mm", "step 2 mm", "bearing radius")}

    def record(name, m, truth_value):
        err, u_all, u_rand = out[name]
        err.append(float(m.values[0]) - truth_value)
        u_all.append(float(m.std[0]))
        u_rand.append(float(np.sqrt(sum(m.budget[s][0] ** 2 for s in SOURCES_RANDOM))))

    for _ in range(REPEATS):
        cal = calibrate(_noisy_observations(obs, truth, rng))
        d, gc = diagnostics(cal, block="joint"), group_covariance(cal)
        for name, p, e in zip(("step 1 mm", "step 2 mm"), profs, exact):
            px = p.px_true + SIGMA_STRIPE * rng.standard_normal(p.px_true.shape)
            record(name, measure_stripes(cal, px, Steps(), labels=p.labels,
                                         sigma_px=SIGMA_STRIPE, diag=d,
                                         calibration_covariance=gc), e)
        px = cpx + SIGMA_STRIPE * rng.standard_normal(cpx.shape)
        record("bearing radius", measure_stripes(
            cal, px, Cylinder(), frame="measurement", frame_index=cfi, sigma_px=SIGMA_STRIPE,
            diag=d, calibration_covariance=gc), scan.radius)
        # one line per repeat (pytest -s): error and u (µm) of each value so far
        print(f"repeat {len(out['step 1 mm'][0])}: " + "; ".join(
            f"{k} {v[0][-1] * 1e3:+.4f} ± {2 * v[1][-1] * 1e3:.4f}" for k, v in out.items()),
            flush=True)
    for name, (err, u_all, u_rand) in out.items():
        _check_against_truth(name, np.asarray(err), np.asarray(u_all), np.asarray(u_rand))


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="model error of the undistorted central camera: +0.19 µm bias, spread 2.3 × u "
    "(docs/metrology.md)",
)
def test_step_uncertainty_vs_monte_carlo_of_re_calibrations_without_distortion():
    """The model-error case: 4 views of a 6 × 5 × 0.4 mm board, `distortion="none"`."""
    rig = paper_rig(refine=False)
    obs, truth = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    prof = step_gauge(rig, (1.5,), step_px=4.0)[0]
    exact = float(measure_points(prof.points_c, Steps(), labels=prof.labels).values[0])
    rng = np.random.default_rng(21)
    err, u_all, u_rand = [], [], []
    for _ in range(REPEATS):
        cal = calibrate(_noisy_observations(obs, truth, rng), distortion="none")
        px = prof.px_true + SIGMA_STRIPE * rng.standard_normal(prof.px_true.shape)
        m = measure_stripes(cal, px, Steps(), labels=prof.labels, sigma_px=SIGMA_STRIPE)
        err.append(float(m.values[0]) - exact)
        u_all.append(float(m.std[0]))
        u_rand.append(float(np.sqrt(sum(m.budget[s][0] ** 2 for s in SOURCES_RANDOM))))
    _check_against_truth("step 1.5 mm (distortion none)", np.asarray(err), np.asarray(u_all),
                         np.asarray(u_rand))


@pytest.mark.slow
def test_frozen_term_predicts_a_recalibration_with_other_held_values():
    """The frozen-parameter term's total derivative dv/dq (calibration re-solved to first
    order) against two real calibrations of the same noise-free ray-traced data, the
    tilt held at the rounded nominal value and at the rig's exact paraxial one."""
    import math

    from scheimflux.io._observations import Nominal
    from scheimflux.metrology._frozen import frozen_derivatives

    rig = paper_rig(refine=False)
    obs, truth = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    prof = step_gauge(rig, (1.5,), step_px=4.0)[0]
    clean = dataclasses.replace(
        obs, views=[View(c, s) for c, s in zip(truth.corners_px, truth.stripe_px)]
    )
    nom = truth.nominal_params
    exact_tilt = (math.degrees(nom["phi"]), math.degrees(nom["theta"]))
    a = calibrate(clean, distortion="none")
    assert {"camera.phi", "camera.theta"} <= set(a.freeze)
    lab = prof.labels
    D = frozen_derivatives(a, Steps(), prof.px_true, np.zeros(len(lab)), lab, "camera",
                           ["camera.phi", "camera.theta"])
    b = calibrate(
        dataclasses.replace(clean, nominal=Nominal(obs.nominal.focal_length_mm,
                                                   obs.nominal.magnification, exact_tilt)),
        distortion="none",
    )
    va = float(measure_stripes(a, prof.px_true, Steps(), labels=lab, frozen_sigma=None).values[0])
    vb = float(measure_stripes(b, prof.px_true, Steps(), labels=lab, frozen_sigma=None).values[0])
    dq = np.array([float(b.camera.phi - a.camera.phi), float(b.camera.theta - a.camera.theta)])
    predicted = float(D[0] @ dq)
    print(f"re-calibrated {(vb - va) * 1e3:+.4f} µm, predicted {predicted * 1e3:+.4f} µm")
    # first order in a 0.3° change: the second-order rest is below 20 % of the shift
    assert abs(predicted - (vb - va)) < 0.2 * abs(vb - va) + 1e-6 * 1e-3
