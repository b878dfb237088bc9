"""The simulated rig: Scheimpflug placement, real-ray focus, projection conventions."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference

from scheimflux.simulate._lens import load_lens, paraxial
from scheimflux.simulate._rig import (
    PAPER_PHI,
    PAPER_THETA,
    build_rig,
    paper_rig,
    paraxial_sensor_pose,
)


@pytest.fixture(scope="module")
def rig():
    return paper_rig()


def _grid(rig, n=3):
    w, h = rig.sensor_size
    g = np.stack(
        np.meshgrid(np.linspace(0.05, 0.95, n) * (w - 1), np.linspace(0.05, 0.95, n) * (h - 1)),
        -1,
    )
    return jnp.asarray(g.reshape(-1, 2))


def test_paper_rig_nominal_values(rig):
    nom = rig.nominal_thick_lens_params()
    assert nom["f"] == pytest.approx(97.0, rel=1e-12)
    assert nom["z0"] == pytest.approx(97.0 * 2.5, rel=1e-12)  # z0 = f (1 + |β|)
    assert nom["phi"] == pytest.approx(PAPER_PHI, abs=1e-12)
    assert nom["theta"] == pytest.approx(PAPER_THETA, abs=1e-12)
    assert (nom["x0"], nom["y0"], nom["dx"], nom["dy"]) == (799.5, 599.5, 0.0044, 0.0044)
    par = paraxial(rig.lens)
    assert nom["e"] == pytest.approx(float(par.z_principal_image - par.z_principal_object))
    # The real-ray refinement moves the sensor only slightly.
    assert abs(float(rig.z0) - nom["z0"]) < 1.0
    assert abs(float(rig.theta) - nom["theta"]) < math.radians(0.2)
    assert abs(float(rig.phi) - nom["phi"]) < math.radians(0.2)


def test_sensor_in_focus_on_laser_plane(rig):
    pts = rig.laser_points(_grid(rig))
    spot = rig.spot(pts, 48)
    assert np.all(np.asarray(spot.fraction_valid) == 1.0)
    rms_um = 1e3 * np.asarray(spot.rms_mm)
    assert rms_um.max() < 3.0
    # 1 mm off the laser plane (along its normal) the spots are far larger.
    n = rig.laser_plane / jnp.linalg.norm(rig.laser_plane)
    off = 1e3 * np.asarray(rig.spot(pts + n, 48).rms_mm)
    assert off.min() > 10 * rms_um.max()
    # The spot centroids agree with the chief-ray images to a fraction of a pixel.
    uv, ok = rig.project(pts)
    assert np.all(np.asarray(ok))
    np.testing.assert_allclose(spot.centroid_uv, uv, atol=0.2)


def test_project_conventions(rig):
    par = paraxial(rig.lens)
    z_axis = 1.0 / float(rig.laser_plane[2])
    np.testing.assert_allclose(z_axis, float(par.e) + 97.0 * (1 + 1 / 1.5), rtol=1e-12)
    # Nine points (one compiled shape): on axis, +x, +y, far off the sensor, and more.
    pts = jnp.asarray(
        [[0.0, 0.0, z_axis], [0.3, 0.0, z_axis], [0.0, 0.3, z_axis], [50.0, 0.0, z_axis]]
        + [[0.1 * k, -0.1 * k, z_axis] for k in range(5)]
    )
    uv, ok = rig.project(pts)
    assert np.asarray(ok).tolist() == [True, True, True, False] + [True] * 5
    # The on-axis point of the laser plane images on the principal pixel.
    np.testing.assert_allclose(uv[0], [799.5, 599.5], atol=1e-9)
    # The image is inverted: +x, +y in the camera frame land left of / above the centre,
    # magnified about 1.5 times.
    assert float(uv[1, 0]) < 799.5 - 0.3 * 1.4 / 0.0044
    assert float(uv[2, 1]) < 599.5 - 0.3 * 1.4 / 0.0044
    # Batch shapes.
    uv3, ok3 = rig.project(pts.reshape(3, 3, 3))
    assert uv3.shape == (3, 3, 2) and ok3.shape == (3, 3)
    np.testing.assert_array_equal(uv3.reshape(9, 2), uv)
    # Paraxial back-projection and the real projection agree to a fraction of a pixel.
    g = _grid(rig)
    uv, ok = rig.project(rig.laser_points(g))
    assert np.all(np.asarray(ok))
    np.testing.assert_allclose(uv, g, atol=1.0)


def test_project_gradient_matches_central_differences(rig):
    x = rig.laser_points(jnp.asarray([300.0, 900.0]))

    def proj(x):
        return rig.project(x)[0]

    both = jax.jit(lambda x: (proj(x), jax.jacfwd(proj)(x)))
    jac = both(x)[1]
    fd = central_difference(lambda x: both(x)[0], x, step=1e-6)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6)


def test_build_rig_scheimpflug_angle():
    """Paraxial placement obeys tan θ = |β| cot α (α: laser plane vs optical axis)."""
    lens = load_lens("achromat")
    for beta, alpha in [(0.5, 45.0), (2.0, 70.0)]:
        r = build_rig(lens, beta, alpha, refine=False)
        assert float(r.theta) == pytest.approx(-math.atan(beta / math.tan(math.radians(alpha))))
        assert float(r.phi) == pytest.approx(0.0, abs=1e-15)
        z0, _, _ = paraxial_sensor_pose(paraxial(lens), r.laser_plane)
        assert float(z0) == pytest.approx(float(paraxial(lens).efl) * (1 + beta), rel=1e-12)
    r = build_rig(lens, 1.0, 60.0, 90.0, refine=False)  # normal tilted towards +y: φ only
    assert float(r.theta) == pytest.approx(0.0, abs=1e-15)
    assert float(r.phi) == pytest.approx(math.atan(1.0 / math.tan(math.radians(60.0))))


def test_focus_refinement_never_worse_than_paraxial():
    """The achromat at ×2 with a laser plane 45° to the axis, tilted towards the
    sensor's diagonal: paraxially a 63° sensor tilt, where the full-aperture spots are
    ~0.5 mm. Refining the pose by plain Gauss-Newton once ran the sensor to 85° (rays
    missing it lowered the sum; spots of 53 mm, 50 of 264 board corners imaged). The
    refinement only takes steps that improve the focus and lose no ray, so for every
    azimuth the spots are no larger than the paraxial pose's and the sensor stays a
    sensor (tilt below 80°). The CLI warns of such a rig's blur (`_focus_note`) and not
    of the paper's (0.7 µm spots)."""
    from scheimflux.cli._simulate import _focus_note

    lens = load_lens("achromat")
    for az in (0.0, 45.0):
        start = build_rig(lens, 2.0, 45.0, az, refine=False)
        refined = build_rig(lens, 2.0, 45.0, az)
        s0, s1 = start.summary(), refined.summary()
        assert s1["rms_spot_um_mean"] <= s0["rms_spot_um_mean"], (az, s0, s1)
        tilt = math.acos(math.cos(float(refined.phi)) * math.cos(float(refined.theta)))
        assert math.degrees(tilt) < 80.0, (az, s1)
    assert "warning: the lens images the laser plane with spots of" in _focus_note(refined)
    assert _focus_note(paper_rig()) == ""


def test_build_rig_errors():
    lens = load_lens("double-gauss")
    with pytest.raises(ValueError, match="magnification"):
        build_rig(lens, 3.0)
    with pytest.raises(ValueError, match="laser angle"):
        build_rig(lens, 1.0, 0.0)
