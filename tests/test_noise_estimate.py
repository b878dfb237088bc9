"""The noise measured, not assumed (`trust._variance`), the joint solve held to its
corners' camera (`trust._shift`), and the gates no real camera fails.

The end-to-end scene is ray traced through the paper's lens (`simulate_observations`: 8
views of a 6 x 5 checkerboard) with corner noise 0.06 px where 0.03 px is stated, and two
views' laser lines 0.4 px noisier across the line (drawn here, as a speckled line
scatters its centres)."""

import dataclasses
import math
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.calibration import SystemParams, calibrate, free_spec, parameter_labels
from scheimflux.calibration.core._model import make_data
from scheimflux.calibration.trust._gates import (
    MIN_FOCAL_FRACTION,
    focal_length_gate,
    principal_point_gate,
)
from scheimflux.calibration.trust._shift import TAIL, camera_shift, chi2_quantile
from scheimflux.calibration.trust._variance import (
    VarianceComponents,
    sigma_change,
    with_factors,
)
from scheimflux.camera import Pinhole
from scheimflux.geometry import Pose
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard

CORNER_PX, STATED_CORNER_PX = 0.06, 0.03
NOISY, EXTRA_PX = (1, 3), 0.4


def test_chi2_quantile_is_scipys():
    from scipy.stats import chi2

    for dof in (1, 2, 5, 9, 12, 40, 100):
        for tail in (TAIL, 1e-3, 0.05):
            assert chi2_quantile(dof, tail) == pytest.approx(chi2.ppf(1 - tail, dof), rel=1e-8)


def test_focal_length_and_principal_point_gates():
    # the collapsed camera of a real capture (fx 2.7 px on a 640 x 480 webcam) fails ...
    g = focal_length_gate(2.68, 3.55, 640, 480)
    assert not g.passed and "no real lens" in g.message and "field of view" in g.message
    # ... a webcam's (fx 550, fy 733: a 16:9 stream resized to 4:3) passes
    assert focal_length_gate(549.9, 733.1, 640, 480).passed
    # at the limit: a field of view of 2 atan(5) across the larger side
    side = 640
    assert focal_length_gate(MIN_FOCAL_FRACTION * side, MIN_FOCAL_FRACTION * side, 640, 480).passed
    assert not focal_length_gate(0.99 * MIN_FOCAL_FRACTION * side, 100.0, 640, 480).passed
    assert not focal_length_gate(500.0, 2100.0, 640, 480).passed  # 4.2x from square
    assert principal_point_gate(330.0, 250.0, 640, 480).passed
    assert principal_point_gate(-600.0, 250.0, 640, 480).passed  # within one sensor size
    g = principal_point_gate(-700.0, 250.0, 640, 480)
    assert not g.passed and g.value == pytest.approx(700 / 640)


def _pinhole_params():
    cam = Pinhole(alpha=1000.0, beta=1000.0, gamma=0.0, x0=320.0, y0=240.0)
    poses = Pose(jnp.zeros((2, 3)), jnp.ones((2, 3)))
    return SystemParams(cam, poses)


def _fit(params, spec, H, cost, n):
    return SimpleNamespace(
        params=params, free_mask=spec, labels=parameter_labels(params, spec),
        normal_matrix=H, cost=cost, n_observations=n,
    )  # fmt: skip


def test_camera_shift_is_the_chi_square_of_the_move_in_the_corners_covariance():
    params = _pinhole_params()
    spec = free_spec(params, ("board_poses",))
    labels = parameter_labels(params, spec)
    assert labels == ["camera.alpha", "camera.beta", "camera.gamma", "camera.x0", "camera.y0"]
    # independent derivation: a diagonal JᵀJ with s² = 2 cost / (n − p) = 4 gives
    # σ_k = 2 / sqrt(H_kk), and a move δ_k gives d² = Σ (δ_k / σ_k)²
    h = np.array([4.0, 1.0, 16.0, 0.25, 1.0])
    n, p = 105, 5
    cost = 0.5 * 4.0 * (n - p)
    sigma = 2.0 / np.sqrt(h)
    camera = _fit(params, spec, np.diag(h), cost, n)
    delta = np.array([1.0, -2.0, 0.0, 3.0, 0.5]) * sigma
    moved = dataclasses.replace(
        params,
        camera=Pinhole(
            alpha=1000.0 + delta[0], beta=1000.0 + delta[1], gamma=0.0 + delta[2],
            x0=320.0 + delta[3], y0=240.0 + delta[4],
        ),
    )  # fmt: skip
    joint = _fit(moved, spec, None, 0.0, n)
    shift = camera_shift(camera, joint)
    assert shift.dof == 5 and shift.s2 == pytest.approx(4.0)
    assert shift.d2 == pytest.approx(1 + 4 + 0 + 9 + 0.25, rel=1e-9)
    assert shift.worst[0] == "camera.x0" and shift.worst[3] == pytest.approx(sigma[3])
    assert shift.limit == pytest.approx(chi2_quantile(5)) and not shift.moved
    far_camera = dataclasses.replace(params.camera, alpha=1000.0 + 5 * sigma[0])
    far = dataclasses.replace(params, camera=far_camera)
    far_shift = camera_shift(camera, _fit(far, spec, None, 0.0, n))
    assert far_shift.d2 == pytest.approx(25.0) and far_shift.moved == (25.0 > chi2_quantile(5))
    assert camera_shift(_fit(params, spec, None, cost, n), joint) is None  # no JᵀJ kept


@pytest.fixture(scope="module")
def traced():
    return simulate_observations(
        paper_rig(refine=False), Checkerboard(6, 5, 0.4), n_views=8, stage_scan=False,
        seed=0, corner_noise_px=CORNER_PX,
    )  # fmt: skip


def _across(px):
    d = np.linalg.svd(px - px.mean(axis=0), full_matrices=False)[2][0]
    return np.array([-d[1], d[0]])


@pytest.fixture(scope="module")
def noisy(traced):
    obs, truth = traced
    rng = np.random.default_rng(100)
    views = []
    for i, v in enumerate(obs.views):
        s = np.array(v.stripe_px)
        if i in NOISY:
            s = s + rng.normal(0.0, EXTRA_PX, (len(s), 1)) * _across(s)
        views.append(dataclasses.replace(v, stripe_px=s))
    return dataclasses.replace(obs, views=views)


def test_with_factors_scales_each_group_and_keeps_the_stated_floor(traced):
    obs, _ = traced
    data = make_data(obs, sigma_corner_px=0.03, sigma_stripe_mm=1e-3)
    V = len(obs.views)
    f = np.linspace(0.25, 4.0, V)
    vc = VarianceComponents(4.0, f, None, {})
    new = with_factors(data, vc)
    assert float(new.sigma_corner_px) == pytest.approx(0.06)
    eff = float(new.sigma_stripe_mm) * np.asarray(new.stripe_scale)
    np.testing.assert_allclose(eff, 1e-3 * np.sqrt(f), rtol=1e-12)
    floored = with_factors(data, vc, floor=data)
    eff = float(floored.sigma_stripe_mm) * np.asarray(floored.stripe_scale)
    np.testing.assert_allclose(eff, 1e-3 * np.sqrt(np.maximum(f, 1.0)), rtol=1e-12)
    assert sigma_change(data, new) == pytest.approx(math.log(2.0))
    assert sigma_change(data, data) == 0.0


@pytest.mark.slow
def test_the_noise_estimate_recovers_the_traced_noise(noisy):
    cal = calibrate(noisy)  # default: noise estimated, stated 0.03 / 0.05 px as priors
    noise = cal.quality.noise
    assert noise["mode"] == "estimate" and cal.quality.passed
    # Förstner's estimate of a variance over redundancy r has relative σ sqrt(2 / r), so
    # σ within sqrt(1 / (2 r)); r ≈ 2 · 8 · 30 − (camera + poses) ≈ 420: 3.5 %; 4 σ of it
    red = 2 * 8 * 30 - 60
    assert noise["corner_px"] == pytest.approx(CORNER_PX, rel=4 * math.sqrt(1 / (2 * red)))
    px = np.array(noise["stripe_px"])
    clean = np.setdiff1d(np.arange(len(px)), NOISY)
    # the clean views stay at the stated floor (their distances scatter less than the
    # stated pixel σ gives them at the footprint) ...
    assert np.all(px[clean] == 0.05)
    # ... the noisy views are raised to their own σ across the line, sqrt(0.05² + 0.4²):
    # within 4 σ of a variance over each view's ~450 of redundancy (13 %) and the gain's
    # approximation of how a pixel's error moves a point off its board (7 %)
    own = math.hypot(0.05, EXTRA_PX)
    np.testing.assert_allclose(px[list(NOISY)], own, rtol=0.2)
    assert not any("scatter" in w and "corners" in w for w in cal.quality.warnings)  # 2x: not said
    # the camera was not held: the lines refine it within what the corners allow
    assert not noise["camera_shift"]["moved"] and "camera" not in cal.freeze
