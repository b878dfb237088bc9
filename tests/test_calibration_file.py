"""The calibration file: round trip to 1e-12, validation messages, no clobbering."""

import copy
import dataclasses
import functools
import json
import math
from types import SimpleNamespace

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.calibration import (
    Calibration,
    MissingObservations,
    SystemParams,
    calibration_to_dict,
    parse_calibration,
    read_calibration,
    write_calibration,
)
from scheimflux.camera import (
    Division,
    OpenCVCamera,
    Pinhole,
    RadialTangential,
    ThickLensScheimpflug,
)
from scheimflux.geometry import LaserPlane, Pose, RotaryStage
from scheimflux.io._calibration import FORMAT
from scheimflux.reconstruct import stripe_to_camera, stripe_to_measurement


def _fit(steps=7, converged=True):
    # a duck-typed stand-in for a solve: the writer reads its attributes only (Fit is
    # type-checked and needs real solver output)
    return SimpleNamespace(
        converged=converged,
        message="" if converged else "nonlinear max steps reached",
        steps=steps,
        residuals=jnp.zeros(3),
        initial_cost=10.0,
        cost=0.5,
        time_s=1.25,
        free_mask=None,
        scale=None,
        stats=None,
    )


def _thick_lens(distortion=None):
    return ThickLensScheimpflug(
        f=97.004,
        e=-2.4125,
        z0=249.47,
        phi=math.radians(2.8718),
        theta=math.radians(13.307),
        x0=796.21,
        y0=593.99,
        dx=0.0044,
        dy=0.0044,
        distortion=distortion,
    )


def _stage():
    R = np.array([[0.41199, 0.036022, -0.91047], [0.082152, 0.99368, 0.076488]])
    R = np.vstack([R, np.cross(R[0], R[1])])
    U, _, Vt = np.linalg.svd(R)
    return RotaryStage(U @ Vt, [10.023, 300.06, 11.231], math.radians(10.0))


@functools.cache
def _focus_plane():
    return _thick_lens().focus_plane()  # (distortion does not move it)


def make_calibration(camera, *, stage=True, model="thick-lens", distortion="none"):
    if isinstance(camera, ThickLensScheimpflug):
        plane = _focus_plane()
    else:
        plane = LaserPlane(1e-4 * jnp.array([8.6089, 3.6205, 31.749]))
    params = SystemParams(
        camera,
        Pose(jnp.zeros((2, 3)), jnp.ones((2, 3))),
        plane,
        _stage() if stage else None,
        jnp.array([0.05, -0.03]) if stage else None,
    )
    fits = {"camera": _fit(12), "joint": _fit(5)}
    if stage:
        fits["stage"] = _fit(9)
    return Calibration(
        params=params,
        model=model,
        distortion=distortion,
        init="nominal",
        joint=True,
        fits=fits,
        freeze={
            "thick-lens": ("camera.dx", "camera.dy", "camera.f"),
            "opencv": ("camera.tau_x",),
        }.get(model, ("camera.x0",)),
        reprojection_rms_px=0.031,
        plane_rms_mm=0.0012,
        gauge_rms_mm=0.0009 if stage else None,
        data=MissingObservations("the test's calibration"),
        sensor_size=(1600, 1200),
    )


CASES = {
    "thick-lens-rt-stage": lambda: make_calibration(
        _thick_lens(RadialTangential(0.8, -30.0, 200.0, 1e-3, -2e-3)),
        distortion="radial-tangential",
    ),
    "thick-lens-division-no-stage": lambda: make_calibration(
        _thick_lens(Division(-0.5)), stage=False, distortion="division"
    ),
    "pinhole-stage": lambda: make_calibration(
        Pinhole(39326.0, 36572.0, 256.63, -1818.3, 504.58), model="pinhole"
    ),
    "pinhole-no-stage": lambda: make_calibration(
        Pinhole(39326.0, 36572.0, 256.63, -1818.3, 504.58), model="pinhole", stage=False
    ),
    # all 14 of OpenCV's coefficients non-zero (τx, τy ≈ 1.7°, −1.1°)
    "opencv-stage": lambda: make_calibration(
        OpenCVCamera.from_opencv(
            np.array([[30000.0, 0.0, 805.3], [0.0, 30012.5, 597.1], [0.0, 0.0, 1.0]]),
            np.array(
                [-0.12, 0.35, 1.2e-3, -8e-4, -0.9, 0.05, -0.02, 0.3, 2e-3, -1e-3, 1.5e-3, -5e-4]
                + [0.03, -0.02]
            ),
        ),
        model="opencv",
        distortion="opencv",
    ),
}


@eqx.filter_jit
def _project(camera, X):
    return camera.project(X)


def _pixels(camera, plane):
    u, v = np.meshgrid(np.linspace(300, 1300, 7), np.linspace(200, 1000, 5))
    uv = jnp.asarray(np.stack([u.ravel(), v.ravel()], axis=1))
    rec = stripe_to_camera(camera, plane, uv)
    assert bool(jnp.all(rec.valid))
    return uv, rec.points


@pytest.mark.parametrize("name", sorted(CASES))
def test_round_trip_reproduces_projection_and_reconstruction(tmp_path, name):
    cal = CASES[name]()
    path = tmp_path / "cal.json"
    write_calibration(path, cal, diagnostics={"note": "test", "array": np.arange(3)})
    loaded = read_calibration(path)

    assert loaded.model == cal.model
    assert loaded.distortion == cal.distortion
    assert type(loaded.camera) is type(cal.params.camera)
    uv, X = _pixels(cal.params.camera, cal.params.plane)
    uv2, X2 = _pixels(loaded.camera, loaded.plane)
    np.testing.assert_allclose(np.asarray(X2), np.asarray(X), rtol=0, atol=1e-12)
    proj = np.asarray(_project(cal.params.camera, X))
    proj2 = np.asarray(_project(loaded.camera, X))
    np.testing.assert_allclose(proj2, proj, rtol=0, atol=1e-12)
    np.testing.assert_allclose(proj, np.asarray(uv), atol=1e-6)
    # angles come back bit for bit (degrees chosen to convert back exactly)
    if isinstance(cal.params.camera, ThickLensScheimpflug):
        assert float(loaded.camera.phi) == float(cal.params.camera.phi)
        assert float(loaded.camera.theta) == float(cal.params.camera.theta)
    if isinstance(cal.params.camera, OpenCVCamera):
        for a, b in zip(loaded.camera.to_opencv(), cal.params.camera.to_opencv()):
            np.testing.assert_array_equal(a, b)  # τ through degrees bit for bit too
    # the board poses come back exactly (they let diagnostics be rebuilt)
    np.testing.assert_array_equal(loaded.params.board_poses.rotvec, cal.params.board_poses.rotvec)
    np.testing.assert_array_equal(
        loaded.params.board_poses.translation, cal.params.board_poses.translation
    )

    if cal.params.stage is None:
        assert loaded.stage is None and loaded.eccentricity_mm is None
    else:
        idx = np.arange(uv.shape[0]) % 36
        a = stripe_to_measurement(cal.params.camera, cal.params.plane, cal.params.stage, uv, idx)
        b = stripe_to_measurement(loaded.camera, loaded.plane, loaded.stage, uv, idx)
        np.testing.assert_allclose(np.asarray(b.points), np.asarray(a.points), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(loaded.eccentricity_mm, [0.05, -0.03])
        assert float(loaded.stage.delta_omega) == float(cal.params.stage.delta_omega)

    d = loaded.diagnostics
    assert d["reprojection_rms_px"] == 0.031
    assert d["laser_plane_rms_mm"] == 0.0012
    assert d["solves"]["camera"] == {"steps": 12, "converged": True, "time_s": 1.25, "cost": 0.5}
    assert d["frozen"] == list(cal.freeze)
    assert d["converged"] is True
    assert d["note"] == "test" and d["array"] == [0, 1, 2]
    assert loaded.raw["software"]["name"] == "scheimflux"
    assert loaded.sensor_size == (1600, 1200)


def test_file_layout_units_and_degrees(tmp_path):
    cal = CASES["thick-lens-rt-stage"]()
    doc = calibration_to_dict(cal)
    assert doc["format"] == FORMAT
    cam = doc["camera"]
    assert cam["f"] == {"value": 97.004, "unit": "mm"}
    assert cam["phi"]["unit"] == "deg"
    assert cam["phi"]["value"] == pytest.approx(2.8718, abs=1e-12)
    assert cam["x0"]["unit"] == "px" and cam["dx"]["unit"] == "mm"
    assert cam["distortion"]["model"] == "radial-tangential"
    assert cam["distortion"]["k2"] == {"value": -30.0, "unit": "1"}
    pl = doc["laser_plane"]
    n = np.asarray(pl["n_per_mm"])
    np.testing.assert_allclose(pl["unit_normal"], n / np.linalg.norm(n))
    assert pl["distance_mm"] == pytest.approx(1 / np.linalg.norm(n))
    st = doc["stage"]
    assert np.shape(st["R_m_c"]) == (3, 3)
    assert st["delta_omega_deg"] == pytest.approx(10.0, abs=1e-12)
    assert st["gauge_eccentricity_mm"] == [0.05, -0.03]
    json.dumps(doc, allow_nan=False)  # plain JSON


def test_unconverged_solve_is_recorded():
    cal = make_calibration(_thick_lens())
    fits = dict(cal.fits, joint=_fit(300, converged=False))
    cal = dataclasses.replace(cal, fits=fits)
    d = calibration_to_dict(cal)["diagnostics"]
    assert d["converged"] is False
    assert d["solves"]["joint"]["converged"] is False
    assert "max steps" in d["solves"]["joint"]["message"]


def test_no_clobber(tmp_path):
    path = tmp_path / "cal.json"
    write_calibration(path, make_calibration(_thick_lens()))
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="exists"):
        write_calibration(path, CASES["pinhole-stage"]())
    assert path.read_bytes() == before
    write_calibration(path, CASES["pinhole-stage"](), overwrite=True)
    assert read_calibration(path).model == "pinhole"


def _good():
    return calibration_to_dict(CASES["thick-lens-rt-stage"]())


def _set(doc, path, value):
    node = doc
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[k]
    if value is _DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return doc


_DELETE = object()
_NOT_ROTATION = [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
_REFLECTION = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]

INVALID = [
    ("format", "scheimflux.observations/1", r"format must be 'scheimflux.calibration/1'"),
    ("format", _DELETE, r"format must be .* got None"),
    ("model", _DELETE, r"missing key model"),
    (
        "model",
        "fisheye",
        r"model must be one of \['thick-lens', 'thick-lens-noncentral', 'pinhole', 'opencv'\], "
        r"got 'fi",
    ),
    ("camera", _DELETE, r"missing key camera"),
    ("camera", [1, 2], r"camera must be a JSON object"),
    ("camera.z0", _DELETE, r"missing key camera.z0"),
    ("camera.z0", 249.0, r'camera.z0 must be \{"value": number, "unit": "mm"\}'),
    ("camera.f.value", "97", r"camera.f.value must be a finite number, got '97'"),
    ("camera.f.value", True, r"camera.f.value must be a finite number"),
    ("camera.f.unit", _DELETE, r"missing key camera.f.unit"),
    ("camera.phi.unit", "rad", r"camera.phi.unit must be 'deg', got 'rad'"),
    ("camera.dx.value", -0.0044, r"camera.dx.value must be positive \(pixel pitch\)"),
    # range checks (issue 11.4): each names the key
    ("camera.z0.value", -249.0, r"camera.z0.value must be positive \(the sensor lies behind"),
    ("camera.z0.value", 0.0, r"camera.z0.value must be positive"),
    ("camera.f.value", -97.0, r"camera.f.value must be positive \(the focal length\)"),
    ("camera.phi.value", 400.0,
     r"camera.phi.value = 400.0° is beyond any Scheimpflug camera's sensor tilt \(\|tilt\| <= 80"),
    ("camera.theta.value", -90.0, r"camera.theta.value = -90.0° is beyond any Scheimpflug camera"),
    ("camera.f.value", math.nan, r"camera.f.value must be a finite number, got nan"),
    ("camera.e.value", math.inf, r"camera.e.value must be a finite number, got inf"),
    ("laser_plane.n_per_mm", [0.0, 0.0, 1.0 / 1.5e-4], r"n_per_mm is degenerate: .* 0.15 µm"),
    ("sensor.width", 0, r"sensor.width must be a positive integer, got 0"),
    ("sensor.height", 1200.5, r"sensor.height must be a positive integer"),
    ("board_poses.rotvec", [[0.0, 0.0, 0.0]], r"board_poses.rotvec has 1 rows but .* 2"),
    # unknown keys, with the closest valid name
    ("camera.focal_lenght", 1.0, r"unknown key camera.focal_lenght; allowed here: f, e, z0"),
    ("camera.z_0", {"value": 1.0, "unit": "mm"}, r"unknown key camera.z_0 \(did you mean 'z0'"),
    ("laser_plane.normal", [0, 0, 1], r"unknown key laser_plane.normal \(did you mean 'unit_n"),
    ("stage.delta_omega", 10.0, r"unknown key stage.delta_omega \(did you mean 'delta_omega_"),
    ("camera.f.units", "mm", r"unknown key camera.f.units \(did you mean 'unit'"),
    ("camera.distortion.k4", {"value": 0.0, "unit": "1"}, r"unknown key camera.distortion.k4"),
    ("sensor.widht", 10, r"unknown key sensor.widht \(did you mean 'width'"),
    ("diagnostic", {}, r"unknown key diagnostic \(did you mean 'diagnostics'"),
    ("stage.delta_omega_deg", 0.0, r"stage.delta_omega_deg must be non-zero"),
    ("camera.distortion", _DELETE, r"missing key camera.distortion"),
    ("camera.distortion.model", "fisheye", r"camera.distortion.model of the thick-lens model"),
    ("camera.distortion.k3", _DELETE, r"missing key camera.distortion.k3"),
    ("laser_plane", _DELETE, r"missing key laser_plane \(the stage needs"),
    ("laser_plane.n_per_mm", [1.0, 2.0], r"laser_plane.n_per_mm must be a list of 3 numbers"),
    ("laser_plane.n_per_mm", [0.0, 0.0, 0.0], r"laser_plane.n_per_mm must not be zero"),
    ("laser_plane.n_per_mm", [0.0, None, 1.0], r"laser_plane.n_per_mm\[1\] must be a finite"),
    ("laser_plane.unit_normal", [1.0, 0.0, 0.0], r"unit_normal disagrees with n_per_mm"),
    ("laser_plane.distance_mm", 1.0, r"distance_mm = 1.0 disagrees with n_per_mm"),
    ("stage", "yes", r"stage must be a JSON object"),
    ("stage.R_m_c", _DELETE, r"missing key stage.R_m_c"),
    ("stage.R_m_c", [[1.0, 0.0, 0.0]], r"stage.R_m_c must be a 3x3 list of lists"),
    ("stage.R_m_c", [[1, 0, 0], [0, 1, 0], [0, 0]], r"stage.R_m_c\[2\] must be a list of 3"),
    ("stage.R_m_c", _NOT_ROTATION, r"stage.R_m_c is not a rotation matrix"),
    ("stage.R_m_c", _REFLECTION, r"stage.R_m_c is not a rotation matrix .*det = -1"),
    ("stage.t_m_c_mm", [1.0, 2.0, 3.0, 4.0], r"stage.t_m_c_mm must be a list of 3 numbers"),
    ("stage.delta_omega_deg", _DELETE, r"missing key stage.delta_omega_deg"),
    ("stage.gauge_eccentricity_mm", [0.1], r"stage.gauge_eccentricity_mm must be a list of 2"),
    ("diagnostics", [1], r"diagnostics must be a JSON object"),
]


@pytest.mark.parametrize(
    "path,value,message", INVALID, ids=[f"{p}-{i}" for i, (p, *_) in enumerate(INVALID)]
)
def test_validation_messages(tmp_path, path, value, message):
    doc = _set(copy.deepcopy(_good()), path, value)
    with pytest.raises(ValueError, match=message):
        parse_calibration(doc)
    file = tmp_path / "bad.json"
    file.write_text(json.dumps(doc))
    with pytest.raises(ValueError) as err:
        read_calibration(file)
    text = str(err.value)
    assert text.startswith(str(file) + ": ") and "\n" not in text


def test_pinhole_with_distortion_is_rejected():
    doc = calibration_to_dict(CASES["pinhole-stage"]())
    doc["camera"]["distortion"] = {"model": "division", "kappa": {"value": 0.1, "unit": "1"}}
    with pytest.raises(ValueError, match="distortion.model of the pinhole model must be one of"):
        parse_calibration(doc)


def test_optional_parts():
    doc = _good()
    del doc["diagnostics"], doc["software"], doc["stage"]
    del doc["laser_plane"]["unit_normal"], doc["laser_plane"]["distance_mm"]
    loaded = parse_calibration(doc)
    assert loaded.stage is None and loaded.diagnostics == {}


def test_unreadable_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="calibration file not found"):
        read_calibration(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_calibration(bad)
    bad.write_text("[1, 2]")
    with pytest.raises(ValueError, match="must hold a JSON object"):
        read_calibration(bad)


def test_unsupported_camera_is_refused(tmp_path):
    from scheimflux.camera import OpenCVDistortion

    cal = make_calibration(_thick_lens(OpenCVDistortion()))
    with pytest.raises(ValueError, match="cannot store a thick-lens camera with opencv dist"):
        write_calibration(tmp_path / "c.json", cal)
    assert not (tmp_path / "c.json").exists()


def test_camera_only_file_has_no_plane():
    cal = make_calibration(
        OpenCVCamera(3000.0, 3000.0, 800.0, 600.0), stage=False, model="opencv", distortion="opencv"
    )
    cal = dataclasses.replace(
        cal, params=SystemParams(cal.params.camera, cal.params.board_poses), plane_rms_mm=None
    )
    doc = calibration_to_dict(cal)
    assert "laser_plane" not in doc
    loaded = parse_calibration(doc)
    assert loaded.plane is None and loaded.camera_only and loaded.stage is None
    assert loaded.plane_rms_mm is None


def test_loaded_is_a_calibration_and_says_what_it_needs():
    import scheimflux as sf

    loaded = parse_calibration(_good(), source="cal.json")
    assert type(loaded) is sf.Calibration  # one type, computed or read back
    assert loaded.init == "nominal" and loaded.joint and loaded.converged
    assert loaded.freeze == ("camera.dx", "camera.dy", "camera.f")
    assert set(loaded.fits) == {"camera", "stage", "joint"}
    assert loaded.fits["joint"].steps == 5 and loaded.fits["joint"].cost == 0.5
    with pytest.raises(ValueError, match="cal.json was read without its observations"):
        loaded.data.corners
    doc = _good()
    doc["diagnostics"]["frozen"] = ["camera.alpha"]
    with pytest.raises(ValueError, match="diagnostics.frozen: cannot freeze 'camera.alpha'"):
        parse_calibration(doc)


def test_unconverged_file_warns_when_read(tmp_path):
    from scheimflux.io import UnconvergedCalibrationWarning

    cal = make_calibration(_thick_lens())
    cal = dataclasses.replace(cal, fits=dict(cal.fits, joint=_fit(300, False)))
    path = tmp_path / "cal.json"
    write_calibration(path, cal)  # writing does not warn (filterwarnings = error)
    with pytest.warns(UnconvergedCalibrationWarning, match=r"did NOT converge \(solves: joint\)"):
        loaded = read_calibration(path)
    assert not loaded.converged
