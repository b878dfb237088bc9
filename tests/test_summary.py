"""The calibration summary as a library function: the text reads back the numbers of the
model it describes, and `scheimflux calibrate` prints exactly that text."""

import dataclasses
import importlib
import json
import math
import re

import numpy as np
from test_calibration_file import _thick_lens, make_calibration
from test_cli_calibrate import _observations

from scheimflux.calibration import (
    SystemParams,
    calibration_summary,
    calibration_to_dict,
    format_summary,
)
from scheimflux.camera import RadialTangential
from scheimflux.cli import main
from scheimflux.io import write_observations

LINE = re.compile(r"^  (\w+)\s+=\s+(\S+) (\S*)\s*(\(fixed\))?$")


def _camera_lines(text):
    block = text.split("camera:\n", 1)[1].split("\nlaser plane", 1)[0]
    out = {}
    for line in block.splitlines():
        m = LINE.match(line)
        assert m, line
        out[m.group(1)] = (float(m.group(2)), m.group(3), m.group(4) is not None)
    return out


def _cal():
    cam = _thick_lens(RadialTangential(0.8, -30.0, 200.0, 1e-3, -2e-3))
    return make_calibration(cam, distortion="radial-tangential")


def test_summary_reads_back_the_model():
    cal = _cal()
    cam, plane, stage = cal.params.camera, cal.params.plane, cal.params.stage
    text = format_summary(calibration_to_dict(cal))
    lines = _camera_lines(text)
    # the camera's own attributes, in the file's units (angles in degrees), to the 8
    # significant digits printed
    expected = {
        "f": float(cam.f), "e": float(cam.e), "z0": float(cam.z0),
        "phi": math.degrees(float(cam.phi)), "theta": math.degrees(float(cam.theta)),
        "x0": float(cam.x0), "y0": float(cam.y0), "dx": float(cam.dx), "dy": float(cam.dy),
        "k1": 0.8, "k2": -30.0, "k3": 200.0, "p1": 1e-3, "p2": -2e-3,
    }  # fmt: skip
    assert set(expected) <= set(lines)
    for name, value in expected.items():
        assert math.isclose(lines[name][0], value, rel_tol=1e-7, abs_tol=1e-300), name
    assert lines["phi"][1] == "deg" and lines["f"][1] == "mm" and lines["x0"][1] == "px"
    assert {n for n, (_, _, fixed) in lines.items() if fixed} == {"dx", "dy", "f"}
    m = re.search(r"distance ([\d.]+) mm", text)
    assert abs(float(m.group(1)) - float(plane.distance)) < 5e-5  # printed to 4 decimals
    m = re.search(r"t_m_c = \[([^\]]+)\] mm, delta omega = (\S+) deg", text)
    t = np.array([float(x) for x in m.group(1).split(",")])
    np.testing.assert_allclose(t, np.asarray(stage.t_m_c), atol=5e-6)
    assert math.isclose(float(m.group(2)), math.degrees(float(stage.delta_omega)), rel_tol=1e-5)
    assert "reprojection RMS: 0.0310 px" in text
    assert "laser-plane fit RMS: 1.200 um" in text and "gauge RMS: 0.900 um" in text
    assert "solve joint  :    5 steps" in text
    assert text.splitlines()[-1] == "frozen: camera.dx, camera.dy, camera.f"


def test_summary_frozen_override_missing_numbers_and_camera_only():
    cal = _cal()
    doc = calibration_to_dict(cal)
    lines = _camera_lines(format_summary(doc, frozen=("camera.e", "camera.distortion")))
    fixed = {n for n, (_, _, f) in lines.items() if f}
    assert fixed == {"e", "k1", "k2", "k3", "p1", "p2"}  # a block path marks its members
    doc["diagnostics"]["reprojection_rms_px"] = None
    assert "reprojection RMS: n/a px" in format_summary(doc)
    cal = dataclasses.replace(
        cal, params=SystemParams(cal.params.camera, cal.params.board_poses), gauge_rms_mm=None
    )
    text = calibration_summary(cal)
    assert "laser plane: none (camera-only calibration)" in text
    assert "stage: not calibrated" in text
    assert text.splitlines()[-1].startswith("note: no stripe pixels on the board views")


def test_summary_states_the_stripe_gates_sigma():
    # each view's σ off its board = the stated σ at the footprint × its own-noise factor
    # × its gain: views (1, 1.0, 0.2), (1, 8.0, 0.4) -> 0.2 and 3.2 µm of 1 µm stated
    doc = calibration_to_dict(_cal())
    d = doc["diagnostics"]
    assert "stripe σ off the boards" not in format_summary(doc)  # no gains: not stated
    d.update(sigma_stripe_mm=1e-3, stripe_gain=[0.2, 0.4], stripe_sigma_scale=[1.0, 8.0])
    line = [ln for ln in format_summary(doc).splitlines() if "stripe σ off" in ln]
    assert line == [
        "stripe σ off the boards (the stripe gate's): 0.2-3.2 um per view = 1 um (the stated "
        "pixel σ at a pixel's footprint) × 1-8 (views' own noise, stripe_sigma_px) × 0.2-0.4 "
        "(a pixel's error moved off its board)"
    ]


def test_the_cli_prints_the_library_summary(tmp_path, monkeypatch, capsys):
    cal = _cal()
    calibrate_module = importlib.import_module("scheimflux.calibration")  # where the CLI looks
    monkeypatch.setattr(calibrate_module, "calibrate", lambda obs, **kw: cal)
    src, out = tmp_path / "obs.json", tmp_path / "cal.json"
    write_observations(src, _observations())
    assert main(["calibrate", str(src), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    doc = json.loads(out.read_text())
    summary = calibration_summary(cal, doc)
    assert summary.startswith(format_summary(doc))
    assert summary in printed
