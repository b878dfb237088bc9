"""The observations file: round trip, validation messages, no clobbering."""

import json

import numpy as np
import pytest

from scheimflux.io import (
    Nominal,
    Observations,
    StageScan,
    View,
    read_observations,
    write_observations,
)


def _obs():
    board = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    corners = np.array([[10.0, 20.0], [np.nan, np.nan], [12.5, 30.25], [40.0, 41.0]])
    return Observations(
        1600,
        1200,
        (0.0044, 0.0044),
        board,
        [View(corners, np.array([[1.0, 2.0], [3.0, 4.0]]))],
        Nominal(97.0, 1.5, (0.0, 13.0)),
        StageScan(10.0, 17.5, [np.array([[5.0, 6.0]]), np.zeros((0, 2))]),
    )


def test_round_trip(tmp_path):
    path = tmp_path / "obs.json"
    write_observations(path, _obs())
    back = read_observations(path)
    np.testing.assert_array_equal(back.views[0].corners_px, _obs().views[0].corners_px)
    assert back.views[0].corner_mask.tolist() == [True, False, True, True]
    assert back.nominal == _obs().nominal and back.stage.frames[1].shape == (0, 2)
    assert json.loads(path.read_text())["views"][0]["corners_px"][1] is None


def test_no_clobber(tmp_path):
    path = tmp_path / "obs.json"
    path.write_text("precious")
    with pytest.raises(FileExistsError):
        write_observations(path, _obs())
    assert path.read_text() == "precious"
    write_observations(path, _obs(), overwrite=True)
    assert read_observations(path).width == 1600


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.pop("format"), "format must be"),
        (lambda d: d.pop("sensor"), "missing key 'sensor'"),
        (lambda d: d["sensor"].__setitem__("pixel_pitch_mm", [1]), "sensor.pixel_pitch_mm"),
        (lambda d: d["views"][0]["corners_px"].pop(), "has 3 entries but board_points_mm has 4"),
        (lambda d: d["views"][0]["corners_px"].__setitem__(0, [1, "a"]), r"corners_px\[0\]"),
        (lambda d: d["board_points_mm"].__setitem__(0, [1, 2]), r"board_points_mm\[0\]"),
        (lambda d: d["stage"].pop("gauge_radius_mm"), "stage.gauge_radius_mm"),
        (lambda d: d["sensor"].__setitem__("width", -3), "sensor.width must be positive"),
    ],
)
def test_validation_messages(tmp_path, mutate, message):
    path = tmp_path / "obs.json"
    write_observations(path, _obs())
    doc = json.loads(path.read_text())
    mutate(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=message):
        read_observations(path)


def test_not_json(tmp_path):
    path = tmp_path / "obs.json"
    path.write_text("{oops")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_observations(path)
    with pytest.raises(FileNotFoundError, match="observations file not found"):
        read_observations(tmp_path / "missing.json")


def test_within_radius_drops_what_lies_beyond_it():
    # the sensor's centre is (799.5, 599.5); distances worked out by hand: corners
    # (10, 20) 979.3 px, (12.5, 30.25) 971.3 px (the second corner is undetected), stripe
    # (1, 2) 997.3 px, (800, 600) 0.7 px: at 975 px the first corner and stripe pixel go
    from scheimflux.io._observations import within_radius

    obs = _obs()
    v = obs.views[0]
    obs.views[0] = View(np.vstack([v.corners_px[:3], [[800.0, 600.0]]]),
                        np.array([[1.0, 2.0], [800.0, 600.0]]))  # fmt: skip
    cut = within_radius(obs, 975.0)
    np.testing.assert_array_equal(cut.views[0].corner_mask, [False, False, True, True])
    np.testing.assert_array_equal(cut.views[0].corners_px[2:], obs.views[0].corners_px[2:])
    np.testing.assert_array_equal(cut.views[0].stripe_px, [[800.0, 600.0]])
    assert cut.width == obs.width and cut.board_points_mm is obs.board_points_mm


def test_board_motion_round_trip_and_validation(tmp_path):
    # measured (px), not measurable (NaN <-> null) and not applicable (None <-> absent)
    obs = _obs()
    v = obs.views[0]
    obs.views[:] = [View(v.corners_px, v.stripe_px, ("a.png",), m)
                    for m in (0.012, float("nan"), None)]  # fmt: skip
    path = tmp_path / "obs.json"
    write_observations(path, obs)
    doc = json.loads(path.read_text())
    assert doc["views"][0]["board_motion_px"] == 0.012
    assert doc["views"][1]["board_motion_px"] is None
    assert "board_motion_px" not in doc["views"][2]
    back = read_observations(path)
    assert back.views[0].board_motion_px == 0.012
    assert np.isnan(back.views[1].board_motion_px) and back.views[2].board_motion_px is None
    for bad in (-0.1, "0.1", True):
        doc["views"][0]["board_motion_px"] = bad
        path.write_text(json.dumps(doc))
        with pytest.raises(ValueError, match=r"views\[0\].board_motion_px must be a number"):
            read_observations(path)


def test_stripe_sigma_round_trip_and_validation(tmp_path):
    # a view's own stripe noise (detect writes a speckled line's scatter) or absent
    obs = _obs()
    v = obs.views[0]
    obs.views[:] = [View(v.corners_px, v.stripe_px, stripe_sigma_px=s) for s in (0.31, None)]
    path = tmp_path / "obs.json"
    write_observations(path, obs)
    doc = json.loads(path.read_text())
    assert doc["views"][0]["stripe_sigma_px"] == 0.31 and "stripe_sigma_px" not in doc["views"][1]
    back = read_observations(path)
    assert [w.stripe_sigma_px for w in back.views] == [0.31, None]
    for bad in (0, -0.2, "0.3", True, None, float("inf")):
        doc["views"][0]["stripe_sigma_px"] = bad
        path.write_text(json.dumps(doc).replace("Infinity", "1e999"))
        with pytest.raises(ValueError, match=r"views\[0\].stripe_sigma_px must be a number"):
            read_observations(path)
