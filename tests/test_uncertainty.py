"""Uncertainty of what users measure: lengths between reconstructed points.

A per-point σ is relative to the camera frame and is dominated by its poorly determined
depth (the camera datum); a length between two points is not. The fast tests check the
propagation against finite differences and the datum's cancellation; the slow test
re-solves fresh noisy ray-traced data sets and compares the spread of the lengths with
the prediction.
"""

import dataclasses

import equinox as eqx
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.calibration import calibrate, fit_diagnostics, length_uncertainty
from scheimflux.calibration.core._solve import split
from scheimflux.io import View
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard

SIGMA_CORNER, SIGMA_STRIPE = 0.03, 0.05


@pytest.fixture(scope="module")
def scene():
    obs, truth = simulate_observations(
        paper_rig(refine=False), Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    return obs, truth


@pytest.fixture(scope="module")
def cal(scene):
    return calibrate(scene[0], distortion="none")


def _pairs(truth):
    """Pixel pairs 1–2 mm apart on the stripes of two different views."""
    a = np.asarray(truth.stripe_px[0])[::90]
    b = np.asarray(truth.stripe_px[3])[::90][: len(a)]
    return a[: len(b)], b


def _lengths(camera, plane, a, b):
    Xa = np.asarray(sf.stripe_to_camera(camera, plane, a).points)
    Xb = np.asarray(sf.stripe_to_camera(camera, plane, b).points)
    return np.linalg.norm(Xa - Xb, axis=1)


def test_length_sigma_equals_finite_difference_propagation(cal, scene):
    a, b = _pairs(scene[1])
    d = fit_diagnostics(cal)
    out = length_uncertainty(cal, a, b, diag=d)
    fit = cal.fits["joint"]
    x0, unravel, static = split(fit.params, fit.free_mask)
    idx = d.select(("camera.", "plane."))
    L0 = _lengths(cal.camera, cal.plane, a, b)
    np.testing.assert_allclose(out["length"], L0, rtol=1e-12)
    # dL/dθ by central differences on the independent reconstruction (stripe_to_camera)
    cols = []
    for i in idx:
        # a thousandth of the parameter's σ: truncation ~1e-6 relative, rounding of
        # the ~1 mm lengths (1e-16 mm) / h × σ ~ 1e-13 mm, far below the σ_L ~ 1e-5 mm
        h = 1e-3 * float(d.std[i])
        p = [eqx.combine(unravel(x0.at[i].add(s * h)), static) for s in (1, -1)]
        cols.append(
            (_lengths(p[0].camera, p[0].plane, a, b) - _lengths(p[1].camera, p[1].plane, a, b))
            / (2 * h)
        )
    g = np.stack(cols, 1)
    S = d.covariance[np.ix_(idx, idx)]
    sigma_fd = np.sqrt(np.einsum("nq,qr,nr->n", g, S, g))
    np.testing.assert_allclose(out["sigma_calibration"], sigma_fd, rtol=2e-3)


def test_the_camera_datum_cancels_in_lengths(cal, scene):
    a, b = _pairs(scene[1])
    out = length_uncertainty(cal, a, b, sigma_px=SIGMA_STRIPE)
    # the per-point σ (camera frame) is dominated by the datum; the length is far better
    # determined than either end
    assert np.all(out["sigma_calibration"] < 0.2 * out["point_sigma_a"].max(axis=1))
    # the pixels' own noise adds in quadrature
    np.testing.assert_allclose(
        out["sigma"] ** 2, out["sigma_calibration"] ** 2 + out["sigma_pixels"] ** 2, rtol=1e-12
    )
    assert np.all(out["sigma_pixels"] > 0)
    with pytest.raises(ValueError, match="same shape"):
        length_uncertainty(cal, a, b[:-1])


@pytest.mark.slow
def test_length_sigma_vs_monte_carlo_of_re_solves(cal, scene):
    # 30 fresh noise realisations on the same ray-traced geometry, each calibrated from
    # scratch; the spread of the reconstructed lengths (same pixels) against the
    # predicted calibration σ. 30 samples know a σ to ±13 %: factor 1.5 is > 3 such σ.
    obs, truth = scene
    a, b = _pairs(truth)
    pred = length_uncertainty(cal, a, b)["sigma_calibration"]
    rng = np.random.default_rng(11)
    L = []
    for _ in range(30):
        views = [
            View(
                t_c + SIGMA_CORNER * rng.standard_normal(t_c.shape),
                t_s + SIGMA_STRIPE * rng.standard_normal(np.shape(t_s)),
            )
            for t_c, t_s in zip(truth.corners_px, truth.stripe_px)
        ]
        c = calibrate(dataclasses.replace(obs, views=views), distortion="none")
        L.append(_lengths(c.camera, c.plane, a, b))
    mc = np.std(np.asarray(L), axis=0, ddof=1)
    ratio = mc / pred
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
