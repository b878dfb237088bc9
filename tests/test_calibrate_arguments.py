"""`calibrate`'s arguments refused in one line naming them, before any solve: the wrong
type of observations, a Huber threshold of 0, a table that does not turn, one pose
imaged over and over; and a repeated view named."""

import dataclasses
import inspect

import numpy as np
import pytest

import scheimflux as sf
from scheimflux.calibration._calibrate import _duplicate_views_note
from scheimflux.io import StageScan
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard


@pytest.fixture(scope="module")
def obs():
    o, _ = simulate_observations(
        paper_rig(refine=False), Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    return o


@pytest.mark.parametrize("bad", [None, {"views": []}, "observations.json"])
def test_observations_of_another_type_are_a_type_error_naming_obs(bad):
    # the library's own check (under pytest the jaxtyping checker, switched on for the
    # test run only, stops the call first: its wrapper is taken off here)
    calibrate = inspect.unwrap(sf.calibrate)
    with pytest.raises(TypeError, match=r"^obs must be Observations .*got (NoneType|dict|str)$"):
        calibrate(bad)


def test_a_huber_threshold_of_zero_is_refused(obs):
    with pytest.raises(ValueError, match=r"robust must be a Huber threshold > 0 .* got 0.0"):
        sf.calibrate(obs, robust=0.0)


def test_a_table_that_does_not_turn_is_refused_by_name(obs):
    frames = [np.zeros((0, 2))] * 3
    still = dataclasses.replace(obs, stage=StageScan(0.0, 17.5, frames))
    with pytest.raises(ValueError, match=r"obs.stage.delta_omega_deg is 0: the table must turn"):
        sf.calibrate(still)


def test_one_pose_imaged_over_and_over_is_refused(obs):
    same = dataclasses.replace(obs, views=[obs.views[0]] * 8)
    with pytest.raises(ValueError, match=r"the 8 views hold identical corners: one pose"):
        sf.calibrate(same)


def test_a_repeated_view_is_named(obs):
    views = [obs.views[0], obs.views[1], obs.views[0], obs.views[2], obs.views[1]]
    (note,) = _duplicate_views_note(dataclasses.replace(obs, views=views))
    assert note.startswith("view(s) 2 (= 0), 4 (= 1) repeat an earlier view's corners")
    assert _duplicate_views_note(obs) == ()


def test_the_centred_closed_form_recovers_a_pinholes_focal_lengths():
    # independent derivation: the homography of a plane z = 0 seen by K [R | t] is
    # K [r1 r2 t]; with the principal point at the centre the two focal lengths follow
    import cv2

    from scheimflux.calibration.core._zhang import centred_intrinsics

    K = np.array([[812.0, 0.0, 319.5], [0.0, 1083.0, 239.5], [0.0, 0.0, 1.0]])
    Hs = []
    for rv, t in [((0.3, 0.1, 0.0), (-50, -40, 600)), ((-0.2, 0.35, 0.1), (-30, -60, 700)),
                  ((0.1, -0.3, -0.2), (-60, -20, 650))]:  # fmt: skip
        R = cv2.Rodrigues(np.array(rv, dtype=np.float64))[0]
        H = K @ np.column_stack([R[:, 0], R[:, 1], t])
        Hs.append(H / H[2, 2])
    got = centred_intrinsics(Hs, 640, 480)
    np.testing.assert_allclose(got, K, rtol=1e-9)
