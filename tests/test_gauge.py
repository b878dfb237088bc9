"""The thick lens's gauge (issue 16 part 1): what the frozen nominal values may not change.

Data are ray traced through a real double Gauss (never made by the model under test),
noise-free, so every difference between two calibrations is the gauge's doing (or the
solver's tolerance), not noise.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.calibrate import DEFAULT_FREEZE, calibrate_camera, fit_laser_plane, with_nominal
from scheimflux.calibrate._gauge import (
    GAUGE_HELD,
    PIXEL_PITCH,
    PROFILED,
    gauge_spectrum,
    profile_solve,
)
from scheimflux.calibrate._model import camera_residuals, make_data
from scheimflux.simulate import build_rig, load_lens, paraxial, simulate_observations
from scheimflux.targets import Checkerboard


def test_default_freeze_keeps_the_ideal_gauge_for_the_ideal_camera():
    # the distortion-free camera has an exact null direction (tilt against axis point):
    # its default still holds one of them; with distortion only pitch and f are held
    for how, held in (("nominal", "camera.phi"), ("closed-form", "camera.x0")):
        assert held in DEFAULT_FREEZE[("thick-lens", how)]
    assert set(GAUGE_HELD) == set(PIXEL_PITCH) | {"camera.f"}


@dataclasses.dataclass
class _FakeFit:
    """What `profile_solve` reads of a `Fit`: the held value's cost and the params."""

    params: object
    cost: float
    converged: bool = True
    steps: int = 1


class _Holder(eqx.Module):
    camera: object


class _X(eqx.Module):
    x0: jax.Array


def _two_minima(x):
    # a local minimum at 500 (cost 0.19) and the global one at 1061.5 (cost 0.0626):
    # the shape of the 50 mm scene's profile below (two parabolas, the lower one wins)
    return min(0.19 + 2e-6 * (x - 500.0) ** 2, 0.0626 + 4.4e-6 * (x - 1061.5) ** 2)


def test_profile_finds_the_global_minimum_from_either_side():
    # started at either minimum, the scan over the grid finds the lower one, and the
    # parabolic refinement places it to 1e-3 of its σ: a parabola's vertex exactly
    # (the profile is one near the minimum), here within 0.1 px
    for start in (500.0, 1061.5, 20.0):
        calls = []

        def solve(p):
            x = float(p.camera.x0)
            calls.append(x)
            return _FakeFit(p, _two_minima(x))

        p0 = _Holder(_X(jnp.asarray(start)))
        fit, prof = profile_solve(solve, p0, grid=np.linspace(0.0, 1599.0, 9))
        assert prof.converged, prof
        assert abs(prof.value - 1061.5) < 0.1, prof
        assert abs(float(fit.params.camera.x0) - prof.value) < 1e-9
        assert prof.sigma == pytest.approx(1 / np.sqrt(2 * 4.4e-6), rel=1e-6)
        assert len(calls) == len(prof.values) <= 9 + 12


def test_profile_extends_past_the_grid():
    # the minimum outside the scanned range: the scan steps outward until it brackets it
    def solve(p):
        x = float(p.camera.x0)
        return _FakeFit(p, 1.0 + 1e-5 * (x - 2100.0) ** 2)

    start = _Holder(_X(jnp.asarray(800.0)))
    _, prof = profile_solve(solve, start, grid=[0.0, 800.0, 1600.0])
    assert prof.converged and abs(prof.value - 2100.0) < 1e-3 and not prof.at_bound, prof
    # within bounds that exclude it, it stays at the bound and says so
    fit, prof = profile_solve(solve, start, grid=[0.0, 800.0, 1600.0], bounds=(0.0, 1800.0))
    assert prof.at_bound and prof.value == 1800.0 and float(fit.params.camera.x0) == 1800.0


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
def test_rounded_nominal_tilt_does_not_change_distances(scene):
    # Target (issue 16): a nominal tilt off by ±1° changes noise-free distances by
    # ≤ 0.005 µm. Holding the nominal tilt (the former default) this scene gave 0.054 µm
    # for 1°. Now the tilt is free and the axis point's x is profiled: every start
    # reaches the same optimum (measured: changes of 1e-11 µm for ±1° and ±3°), so what
    # is left is the solver's tolerance (1e-5 σ of the unit-scaled state, and 1e-3 σ of
    # the profiled x0: 0.4 px at 4e-4 µm per px along the profile).
    rig, obs, truth = scene
    phi, theta = obs.nominal.tilt_deg
    cc0, X0, truth_points = _points(obs, truth)
    assert cc0.fit.converged and cc0.gauge_profile.converged
    assert "camera.phi" not in cc0.freeze and "camera.theta" not in cc0.freeze
    assert set(cc0.freeze) == set(GAUGE_HELD) | {PROFILED}
    d0 = _distances(X0)
    err_um = float(np.sqrt(np.mean((d0 - _distances(truth_points)) ** 2))) * 1e3
    print(f"distance error vs the ray tracer: {err_um:.4f} um")
    # measured 0.0066 µm (tilt held at the nominal value: 0.05 µm; the axis point held at
    # the sensor centre: 0.28 µm; either other local minimum of the profile: 0.14 µm)
    assert err_um < 0.02
    for dphi, dtheta in ((1.0, -1.0), (-1.0, 1.0), (1.0, 1.0), (-1.0, -1.0)):
        cc, X, _ = _points(with_nominal(obs, tilt_deg=(phi + dphi, theta + dtheta)), truth)
        assert cc.fit.converged and cc.gauge_profile.converged
        change_um = float(np.sqrt(np.mean((_distances(X) - d0) ** 2))) * 1e3
        print(f"nominal tilt {dphi:+}, {dtheta:+} deg: distances change {change_um:.2e} um")
        assert change_um <= 0.005, (dphi, dtheta, change_um)


@pytest.mark.slow
def test_gauge_singular_values(scene):
    # At the default solution (relative singular values of the column-scaled Jacobian):
    # - pixel pitch only: the weakest, along (f, z0, e), at the ~1e-7 level of rounding
    #   (measured 1.0e-7); the axis point's x against the boards' x translations next
    #   (3.6e-7), y0 against their y translations (1.3e-6).
    # - pitch and f held (what the default holds): x0's direction is the weakest, and no
    #   direction of the tilt is weak (the tilt is free and determined).
    # - x0 held too (the default's frozen set, x0 at its profile's optimum): the weakest
    #   is y0's (1.4e-6), above the rank threshold (1e-13 in JᵀJ, i.e. ~3e-7 here).
    # - the former default (tilt held, 1.7e-5) looked better conditioned only because it
    #   held a parameter the data determine: it biased distances (0.054 µm for 1°).
    _, obs, truth = scene
    cc, _, _ = _points(obs, truth)
    data = make_data(obs)

    def spec(freeze):
        s = gauge_spectrum(camera_residuals, cc.fit.params, data, freeze)
        print(s.format())
        return s

    free = spec(PIXEL_PITCH)
    held = spec(GAUGE_HELD)
    default = spec(GAUGE_HELD + (PROFILED,))
    tilt = spec(GAUGE_HELD + ("camera.phi", "camera.theta"))
    s_null, comps = free.directions[0]
    assert s_null < 3e-7 and "camera.f" in {lab for lab, _ in comps}
    s_x, weak = held.directions[0]
    assert "camera.x0" in {lab for lab, _ in weak}
    assert default.singular_values[-1] > 3 * s_x
    assert tilt.singular_values[-1] > default.singular_values[-1]
    for _, cs in (free.directions[0], held.directions[0], default.directions[0]):
        assert all(abs(c) < 0.3 for lab, c in cs if lab in ("camera.phi", "camera.theta"))
