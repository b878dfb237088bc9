"""`scheimflux measure` from points files: values, JSON, and one-line refusals."""

import json
import math
import re

import numpy as np
import pytest
from test_metrology_fits import cylinder_points, step_profile

from scheimflux.cli._main import main
from scheimflux.io import write_points


def _run(argv, capsys):
    rc = main(argv)
    out, err = capsys.readouterr()
    # no NaN ever printed as a number
    assert "nan" not in out.lower() and "nan" not in err.lower()
    return rc, out, err


def test_cylinder_from_a_measurement_frame_points_file(tmp_path, capsys):
    rng = np.random.default_rng(0)
    pts = str(tmp_path / "points.json")
    write_points(pts, [cylinder_points(rng, noise=1e-3)], "measurement")
    res = str(tmp_path / "result.json")
    rc, out, _ = _run(["measure", pts, "--cylinder", "--out", res], capsys)
    assert rc == 0 and "radius" in out and re.search(r"calibration +not included", out)
    assert re.search(r"frozen parameters +not included", out)
    # the headline's U says what it leaves out
    assert "(U, k = 2, without calibration, frozen parameters, stripe noise)" in out
    with open(res) as fh:
        doc = json.load(fh)
    assert doc["format"] == "scheimflux.measurement/1" and doc["kind"] == "cylinder"
    v = doc["values"]["radius"]
    # 120 points with 1 µm radial noise: the radius is good to ~1e-4 mm; U ≈ 2e-4 mm
    assert abs(v["value"] - 17.5) < 5 * v["standard_uncertainty"]
    assert v["budget"]["calibration"] is None and v["budget"]["fit_residual"] > 0
    assert math.isclose(v["U"], 2 * v["standard_uncertainty"])
    assert 0.5e-3 < doc["residuals"]["rms"] < 2e-3
    # the result is not overwritten without --overwrite
    rc, _, err = _run(["measure", pts, "--cylinder", "--out", res], capsys)
    assert rc == 1 and "--overwrite" in err and len(err.strip().splitlines()) == 1


def test_steps_with_automatic_faces(tmp_path, capsys):
    X, _ = step_profile(np.random.default_rng(1), gap=1.3)
    pts = str(tmp_path / "profile.npy")
    np.save(pts, X)
    rc, out, _ = _run(["measure", pts, "--steps"], capsys)
    assert rc == 0 and "step_1       1.300000 mm" in out


@pytest.mark.parametrize(
    "make, argv, message",
    [
        (lambda r: ([cylinder_points(r)], "camera"), ["--cylinder"], "camera-frame points"),
        (lambda r: ([cylinder_points(r)], "camera"), ["--plane", "--frame", "measurement"],
         "wrong frame"),
        (lambda r: ([cylinder_points(r)[:4]], "measurement"), ["--cylinder"],
         "need at least 6 points"),
        (lambda r: ([np.outer(np.linspace(0, 1, 30), [1.0, 2.0, 3.0])], "measurement"),
         ["--cylinder"], "collinear"),
        (lambda r: ([cylinder_points(r)], "measurement"), ["--distance", "0", "999"],
         "out of range"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, make, argv, message):
    frames, frame = make(np.random.default_rng(2))
    pts = str(tmp_path / "points.json")
    write_points(pts, frames, frame)
    rc, out, err = _run(["measure", pts, *argv], capsys)
    assert rc == 1 and out == ""
    assert message in err and len(err.strip().splitlines()) == 1


def test_calibration_without_covariance_is_refused(tmp_path, capsys):
    cal, stripes = tmp_path / "cal.json", tmp_path / "stripes.json"
    cal.write_text("{}")
    stripes.write_text("{}")
    rc, _, err = _run(
        ["measure", "--cylinder", "--calibration", str(cal), "--stripes", str(stripes)], capsys
    )
    assert rc == 1 and "no parameter covariance" in err and "--observations" in err
    rc, _, err = _run(["measure", "--cylinder", "--calibration", str(tmp_path / "x.json"),
                       "--stripes", str(stripes)], capsys)
    assert rc == 1 and "no such file" in err


def test_small_uncertainties_keep_their_digits():
    # a U of the fit residual alone over ~40000 points is ~1e-4 µm: printed as 0.000 it
    # read as an exact value
    from scheimflux.metrology._gum import _um

    assert _um(2.4e-7) == "0.00024" and _um(-3.1e-8) == "-3.1e-05"
    assert _um(1.2345e-3) == "1.234" and _um(1e-6) == "0.001" and _um(0.0) == "0.000"
