"""`calibrate --model opencv`, nominal values on calibrate, and the pixel pitch.

Fast tests check the flags, the nominal-value overrides and the command's plumbing; the
slow tests calibrate ray-traced corners (a real double Gauss lens, untilted sensor) and
compare with `cv2.calibrateCamera` under the same flags, and run the joint OpenCV-model
calibration with laser plane and stage and read it back.
"""

import dataclasses
import importlib
import json

import cv2
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.calibration import (
    calibrate,
    calibrate_camera,
    cv2_calibration_flags,
    diagnostics,
    opencv_frozen,
    point_uncertainty,
    read_calibration,
    with_nominal,
    write_calibration,
)
from scheimflux.calibration.core._opencv import opencv_flags_from_frozen, parse_opencv_flags
from scheimflux.cli import main
from scheimflux.io import (
    Nominal,
    Observations,
    View,
    write_observations,
)


def _obs(pitch=(0.0044, 0.0044), nominal=None):
    board = np.array([[x, y, 0.0] for y in range(3) for x in range(4)], dtype=float)
    rng = np.random.default_rng(1)
    views = [View(rng.uniform(100, 1500, (12, 2)), np.zeros((0, 2))) for _ in range(3)]
    return Observations(1600, 1200, pitch, board, views, nominal=nominal)


def _without_pitch(obs):
    # `detect` may leave the pitch out (no silent 4.4 µm default): pixel_pitch_mm None
    object.__setattr__(obs, "pixel_pitch_mm", None)
    return obs


# ----------------------------------------------------------------------------- flags


def test_flags_select_the_free_terms_as_opencv_does():
    assert parse_opencv_flags("tilted, rational") == ("rational", "tilted")
    assert parse_opencv_flags(["thin-prism", "thin-prism"]) == ("thin-prism",)
    assert parse_opencv_flags(None) == ()
    with pytest.raises(ValueError, match="unknown OpenCV flag 'tilt'; valid flags: rational"):
        parse_opencv_flags("tilt")
    default = set(opencv_frozen())
    assert default == {
        *(f"camera.distortion.{k}" for k in ("k4", "k5", "k6", "s1", "s2", "s3", "s4")),
        "camera.tau_x",
        "camera.tau_y",
    }
    assert set(opencv_frozen(["rational", "thin-prism", "tilted"])) == set()
    assert set(opencv_frozen(["zero-tangent", "fix-k3"])) == default | {
        "camera.distortion.p1",
        "camera.distortion.p2",
        "camera.distortion.k3",
    }
    for flags in [(), ("tilted",), ("rational", "thin-prism", "tilted", "zero-tangent")]:
        assert opencv_flags_from_frozen(opencv_frozen(flags)) == parse_opencv_flags(flags)
    assert cv2_calibration_flags(["rational", "tilted"]) == (
        cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_TILTED_MODEL
    )
    assert cv2_calibration_flags(["zero-tangent", "fix-k3", "thin-prism"]) == (
        cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3 | cv2.CALIB_THIN_PRISM_MODEL
    )


def test_model_and_flag_mismatches_are_refused():
    obs = _obs()
    with pytest.raises(ValueError, match="opencv_flags apply to model='opencv'"):
        calibrate_camera(obs, model="pinhole", opencv_flags="tilted")
    with pytest.raises(ValueError, match="the OpenCV model starts closed-form"):
        calibrate_camera(obs, model="opencv", init="nominal")
    with pytest.raises(ValueError, match="OpenCV model has OpenCV's distortion"):
        calibrate(obs, model="opencv", distortion="radial-tangential")


# ----------------------------------------------------------------------------- nominal values


def test_with_nominal_overrides_only_what_is_given():
    obs = _obs(nominal=Nominal(97.0, 1.5, (0.0, 13.0)))
    same = with_nominal(obs)
    assert same is obs
    new = with_nominal(obs, pixel_pitch_mm=0.0055, tilt_deg=(1.0, 12.0))
    assert new.pixel_pitch_mm == (0.0055, 0.0055)
    assert new.nominal == Nominal(97.0, 1.5, (1.0, 12.0))
    assert obs.pixel_pitch_mm == (0.0044, 0.0044)  # the input is not changed
    new = with_nominal(_obs(), pixel_pitch_mm=(0.005, 0.006), focal_length_mm=50, magnification=2)
    assert new.pixel_pitch_mm == (0.005, 0.006) and new.nominal == Nominal(50.0, 2.0, None)
    for kwargs, message in [
        ({"pixel_pitch_mm": -1.0}, "pixel_pitch_mm must be positive"),
        ({"pixel_pitch_mm": (1, 2, 3)}, "one number or"),
        ({"focal_length_mm": 0.0}, "focal_length_mm must be positive"),
        ({"magnification": float("nan")}, "magnification must be positive and finite"),
        ({"tilt_deg": (0.0, 95.0)}, "within ±90°"),
    ]:
        with pytest.raises(ValueError, match=message):
            with_nominal(obs, **kwargs)


def test_thick_lens_demands_the_pixel_pitch():
    obs = _without_pitch(_obs())
    with pytest.raises(ValueError, match="needs the sensor's pixel pitch: give --pixel-pitch-mm"):
        calibrate(obs)  # before any solve
    assert with_nominal(obs, pixel_pitch_mm=0.0044).pixel_pitch_mm == (0.0044, 0.0044)


# ----------------------------------------------------------------------------- CLI


@pytest.fixture
def fake(monkeypatch):
    """The solver replaced by a prepared calibration; records what it was given."""
    from test_calibration_file import _thick_lens, make_calibration

    # the subpackage (`sf.calibrate` is the function): the CLI looks `calibrate` up there
    calibrate_module = importlib.import_module("scheimflux.calibration")

    calls = []

    def fake(obs, **kwargs):
        calls.append((obs, kwargs))
        return make_calibration(_thick_lens(), distortion="none")

    monkeypatch.setattr(calibrate_module, "calibrate", fake)
    return calls


def _error_line(capsys):
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("scheimflux calibrate: error: ")
    return err


def test_cli_opencv_model_and_flags(tmp_path, fake):
    src = tmp_path / "obs.json"
    write_observations(src, _obs())
    argv = ["calibrate", str(src), "--out", str(tmp_path / "c.json"), "--model", "opencv"]
    assert main(argv + ["--opencv-flags", "tilted,rational"]) == 0
    ((_, kw),) = fake
    assert kw["model"] == "opencv" and kw["distortion"] == "opencv"
    assert kw["opencv_flags"] == ("rational", "tilted")


@pytest.mark.parametrize(
    "extra,message",
    [
        (["--model", "opencv", "--opencv-flags", "tilt"], "--opencv-flags: unknown OpenCV flag"),
        (["--opencv-flags", "tilted"], "--opencv-flags applies to --model opencv"),
        (["--model", "opencv", "--distortion", "division"], "choose its terms with --opencv-f"),
        (["--pixel-pitch-mm", "0"], "--pixel-pitch-mm must be one or two positive numbers"),
        (["--pixel-pitch-mm", "1", "2", "3"], "--pixel-pitch-mm must be one or two"),
        (["--focal-length-mm", "-5"], "--focal-length-mm must be positive"),
        (["--tilt-deg", "0", "120"], "--tilt-deg angles beyond any Scheimpflug camera"),
    ],
)
def test_cli_bad_options(tmp_path, fake, capsys, extra, message):
    src = tmp_path / "obs.json"
    write_observations(src, _obs())
    out = tmp_path / "c.json"
    assert main(["calibrate", str(src), "--out", str(out), *extra]) == 1
    assert message in _error_line(capsys)
    assert not out.exists() and not fake


def test_cli_nominal_values_override_the_file(tmp_path, fake):
    src = tmp_path / "obs.json"
    write_observations(src, _obs(nominal=Nominal(97.0, 1.5, (0.0, 13.0))))
    argv = ["calibrate", str(src), "--out", str(tmp_path / "c.json")]
    argv += ["--pixel-pitch-mm", "0.0055", "0.0056", "--focal-length-mm", "50"]
    argv += ["--magnification", "0.5", "--tilt-deg", "1", "-2"]
    assert main(argv) == 0
    ((obs, _),) = fake
    assert obs.pixel_pitch_mm == (0.0055, 0.0056)
    assert obs.nominal == Nominal(50.0, 0.5, (1.0, -2.0))


def test_cli_missing_pitch_names_the_option(tmp_path, fake, capsys, monkeypatch):
    import scheimflux.io._observations as obs_module

    monkeypatch.setattr(obs_module, "read_observations", lambda p: _without_pitch(_obs()))
    out = tmp_path / "c.json"
    assert main(["calibrate", "obs.json", "--out", str(out)]) == 1
    assert "give --pixel-pitch-mm" in _error_line(capsys)
    assert not fake and not out.exists()
    # given on the command line, the thick lens runs; other models never need it
    assert main(["calibrate", "obs.json", "--out", str(out), "--pixel-pitch-mm", "0.0044"]) == 0
    assert fake[-1][0].pixel_pitch_mm == (0.0044, 0.0044)
    assert (
        main(["calibrate", "o.json", "--out", str(tmp_path / "d.json"), "--model", "opencv"]) == 0
    )
    assert fake[-1][0].pixel_pitch_mm is None


# ----------------------------------------------------------------------------- ray traced


@pytest.fixture(scope="module")
def untilted():
    """An ordinary machine-vision camera: a double Gauss scaled to f = 8 mm (f/13), 1600 ×
    1200 × 4.4 µm untilted sensor, |β| = 0.5, 8 board views; corners ray traced through
    the real lens (its distortion is the lens's, k1 ≈ −0.43), noise 0.03 px."""
    base = sf.simulate.load_lens("double-gauss")
    lens = base.scaled(8.0 / float(sf.simulate.paraxial(base).efl), name="dg-f8")
    rig = sf.simulate.build_rig(
        lens.with_stop_semi_diameter(0.3), 0.5, laser_angle_deg=89.9, refine=False
    )
    return sf.simulate.simulate_observations(
        rig, sf.Checkerboard(11, 8, 1.0), n_views=8, n_frames=8, delta_omega_deg=45, seed=3
    )


def _cv2_calibrate(obs, flags):
    obj = [obs.board_points_mm[v.corner_mask].astype(np.float32) for v in obs.views]
    img = [v.corners_px[v.corner_mask].astype(np.float32) for v in obs.views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 300, 1e-15)
    size = (obs.width, obs.height)
    K0, d0 = None, None
    cv_flags = cv2_calibration_flags(flags)
    if "tilted" in flags:  # OpenCV needs a guess for its tilted model: its plain solution
        K0 = cv2.calibrateCamera(obj, img, size, None, None, criteria=crit)[1]
        d0 = np.zeros(14)
        cv_flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    out = cv2.calibrateCameraExtended(obj, img, size, K0, d0, flags=cv_flags, criteria=crit)
    return out[1], out[2].ravel(), out[5].ravel()


@pytest.mark.slow
@pytest.mark.parametrize("flags", [(), ("tilted",), ("rational",)])
def test_ray_traced_corners_equal_cv2_calibrate_camera(untilted, flags):
    obs, _ = untilted
    obs = dataclasses.replace(obs, stage=None)
    cc = calibrate_camera(obs, model="opencv", opencv_flags=flags)
    assert cc.fit.converged
    K, dist = cc.camera.to_opencv()
    K_cv, dist_cv, std_cv = _cv2_calibrate(obs, flags)
    # measured: |ΔK| ≤ 1e-3 px (both solvers stop within a small fraction of σ)
    np.testing.assert_allclose(K, K_cv, rtol=0, atol=0.01)
    n = len(dist_cv)
    if "rational" in flags:
        # On this mildly distorting lens k1..k6 share a null direction (numerator and
        # denominator trade off), so the coefficients are not comparable one by one; the
        # camera function is: both models' rays through the observed corners agree. Each
        # fits ~1000 corners with 0.03 px noise and ~20 parameters, a standard error of the
        # fitted function of ≈ 0.03·√(20/1000) ≈ 0.004 px; the bound allows 5×.
        px = np.concatenate([v.corners_px[v.corner_mask] for v in obs.views]).reshape(-1, 1, 2)
        a = cv2.undistortPoints(px, K, dist[:n]).reshape(-1, 2)
        b = cv2.undistortPoints(px, K_cv, dist_cv).reshape(-1, 2)
        assert float(np.max(np.abs(a - b)) * K_cv[0, 0]) < 0.02
        return
    ours = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist[:n]])
    theirs = np.array([K_cv[0, 0], K_cv[1, 1], K_cv[0, 2], K_cv[1, 2], *dist_cv])
    free = std_cv[: 4 + n] > 0
    assert np.all(np.abs(ours - theirs)[free] < std_cv[: 4 + n][free])


@pytest.mark.slow
def test_joint_opencv_model_with_plane_and_stage_and_its_file(untilted, tmp_path):
    obs, truth = untilted
    cal = calibrate(obs, model="opencv")
    assert all(f.converged for f in cal.fits.values())
    assert set(cal.fits) == {"camera", "stage", "joint"}
    # Lengths measured with the calibrated camera and laser plane against the ray-traced
    # truth (distances: free of the camera frame, which differs between the OpenCV model
    # and the simulator's lens frame). At |β| = 0.5 one pixel is ≈ 9 µm on the plane;
    # 0.05 px stripe noise averaged over ~5000 points and the model's misfit of the real
    # lens (reprojection 0.034 px for 0.03 px noise) bound it by ~1 µm; measured 0.14 µm.
    px = np.concatenate([np.asarray(p) for p in truth.stripe_px])
    Xt = np.concatenate([np.asarray(p) for p in truth.stripe_c])
    X = np.asarray(sf.stripe_to_camera(cal.camera, cal.plane, px).points)
    idx = np.random.default_rng(0).choice(len(X), 200, replace=False)
    dt = np.linalg.norm(Xt[idx, None] - Xt[None, idx], axis=-1)
    dc = np.linalg.norm(X[idx, None] - X[None, idx], axis=-1)
    err_um = float(np.sqrt(np.mean((dt - dc) ** 2)) * 1e3)
    print(f"length error {err_um:.3f} µm RMS")
    assert err_um < 1.0
    path = tmp_path / "cal.json"
    write_calibration(path, cal)
    assert json.loads(path.read_text())["model"] == "opencv"
    loaded = read_calibration(path, observations=obs)
    a, b = diagnostics(cal), diagnostics(loaded)
    assert a.labels == b.labels
    # entries compared on the scale of their variances, √(Σii Σjj): R_m_c goes through the
    # file as a matrix, so the stage's rotation vector comes back to ~1e-16, which moves the
    # covariance of the gauge-fixed stage components (~1e-21) by as much as themselves
    scale = np.sqrt(np.outer(np.diag(a.covariance), np.diag(a.covariance)))
    assert np.all(np.abs(b.covariance - a.covariance) <= 1e-8 * scale)
    uv = np.concatenate([v.stripe_px for v in obs.views])[:50]
    pa = point_uncertainty(cal, uv)
    pb = point_uncertainty(loaded, uv)
    np.testing.assert_allclose(pb[0], pa[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(pb[1], pa[1], rtol=1e-8)
