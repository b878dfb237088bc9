"""The thick lens's f when no focal length is given: held at a thin-lens estimate, said so."""

import dataclasses

import pytest

from scheimflux.calibration import calibrate_camera, with_nominal
from scheimflux.simulate import build_rig, load_lens, simulate_observations
from scheimflux.targets import Checkerboard


@pytest.fixture(scope="module")
def bare_obs():
    """A double Gauss (f ≈ 99.5 mm by paraxial ray trace) at ×2, observed as `detect`
    writes it: the pixel pitch, no lens data."""
    rig = build_rig(load_lens("double-gauss"), 2.0, refine=False)
    obs, truth = simulate_observations(
        rig, Checkerboard(11, 8, 0.2), n_views=5, stage_scan=False, seed=3
    )
    return dataclasses.replace(obs, nominal=None), truth


@pytest.mark.slow  # ~65 CPU-s: a ray-traced rig and two camera solves
def test_held_f_estimate_is_said(bare_obs):
    obs, truth = bare_obs
    f_lens = truth.nominal_params["f"]  # the ray tracer's paraxial focal length
    est = calibrate_camera(obs, distortion="none")
    f_est = float(est.camera.f)
    assert "camera.f" in est.freeze
    # the thin-lens estimate from the boards' distance is far from the lens's f here
    # (the main planes of a thick lens are not where a thin lens puts them)
    assert abs(f_est - f_lens) > 0.1 * f_lens
    notes = [n for n in est.notes if n.startswith("f was not given")]
    assert len(notes) == 1 and f"{f_est:.4g} mm" in notes[0], est.notes
    # what the note claims: f is a gauge, the same corners fit as well with the lens's f
    given = calibrate_camera(with_nominal(obs, focal_length_mm=round(f_lens)), distortion="none")
    assert float(given.camera.f) == round(f_lens)
    assert not [n for n in given.notes if n.startswith("f was not given")]
    # 0.03 px corner noise: both at the noise floor, within 1 % of each other
    assert given.reprojection_rms_px == pytest.approx(est.reprojection_rms_px, rel=0.01)
