"""`scheimflux calibrate` and `scheimflux reconstruct`.

The fast tests replace the (slow) solver by a prepared calibration, so that they check the
command's plumbing: arguments, summary, files, errors. The `slow` tests run the real
calibration on a small ray-traced data set.
"""

import dataclasses
import importlib
import json
import math
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest
from test_calibration_file import _fit, _thick_lens, make_calibration

from scheimflux.calibration import read_calibration, write_calibration
from scheimflux.cli import main
from scheimflux.io import (
    Observations,
    View,
    read_ply,
    write_observations,
    write_stripes,
)
from scheimflux.reconstruct import Status, stripe_to_camera, stripe_to_measurement

# the subpackage (`sf.calibrate` is the function): the CLI looks `calibrate` up there
calibrate_module = importlib.import_module("scheimflux.calibration")


def _observations(stage=True) -> Observations:
    board = np.array([[x, y, 0.0] for y in range(3) for x in range(4)], dtype=float) * 0.3
    rng = np.random.default_rng(1)
    views = [
        View(rng.uniform(100, 1500, (12, 2)), rng.uniform(100, 1500, (5, 2))) for _ in range(3)
    ]
    from scheimflux.io import StageScan

    scan = StageScan(10.0, 17.5, [rng.uniform(100, 1500, (4, 2))]) if stage else None
    return Observations(1600, 1200, (0.0044, 0.0044), board, views, stage=scan)


@pytest.fixture
def obs_file(tmp_path):
    path = tmp_path / "obs.json"
    write_observations(path, _observations())
    return path


@pytest.fixture
def fake_calibrate(monkeypatch):
    """Replace the solver by a prepared calibration; records the arguments it got."""
    calls = []
    state = SimpleNamespace(converged=True)

    def fake(obs, **kwargs):
        calls.append((obs, kwargs))
        cal = make_calibration(_thick_lens(), distortion="none")
        if not state.converged:
            cal.fits["joint"] = _fit(300, converged=False)
        return cal

    monkeypatch.setattr(calibrate_module, "calibrate", fake)
    state.calls = calls
    return state


def _one_line_error(capsys, command):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"scheimflux {command}: error: ")
    assert "Traceback" not in err
    return lines[0]


def test_calibrate_writes_file_and_summary(tmp_path, obs_file, fake_calibrate, capsys):
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(obs_file), "--out", str(out)]) == 0
    ((obs, kwargs),) = fake_calibrate.calls
    assert len(obs.views) == 3
    # defaults: the most accurate choice
    assert kwargs["model"] == "thick-lens" and kwargs["distortion"] == "radial-tangential"
    assert kwargs["joint"] is True and kwargs["init"] == "auto" and kwargs["freeze"] is None
    assert kwargs["sigma_corner_px"] == 0.03 and kwargs["sigma_stripe_px"] == 0.05
    assert kwargs["robust"] is None and kwargs["reject"] == 5.0
    text = capsys.readouterr().out
    for expected in (
        "model: thick-lens",
        "init: nominal",
        "phi",
        "deg",
        "(fixed)",
        "laser plane: unit normal",
        "R_m_c",
        "reprojection RMS: 0.0310 px",
        "laser-plane fit RMS: 1.200 um",
        "gauge RMS: 0.900 um",
        "solve camera :   12 steps",
        "converged",
        "frozen: camera.dx, camera.dy, camera.f",
        f"wrote {out}",
    ):
        assert expected in text, expected
    loaded = read_calibration(out)
    assert loaded.diagnostics["converged"] is True
    assert loaded.diagnostics["observations"] == str(obs_file)
    assert loaded.stage is not None


def test_calibrate_passes_options(tmp_path, obs_file, fake_calibrate):
    argv = ["calibrate", str(obs_file), "--out", str(tmp_path / "c.json"), "--model", "pinhole"]
    argv += ["--init", "closed-form", "--no-joint", "--freeze", "camera.x0", "camera.y0"]
    argv += ["--freeze", "camera.gamma", "--sigma-corner-px", "0.1", "--robust", "3"]
    assert main(argv) == 0
    ((_, kw),) = fake_calibrate.calls
    assert kw["model"] == "pinhole" and kw["distortion"] == "none"
    assert kw["init"] == "closed-form" and kw["joint"] is False
    assert kw["freeze"] == ["camera.x0", "camera.y0", "camera.gamma"]
    assert kw["sigma_corner_px"] == 0.1 and kw["robust"] == 3.0


def test_unconverged_writes_nothing(tmp_path, obs_file, fake_calibrate, capsys):
    fake_calibrate.converged = False
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(obs_file), "--out", str(out)]) == 1
    line = _one_line_error(capsys, "calibrate")
    assert "did not converge: joint" in line and "no file written" in line
    assert not out.exists()
    assert main(["calibrate", str(obs_file), "--out", str(out), "--allow-unconverged"]) == 0
    with pytest.warns(UserWarning, match="did NOT converge"):  # loud when used
        d = read_calibration(out).diagnostics
    assert d["converged"] is False and d["solves"]["joint"]["converged"] is False
    assert "UNCONVERGED" in capsys.readouterr().out


@pytest.mark.parametrize(
    "setup,message",
    [
        ("missing", "observations file not found"),
        ("malformed", "not valid JSON"),
        ("missing-key", "missing key 'board_points_mm'"),
        ("pinhole-distortion", "the pinhole model (paper eq. 14) has no distortion"),
        ("bad-sigma", "--sigma-corner-px must be positive"),
    ],
)
def test_calibrate_errors(tmp_path, obs_file, fake_calibrate, capsys, setup, message):
    obs = obs_file
    extra = []
    if setup == "missing":
        obs = tmp_path / "nope.json"
    elif setup == "malformed":
        obs.write_text('{"format": ')
    elif setup == "missing-key":
        doc = json.loads(obs.read_text())
        del doc["board_points_mm"]
        obs.write_text(json.dumps(doc))
    elif setup == "pinhole-distortion":
        extra = ["--model", "pinhole", "--distortion", "division"]
    elif setup == "bad-sigma":
        extra = ["--sigma-corner-px", "0"]
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(obs), "--out", str(out), *extra]) == 1
    assert message in _one_line_error(capsys, "calibrate")
    assert not out.exists()
    assert not fake_calibrate.calls


def test_calibrate_refuses_to_clobber_before_solving(tmp_path, obs_file, fake_calibrate, capsys):
    out = tmp_path / "cal.json"
    out.write_text("old")
    assert main(["calibrate", str(obs_file), "--out", str(out)]) == 1
    assert "exists" in _one_line_error(capsys, "calibrate")
    assert out.read_text() == "old"
    assert not fake_calibrate.calls  # checked before the long computation
    assert main(["calibrate", str(obs_file), "--out", str(out), "--overwrite"]) == 0
    assert read_calibration(out).model == "thick-lens"


# ----------------------------------------------------------------------------- reconstruct


@pytest.fixture
def cal_files(tmp_path):
    with_stage = tmp_path / "cal.json"
    no_stage = tmp_path / "cal_nostage.json"
    write_calibration(with_stage, make_calibration(_thick_lens()))
    write_calibration(no_stage, make_calibration(_thick_lens(), stage=False))
    return with_stage, no_stage


@pytest.fixture
def stripes_file(tmp_path):
    u = np.linspace(300.0, 1300.0, 9)
    frames = [np.stack([u, np.full_like(u, 400.0 + 50 * i)], axis=1) for i in range(3)]
    frames[1] = frames[1][:5]
    frames.append(np.zeros((0, 2)))  # a frame without a stripe
    path = tmp_path / "stripes.json"
    write_stripes(path, frames)
    return path, frames


@pytest.mark.parametrize("frame", ["camera", "measurement"])
def test_reconstruct_json(tmp_path, cal_files, stripes_file, capsys, frame):
    path, frames = stripes_file
    out = tmp_path / "points.json"
    assert (
        main(["reconstruct", str(cal_files[0]), str(path), "--out", str(out), "--frame", frame])
        == 0
    )
    doc = json.loads(out.read_text())
    assert doc["frame"] == frame
    assert [len(f) for f in doc["frames"]] == [9, 5, 9, 0]
    cal = read_calibration(cal_files[0])
    for i, f in enumerate(frames[:3]):
        if frame == "camera":
            expect = stripe_to_camera(cal.camera, cal.plane, jnp.asarray(f)).points
        else:  # frame i is turned by i x delta omega
            expect = stripe_to_measurement(
                cal.camera, cal.plane, cal.stage, jnp.asarray(f), i
            ).points
        np.testing.assert_allclose(doc["frames"][i], np.asarray(expect), rtol=0, atol=1e-9)
    text = capsys.readouterr().out
    assert "reconstructed 4 frames, 23 stripe pixels" in text
    assert "valid points  : 23" in text and "invalid points: 0" in text


def test_reconstruct_ply_and_npy(tmp_path, cal_files, stripes_file):
    path, frames = stripes_file
    ply, npy, js = tmp_path / "p.ply", tmp_path / "p.npy", tmp_path / "p.json"
    for out in (ply, npy, js):
        assert main(["reconstruct", str(cal_files[1]), str(path), "--out", str(out)]) == 0
    a = np.load(npy)
    assert a.shape == (4, 9, 3) and np.isnan(a[1, 5:]).all() and np.isnan(a[3]).all()
    pts = np.concatenate(json.loads(js.read_text())["frames"][:3])
    np.testing.assert_array_equal(read_ply(ply), pts)
    np.testing.assert_array_equal(a[~np.isnan(a[..., 0])], pts)


def test_reconstruct_reports_invalid_points(tmp_path, capsys):
    from scheimflux.geometry import LaserPlane

    # The plane x = 5 mm: the pixel of the optical axis sees it edge-on (parallel), pixels
    # on one side meet it in front of the camera, on the other side behind it.
    cal = make_calibration(_thick_lens(), stage=False)
    cam = cal.params.camera
    cal = dataclasses.replace(
        cal,
        params=type(cal.params)(
            cam, cal.params.board_poses, LaserPlane(jnp.array([0.2, 0.0, 0.0])), None, None
        ),
    )
    write_calibration(tmp_path / "c.json", cal)
    c = np.asarray(cam.project(jnp.array([[0.0, 0.0, 150.0]])))[0]
    uv = np.array([c, c + [200.0, 0.0], c - [200.0, 0.0]])
    write_stripes(tmp_path / "s.json", [uv])
    status = np.asarray(stripe_to_camera(cam, cal.params.plane, jnp.asarray(uv)).status)
    assert sorted(status) == [Status.OK, Status.PARALLEL, Status.BEHIND_CAMERA]
    argv = ["reconstruct", str(tmp_path / "c.json"), str(tmp_path / "s.json")]
    assert main([*argv, "--out", str(tmp_path / "p.npy")]) == 0
    text = capsys.readouterr().out
    assert "valid points  : 1" in text and "invalid points: 2" in text
    assert "1  ray parallel to the laser plane" in text
    assert "1  intersection behind the camera" in text
    a = np.load(tmp_path / "p.npy")
    assert a.shape == (1, 3, 3) and np.isnan(a[0][status != 0]).all()


@pytest.mark.parametrize(
    "setup,message",
    [
        ("no-stage", "--frame measurement needs a calibrated rotary stage"),
        ("missing-cal", "calibration file not found"),
        ("missing-stripes", "stripes file not found"),
        ("malformed-cal", "not valid JSON"),
        ("missing-key", "missing key laser_plane"),
        ("bad-stripes", "frame 0 must be a list of [u, v] number pairs"),
        ("bad-extension", "unknown point-cloud format '.txt'"),
        ("exists", "exists; pass overwrite=True (--overwrite)"),
    ],
)
def test_reconstruct_errors(tmp_path, cal_files, stripes_file, capsys, setup, message):
    cal, stripes, out = cal_files[0], stripes_file[0], tmp_path / "points.json"
    extra = []
    if setup == "no-stage":
        cal, extra = cal_files[1], ["--frame", "measurement"]
    elif setup == "missing-cal":
        cal = tmp_path / "none.json"
    elif setup == "missing-stripes":
        stripes = tmp_path / "none.json"
    elif setup == "malformed-cal":
        cal.write_text("{")
    elif setup == "missing-key":
        doc = json.loads(cal.read_text())
        del doc["laser_plane"]
        cal.write_text(json.dumps(doc))
    elif setup == "bad-stripes":
        stripes.write_text(json.dumps({"format": "scheimflux.stripes/1", "frames": [[[1, 2, 3]]]}))
    elif setup == "bad-extension":
        out = tmp_path / "points.txt"
    elif setup == "exists":
        out.write_text("old")
    assert main(["reconstruct", str(cal), str(stripes), "--out", str(out), *extra]) == 1
    assert message in _one_line_error(capsys, "reconstruct")
    if setup == "exists":
        assert out.read_text() == "old"
    else:
        assert not out.exists()


# ----------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    from scheimflux.io import write_stripes as ws
    from scheimflux.simulate import paper_rig, simulate_observations
    from scheimflux.targets import Checkerboard

    folder = tmp_path_factory.mktemp("sim")
    obs, truth = simulate_observations(
        paper_rig(refine=False),
        Checkerboard.parse("11x8", 0.3),
        n_views=6,
        n_frames=12,
        delta_omega_deg=30.0,
        seed=3,
    )
    write_observations(folder / "obs.json", obs)
    ws(folder / "scan.json", obs.stage.frames)
    return folder, obs, truth


@pytest.mark.slow
def test_calibrate_then_reconstruct_end_to_end(simulated, capsys):
    folder, obs, truth = simulated
    cal, pts = folder / "cal.json", folder / "points.json"
    argv = ["calibrate", str(folder / "obs.json"), "--out", str(cal), "--distortion", "none"]
    assert main(argv) == 0, capsys.readouterr().err
    loaded = read_calibration(cal)
    assert loaded.diagnostics["converged"] is True
    assert loaded.diagnostics["reprojection_rms_px"] < 0.1
    argv = ["reconstruct", str(cal), str(folder / "scan.json"), "--out", str(pts)]
    assert main([*argv, "--frame", "camera"]) == 0
    frames = json.loads(pts.read_text())["frames"]
    d = np.concatenate([np.asarray(f) - np.asarray(t) for f, t in zip(frames, truth.scan_c)])
    # A calibrated central camera has its origin at the projection centre (the real
    # lens's entrance pupil); the simulator's camera frame starts at the paraxial front
    # principal point. The two differ by a shift along the optical axis (z_c) only.
    offset = d.mean(axis=0)
    assert np.hypot(offset[0], offset[1]) < 0.05 * abs(offset[2]) + 0.02
    err = np.linalg.norm(d - offset, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.02  # mm: tens of um with 6 views, no distortion
    assert main([*argv, "--out", str(folder / "m.ply"), "--frame", "measurement"]) == 0
    m = read_ply(folder / "m.ply")
    ecc = loaded.eccentricity_mm
    r = np.hypot(m[:, 0] - ecc[0], m[:, 1] - ecc[1])
    assert abs(r.mean() - 17.5) < 0.01
    assert math.isfinite(loaded.diagnostics["gauge_rms_mm"])


@pytest.mark.slow
def test_demo_quick(tmp_path, capsys):
    from scheimflux._demo import run_demo

    summary = run_demo(str(tmp_path / "demo"), seed=1, quick=True)
    for name in ("observations.json", "truth.json", "calibration.json", "points.ply"):
        assert (tmp_path / "demo" / name).exists()
    assert summary["points"] == len(read_ply(tmp_path / "demo" / "points.ply"))
    assert summary["converged"]
    assert abs(summary["gauge_radius_error_um"]) < 20.0
    text = capsys.readouterr().out
    assert "gauge radius" in text and "3-D error" in text
