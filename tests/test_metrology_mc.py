"""Monte Carlo check of the measured values' uncertainty with fresh calibrations (slow).

Each repeat draws new noise on the ray-traced corners, board stripes and step-gauge
stripe, calibrates from scratch (the production solver) and measures the step with
`measure_stripes`. Checked against the **ray-traced truth**, not the repeats' mean:
±U (k = 2) must cover the truth in ≥ 95 % of the repeats, and the stated u must lie
within a factor 1.5 of the repeats' spread (issue 15's targets).

On this small scene (4 views of a 6 × 5 × 0.4 mm board) only `distortion="none"`
calibrates (the default radial-tangential model leaves the plane's offset and the
boards' depth undetermined: RankDeficientError, noise-free), and its model error against
the real lens biases the step by +0.135 µm noise-free (docs/metrology.md, "Where the
bias came from"). Measured 2026-12-02: spread 0.104 µm, stated u 0.0445 µm, mean
+0.187 µm from the truth. The test is a strict xfail: it records the failure and fails
once the targets are met, so that whoever fixes the model error sees it.
"""

import dataclasses

import numpy as np
import pytest

from scheimflux.calibrate import calibrate
from scheimflux.io import View
from scheimflux.metrology import Steps, measure_points, measure_stripes
from scheimflux.simulate import paper_rig, simulate_observations, step_gauge
from scheimflux.targets import Checkerboard

SIGMA_CORNER, SIGMA_STRIPE = 0.03, 0.05
REPEATS = 30


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="model error of the undistorted central camera: +0.19 µm bias, spread 2.3 × u "
    "(docs/metrology.md)",
)
def test_step_uncertainty_vs_monte_carlo_of_re_calibrations():
    rig = paper_rig(refine=False)
    obs, truth = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    prof = step_gauge(rig, (1.5,), step_px=4.0)[0]
    exact = float(measure_points(prof.points_c, Steps(), labels=prof.labels).values[0])
    rng = np.random.default_rng(21)
    values, stds = [], []
    for _ in range(REPEATS):
        views = [
            View(
                t_c + SIGMA_CORNER * rng.standard_normal(t_c.shape),
                t_s + SIGMA_STRIPE * rng.standard_normal(np.shape(t_s)),
            )
            for t_c, t_s in zip(truth.corners_px, truth.stripe_px)
        ]
        cal = calibrate(dataclasses.replace(obs, views=views), distortion="none")
        px = prof.px_true + SIGMA_STRIPE * rng.standard_normal(prof.px_true.shape)
        m = measure_stripes(cal, px, Steps(), labels=prof.labels, sigma_px=SIGMA_STRIPE)
        values.append(float(m.values[0]))
        stds.append(float(m.std[0]))
    values, stds = np.asarray(values), np.asarray(stds)
    spread = np.std(values, ddof=1)
    covered = int(np.sum(np.abs(values - exact) <= 2 * stds))
    print(f"spread {spread * 1e3:.4f} µm, stated u {np.median(stds) * 1e3:.4f} µm, "
          f"bias of the mean {(values.mean() - exact) * 1e3:.4f} µm, truth within ±U in "
          f"{covered} of {REPEATS}")
    # 30 samples know a σ to ±13 %: factor 1.5 is > 3 such σ
    assert 1 / 1.5 < spread / np.median(stds) < 1.5
    # coverage of the truth by ±U: 95 % expected; 30 repeats, ≥ 26 (binomial p = 0.95:
    # P(X < 26) ≈ 6 %)
    assert covered >= 26


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
