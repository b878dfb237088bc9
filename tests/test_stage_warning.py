"""Weak-axis warnings: the predicted across-frame length error against ray-traced truth.

The stage block alone (camera and laser plane are the rig's own model, as in
test_stage_calibration.py), on ray-traced ring-gauge scans. The predicted error is the
stage covariance propagated to lengths between field points seen in frame 0 and half a
turn later; the measured one compares the same lengths through the calibrated and the
true stage. Monte Carlo (10 seeds, 0.05 px, under load): a nearly coaxial gauge
(10 µm off the axis, 6 frames over 50°) predicts 2.87 µm, measured RMS 2.12 µm (ratio
1.35); the eccentric 12 × 30° scan predicts 1.02 µm, measured 0.85 µm (6 seeds).
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from test_stage_calibration import SIGMA_MM, _obs, _scan

from scheimflux.calibration import calibrate_stage
from scheimflux.calibration.trust._stage_warning import (
    WEAK_AXIS_UM,
    _fit_covariance,
    axis_conditioning,
    axis_warning,
    reference_pixels,
)
from scheimflux.camera import ThickLensScheimpflug
from scheimflux.geometry import LaserPlane
from scheimflux.reconstruct._reconstruct import intersect_ray_plane
from scheimflux.simulate import paper_rig

COAX = dict(ecc=(0.01, 0.0), n_frames=6, delta_omega_deg=10.0)
GOOD = dict(ecc=(0.6, -0.4), n_frames=12, delta_omega_deg=30.0)  # shapes of test_stage_calibration


@pytest.fixture(scope="module")
def rig():
    return paper_rig(refine=False)


@pytest.fixture(scope="module")
def model(rig):
    return (
        ThickLensScheimpflug(**rig.nominal_thick_lens_params()),
        LaserPlane(jnp.asarray(rig.laser_plane)),
    )


def _solve(rig, model, seed, kw):
    cam, plane = model
    scan = _scan(rig, seed=seed, **kw)
    obs = _obs(rig, [f.px for f in scan.frames], kw["delta_omega_deg"])
    cal = calibrate_stage(cam, plane, obs, sigma_stripe_mm=SIGMA_MM)
    cond = axis_conditioning(
        cal.fit.params, cal.fit.free_mask, _fit_covariance(cal.fit),
        reference_pixels(*rig.sensor_size), frame_index=np.arange(kw["n_frames"]),
    )  # fmt: skip
    return scan, cal, cond


def _across_errors_um(rig, model, stage, true_stage, j):
    """Length errors (µm) of every pair of reference points, frame 0 against frame j."""
    cam, plane = model
    X = [np.asarray(intersect_ray_plane(cam.backproject_one(jnp.asarray(p)), plane)[0])
         for p in reference_pixels(*rig.sensor_size)]  # fmt: skip

    def lengths(st):
        m = lambda x, i: np.asarray(st.to_measurement(jnp.asarray(x), float(i)))  # noqa: E731
        return np.array([np.linalg.norm(m(a, 0) - m(b, j)) for a in X for b in X])

    return 1e3 * (lengths(stage) - lengths(true_stage))


def test_coaxial_short_arc_warns_with_cause_and_remedy(rig, model):
    scan, cal, cond = _solve(rig, model, 0, COAX)
    assert cond.weak and cond.sigma_across_um > 2 * WEAK_AXIS_UM
    assert cond.n_frames == 6 and cond.arc_deg == pytest.approx(50.0)
    assert cond.opposite_frame == 18  # half a turn at 10° per step
    text = axis_warning(cond)
    for part in ("weak table axis", "nearly coaxial", "short arc (50°)", "few frames (6)",
                 "µm", "target on the table", "eccentric"):  # fmt: skip
        assert part in text, (part, text)
    # the predicted size against this one realisation: the error is one draw of a
    # zero-mean error of that σ, so only a loose bound (the Monte Carlo test is the check)
    err = _across_errors_um(rig, model, cal.stage, scan.stage, cond.opposite_frame)
    assert np.abs(err).max() < 5 * cond.sigma_across_um


def test_eccentric_full_scan_does_not_warn(rig, model):
    _, _, cond = _solve(rig, model, 1, GOOD)
    assert not cond.weak and axis_warning(cond) is None
    assert cond.arc_deg == pytest.approx(330.0) and cond.eccentricity_mm > 0.5
    print("well-determined axis:", cond)


@pytest.mark.slow  # 10 re-solves on fresh ray-traced noise (~3 min under load)
def test_predicted_across_frame_error_matches_monte_carlo(rig, model):
    errs, preds = [], []
    for seed in range(10):
        scan, cal, cond = _solve(rig, model, 100 + seed, COAX)
        errs.append(_across_errors_um(rig, model, cal.stage, scan.stage, cond.opposite_frame))
        preds.append(cond.sigma_across_um)
    rms = np.sqrt(np.mean(np.square(errs), axis=0)).max()  # the worst pair's spread
    pred = float(np.median(preds))
    # issue target: within a factor 2 (10 draws: the RMS itself scatters by ~±22 %)
    assert 0.5 < rms / pred < 2.0, (rms, pred)
    assert math.isfinite(pred)
