"""The thick lens's gauge (issue 16 part 1): what the frozen nominal values may not change.

Data are ray traced through a real double Gauss (never made by the model under test),
noise-free, so every difference between two calibrations is the gauge's doing (or the
solver's tolerance), not noise.
"""


import jax.numpy as jnp
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.calibrate import DEFAULT_FREEZE, calibrate_camera, fit_laser_plane, with_nominal
from scheimflux.calibrate._gauge import (
    DISTORTED_GAUGE,
    PIXEL_PITCH,
    distorted_freeze,
    gauge_spectrum,
)
from scheimflux.calibrate._model import camera_residuals, make_data
from scheimflux.simulate import build_rig, load_lens, paraxial, simulate_observations
from scheimflux.targets import Checkerboard


def test_distorted_freeze_releases_the_tilt_and_axis_point():
    for how in ("nominal", "closed-form"):
        ideal = DEFAULT_FREEZE[("thick-lens", how)]
        assert set(distorted_freeze(ideal)) == set(PIXEL_PITCH + DISTORTED_GAUGE)
        assert "camera.phi" not in distorted_freeze(ideal)


@pytest.fixture(scope="module")
def scene():
    base = load_lens("double-gauss")
    lens = base.scaled(50.0 / float(paraxial(base).efl), name="double-gauss-f50")
    # the axis meets the sensor 29 px off its centre
    rig = build_rig(lens, 0.5, stop_semi_diameter=2.0, principal_pixel=(824.5, 584.5))
    obs, truth = simulate_observations(
        rig,
        Checkerboard(11, 8, 0.9),
        n_views=8,
        corner_noise_px=0.0,
        stripe_noise_px=0.0,
        stage_scan=False,
        seed=1,
    )
    return rig, obs, truth


def _points(obs, truth):
    """Camera + sequential plane (noise-free: the plane is exact up to the camera)."""
    cc = calibrate_camera(obs)
    plane = fit_laser_plane(cc.camera, cc.poses, obs, sigma_mm=1e-3).plane
    px = np.concatenate([np.asarray(p) for p in truth.stripe_px])
    idx = np.random.default_rng(0).choice(len(px), 150, replace=False)
    X = np.asarray(sf.stripe_to_camera(cc.camera, plane, jnp.asarray(px[idx])).points)
    Xt = np.concatenate([np.asarray(p) for p in truth.stripe_c])[idx]
    return cc, X, Xt


def _distances(X):
    return np.linalg.norm(X[:, None] - X[None], axis=-1)


@pytest.mark.slow
@pytest.mark.xfail(
    reason="issue 16 part 1 not solved: the default still holds the nominal tilt (0.054 µm "
    "for 1° measured); freeing tilt and axis point did not converge in 200 LM steps here",
    strict=False,
)
def test_rounded_nominal_tilt_does_not_change_distances(scene):
    # Target (issue 16): a nominal tilt off by ±1° changes noise-free distances by
    # ≤ 0.005 µm. Before the gauge was moved off the tilt this scene gave 0.054 µm.
    # What remains is the solver's stopping tolerance (1e-5 σ of the unit-scaled state).
    rig, obs, truth = scene
    phi, theta = obs.nominal.tilt_deg
    cc0, X0, truth_points = _points(obs, truth)
    assert cc0.fit.converged
    assert "camera.phi" not in cc0.freeze and "camera.f" in cc0.freeze
    d0 = _distances(X0)
    err_um = float(np.sqrt(np.mean((d0 - _distances(truth_points)) ** 2))) * 1e3
    print(f"distance error vs the ray tracer: {err_um:.4f} um")
    assert err_um < 0.05  # measured 0.277 µm with the axis point held at the centre
    for dphi, dtheta in ((1.0, -1.0), (-1.0, 1.0)):
        cc, X, _ = _points(with_nominal(obs, tilt_deg=(phi + dphi, theta + dtheta)), truth)
        assert cc.fit.converged
        change_um = float(np.sqrt(np.mean((_distances(X) - d0) ** 2))) * 1e3
        assert change_um <= 0.005, (dphi, dtheta, change_um)


@pytest.mark.slow
def test_gauge_singular_values(scene):
    # With only the pixel pitch frozen the distorted thick lens has ONE null direction,
    # along (f, z0, e): its relative singular value is at rounding level, and freezing f
    # lifts the smallest one by more than an order of magnitude. The next weakest is the
    # axis point against the boards' translations; the tilt has no large part in either.
    _, obs, truth = scene
    cc, _, _ = _points(obs, truth)
    data = make_data(obs)
    free = gauge_spectrum(camera_residuals, cc.fit.params, data, PIXEL_PITCH)
    held = gauge_spectrum(camera_residuals, cc.fit.params, data, PIXEL_PITCH + ("camera.f",))
    print(free.format())
    print(held.format())
    s_null, comps = free.directions[0]
    names = {lab for lab, _ in comps}
    assert s_null < 1e-6 and "camera.f" in names
    assert held.singular_values[-1] > 10 * s_null
    s_weak, weak = held.directions[0]
    assert {"camera.x0", "camera.y0"} & {lab for lab, _ in weak}
    for _, cs in (free.directions[0], held.directions[0]):
        assert all(abs(c) < 0.3 for lab, c in cs if lab in ("camera.phi", "camera.theta"))
