"""`scheimflux verify`: artefacts not used to calibrate, measured − nominal ± U.

Fast tests: the artefact parser and the CLI's refusals (all before a calibration is
read), the sphere-pair fit against exact geometry, and the ray-traced artefact scenes
measured with the rig's own model camera, plane and stage (scene and fit under test, no
calibration). The slow test runs the whole chain: simulate → calibrate → verify.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.cli._main import main
from scheimflux.io._stripes import write_stripes
from scheimflux.metrology import Cylinder, Steps, fit_shape, label_steps, measure_points
from scheimflux.metrology._stage_verify import (
    SpherePair,
    parse_artefact,
    split_two_clusters,
)
from scheimflux.simulate import default_stage, paper_rig
from scheimflux.simulate._artefacts import (
    ring_artefact,
    sphere_pair_artefact,
    stepped_gauge_artefact,
)


def _run(argv, capsys):
    rc = main(argv)
    out, err = capsys.readouterr()
    assert "nan" not in out.lower() and "nan" not in err.lower()
    return rc, out, err


# ----------------------------------------------------------------------------- parsing


def test_parse_artefact():
    assert parse_artefact("cylinder:17.0") == ("cylinder", (17.0,))
    assert parse_artefact("sphere-pair:25.4") == ("sphere-pair", (25.4,))
    assert parse_artefact("steps:1.0,1.5,2") == ("steps", (1.0, 1.5, 2.0))
    for text, msg in [
        ("cone:3", "unknown artefact 'cone'"),
        ("cylinder", "needs its nominal value"),
        ("steps:", "needs its nominal value"),
        ("sphere-pair:a", "must be numbers"),
        ("cylinder:-2", "must be positive"),
        ("cylinder:1,2", "takes one nominal value"),
    ]:
        with pytest.raises(ValueError, match=msg):
            parse_artefact(text)


# ----------------------------------------------------------------------------- CLI refusals


@pytest.fixture
def files(tmp_path):
    cal = tmp_path / "cal.json"
    cal.write_text("{}")  # never read: every refusal below comes first
    obs = tmp_path / "obs.json"
    obs.write_text("{}")
    u = np.linspace(100.0, 1500.0, 40)
    line = np.stack([u, 600.0 + 0.1 * u], axis=1)
    paths = {}
    for name, frames in {
        "two": [line, line + 3.0],
        "one": [line],
        "few": [line[:4], line[:4] + 1.0],
        "empty": [np.zeros((0, 2))] * 3,
    }.items():
        paths[name] = str(tmp_path / f"{name}.json")
        write_stripes(paths[name], frames)
    return str(cal), str(obs), paths


@pytest.mark.parametrize(
    "scan, extra, message",
    [
        ("two", ["--artefact", "torus:3"], "unknown artefact 'torus'"),
        ("two", ["--artefact", "sphere-pair"], "needs its nominal value"),
        ("two", ["--artefact", "cylinder:17", "--tolerance-um", "0"], "--tolerance-um"),
        ("two", ["--artefact", "cylinder:17", "--delta-omega-deg", "0"], "--delta-omega-deg"),
        ("empty", ["--artefact", "cylinder:17"], "holds no stripe pixels"),
        ("few", ["--artefact", "sphere-pair:17"], "too few stripe points"),
        ("one", ["--artefact", "cylinder:17"], "rotary scan"),
        ("two", ["--artefact", "steps:1,2"], "one laser profile"),
    ],
)
def test_cli_refusals(files, capsys, scan, extra, message):
    cal, obs, scans = files
    rc, out, err = _run(["verify", cal, scans[scan], "--observations", obs, *extra], capsys)
    assert rc == 1 and message in err and len(err.strip().splitlines()) == 1, err


def test_cli_needs_observations_and_files(files, capsys, tmp_path):
    cal, obs, scans = files
    rc, _, err = _run(["verify", cal, scans["two"], "--artefact", "cylinder:17"], capsys)
    assert rc == 1 and "--observations" in err
    missing = str(tmp_path / "nope.json")
    rc, _, err = _run(
        ["verify", missing, scans["two"], "--artefact", "cylinder:17", "--observations", obs],
        capsys,
    )
    assert rc == 1 and "nope.json: no such file" in err


# ----------------------------------------------------------------------------- fits


def _sphere_points(rng, c, r, n, noise=0.0):
    d = rng.normal(size=(n, 3))
    d[:, 2] = -np.abs(d[:, 2])  # a cap, as a scan sees it
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return c + (r + noise * rng.normal(size=(n, 1))) * d


def test_sphere_pair_fit_exact_and_noisy():
    rng = np.random.default_rng(3)
    c0, c1 = np.array([1.0, 2.0, 0.5]), np.array([16.0, -3.0, 1.5])
    D = float(np.linalg.norm(c1 - c0))
    X = np.concatenate([_sphere_points(rng, c0, 1.5, 200), _sphere_points(rng, c1, 1.2, 200)])
    lab = split_two_clusters(X)
    assert np.all(lab[:200] == lab[0]) and np.all(lab[200:] == 1 - lab[0])
    lab = np.where(lab[0] == 0, lab, 1 - lab)
    v = np.asarray(fit_shape(SpherePair(), X, lab).values)
    np.testing.assert_allclose(v, [D, 1.5, 1.2], atol=1e-9)  # exact points: to rounding
    Xn = np.concatenate(
        [_sphere_points(rng, c0, 1.5, 200, 1e-3), _sphere_points(rng, c1, 1.2, 200, 1e-3)]
    )
    m = measure_points(Xn, SpherePair(), labels=lab)
    # 1 µm radial noise over 200-point caps: the centre distance to ~0.3 µm; U (k = 2)
    # covers the error at the 95 % level, asserted at 2 U to keep the test certain
    assert abs(m.values[0] - D) < 2 * m.U[0] and 0.05e-3 < m.U[0] < 2e-3
    with pytest.raises(ValueError, match="one cluster"):
        split_two_clusters(np.zeros((20, 3)) + rng.normal(size=(20, 3)) * 1e-3 * 0)


# ----------------------------------------------------------------------------- scenes


@pytest.fixture(scope="module")
def rig():
    return paper_rig(refine=False)


@pytest.fixture(scope="module")
def model(rig):
    cam = sf.ThickLensScheimpflug(**rig.nominal_thick_lens_params())
    return cam, sf.LaserPlane(jnp.asarray(rig.laser_plane))


def _points_m(model, stage, px, frame_step=None):
    cam, plane = model
    dw = float(stage.delta_omega)
    uv = np.concatenate(px)
    fi = np.concatenate([np.full(len(p), i, float) for i, p in enumerate(px)])
    if frame_step is not None:
        fi = fi * frame_step / dw
    rec = sf.stripe_to_measurement(cam, plane, stage, uv, fi)
    assert np.all(np.asarray(rec.status) == 0)
    return np.asarray(rec.points)


def test_artefact_scenes_measured_with_the_model_camera(rig, model):
    # The rig's paraxial thick-lens model images the real lens's laser plane to ~0.01 px
    # (≈ 0.03 µm); its error off the pupil's chief rays is what remains. Exact points:
    # the scene geometry must give the nominal values to rounding.
    stage = default_stage(rig, 17.5, math.radians(10.0))
    ring = ring_artefact(rig, stage, 17.2, n_frames=8)
    Xt = np.concatenate([(p @ np.asarray(stage.R_m_c).T + np.asarray(stage.t_m_c)) @
                         np.asarray(sf.RotaryStage(stage.R_m_c, stage.t_m_c,
                                                   stage.delta_omega).frame_rotation(i)).T
                         for i, p in enumerate(ring.points_c)])  # fmt: skip
    assert abs(float(fit_shape(Cylinder(), Xt, None).values[0]) - 17.2) < 1e-9
    r = float(fit_shape(Cylinder(), _points_m(model, stage, ring.px_true), None).values[0])
    assert abs(r - 17.2) < 0.5e-3, r  # measured: see the report (model error only)

    sp = sphere_pair_artefact(rig, stage, delta_omega_deg=1.0)
    X = _points_m(model, stage, sp.px_true, math.radians(1.0))
    lab = np.concatenate([lab for lab in sp.labels])
    v = np.asarray(fit_shape(SpherePair(), X, lab).values)
    assert abs(v[0] - sp.nominal_mm[0]) < 2e-3, v
    np.testing.assert_allclose(v[1:], 1.5, atol=2e-3)

    st = stepped_gauge_artefact(rig, (1.0, 1.5, 2.0))
    cam, plane = model
    Xc = np.asarray(sf.stripe_to_camera(cam, plane, st.px_true[0]).points)
    lab = label_steps(Xc, 4)
    np.testing.assert_array_equal(lab, st.labels[0])  # faces numbered from smaller u
    h = np.abs(np.asarray(fit_shape(Steps(n_faces=4), Xc, lab).values))
    np.testing.assert_allclose(h, [1.0, 1.5, 2.0], atol=1e-3)


# ----------------------------------------------------------------------------- own gauge


def _gauge_cal(frames, radius=17.5):
    """A stand-in calibration holding `frames` as its gauge scan, padded as
    `calibrate._model.make_data` pads them (weight 0 on the padding)."""
    import types

    n = max(len(f) for f in frames) + 5
    gauge = np.full((len(frames) + 2, n, 2), 800.0)
    w = np.zeros(gauge.shape[:2])
    for i, f in enumerate(frames):
        gauge[i, : len(f)], w[i, : len(f)] = f, 1.0
    data = types.SimpleNamespace(gauge=gauge, gauge_w=w, gauge_radius=np.float64(radius))
    return types.SimpleNamespace(data=data)


def test_own_gauge_scan_found_and_other_artefacts_not(rig):
    """The calibration's ring gauge where it stood (its own scan, a fresh scan with new
    noise, the same scan from another start angle) is recognised frame by frame; the gauge
    moved by 10 µm on the table, a ring of another radius and a line crossing the gauge's
    stripes are not. All pixels ray-traced."""
    from scheimflux.calibration import MissingObservations
    from scheimflux.metrology._own_gauge import frames_on_calibration_gauge, is_own_gauge_scan
    from scheimflux.simulate import gauge_scan

    stage = default_stage(rig, 17.5, math.radians(30.0))
    ecc = (0.4, -0.3)

    def scan(**kw):
        kw = {"eccentricity_mm": ecc, "noise_px": 0.05, "seed": 1} | kw
        s = gauge_scan(rig, stage, 17.5, 12, points_per_frame=120, **kw)
        return [np.asarray(f.px, np.float64).reshape(-1, 2) for f in s.frames]

    def check(frames):
        uv = np.concatenate(frames)
        fi = np.concatenate([np.full(len(f), i) for i, f in enumerate(frames)])
        return frames_on_calibration_gauge(cal, uv, fi)

    own = scan()
    cal = _gauge_cal(own)
    everything = list(range(12))
    assert check(own) == everything
    assert check(scan(seed=2)) == everything  # a fresh scan: new 0.05 px noise
    assert check(own[5:] + own[:5]) == everything  # started 5 steps later
    assert is_own_gauge_scan(check(own), 12)
    # moved 10 µm on the table: its stripe moves 2.5-5.5 px at x1.5 and 4.4 µm pixels,
    # except in the 2 frames where the move is along the stripe (within 0.7 px of the
    # unmoved gauge's stripe there): the scan is not the gauge scan
    moved = check(scan(eccentricity_mm=(0.41, -0.3)))
    assert len(moved) <= 2 and not is_own_gauge_scan(moved, 12)
    ring = ring_artefact(rig, stage, 17.2, n_frames=12, noise_px=0.05, seed=3)
    assert check([np.asarray(p, np.float64) for p in ring.px]) == []
    # a straight line through one of the gauge's stripes: a few pixels on it, not 80 %
    a, b = own[3][0], own[3][-1]
    t = np.linspace(-0.5, 1.5, 400)[:, None]
    crossing = a + t * (b - a) + np.array([0.0, 40.0]) * (t - 0.5)
    assert check([crossing]) == []
    # no gauge scan to compare with
    empty = _gauge_cal([np.zeros((0, 2))])
    assert frames_on_calibration_gauge(empty, own[0]) is None
    import types

    blind = types.SimpleNamespace(data=MissingObservations("cal.json"))
    assert frames_on_calibration_gauge(blind, own[0]) is None


def test_own_gauge_found_at_another_stripe_sampling(rig):
    """A calibration whose gauge scan holds few centres per frame (the simulator's
    observations, or a subsampled extraction) against a scan of the same gauge with one
    centre per scan line (`extract` of its images), and the other way round: the gauge is
    recognised (matched against its stripe, not against its sampled centres, which lie
    further apart than the match distance); the gauge moved by 10 µm still is not.
    (Before: no frame of the dense scan matched, and `verify` measured the calibration's
    own gauge as its nominal radius.)
    All pixels ray-traced."""
    from scheimflux.metrology._own_gauge import (
        MATCH_PX,
        frames_on_calibration_gauge,
        is_own_gauge_scan,
    )
    from scheimflux.simulate import gauge_scan

    stage = default_stage(rig, 17.5, math.radians(30.0))
    ecc = (0.4, -0.3)

    def scan(n, **kw):
        kw = {"eccentricity_mm": ecc, "noise_px": 0.05, "seed": 1} | kw
        s = gauge_scan(rig, stage, 17.5, 12, points_per_frame=n, **kw)
        return [np.asarray(f.px, np.float64).reshape(-1, 2) for f in s.frames]

    def check(cal, frames):
        uv = np.concatenate(frames)
        fi = np.concatenate([np.full(len(f), i) for i, f in enumerate(frames)])
        return frames_on_calibration_gauge(cal, uv, fi)

    sparse, dense = scan(25), scan(600, seed=2)
    # the sparse centres lie many match distances apart along the stripe
    gaps = [np.median(np.linalg.norm(np.diff(f, axis=0), axis=1)) for f in sparse]
    assert min(gaps) > 8 * MATCH_PX
    everything = list(range(12))
    assert check(_gauge_cal(sparse), dense) == everything
    assert check(_gauge_cal(dense), sparse) == everything
    moved = scan(600, eccentricity_mm=(0.41, -0.3), seed=3)
    assert not is_own_gauge_scan(check(_gauge_cal(sparse), moved), 12)


# ----------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def calibrated(rig, tmp_path_factory):
    from scheimflux.calibration import write_calibration
    from scheimflux.io import write_observations
    from scheimflux.simulate import simulate_observations
    from scheimflux.targets import Checkerboard

    # eccentric gauge, full turn: an axis the warning calls determined
    obs, truth = simulate_observations(
        rig, Checkerboard(11, 8, 0.3), n_views=12, eccentricity_mm=(0.4, -0.3), seed=2
    )
    cal = sf.calibrate(obs)
    folder = tmp_path_factory.mktemp("verify")
    cal_path, obs_path = str(folder / "cal.json"), str(folder / "obs.json")
    write_calibration(cal_path, cal)
    write_observations(obs_path, obs)
    return folder, cal_path, obs_path, truth.stage


def _verify(calibrated, scene, spec, extra, capsys):
    import json

    folder, cal_path, obs_path, _ = calibrated
    scan = str(folder / f"{scene.kind}.json")
    write_stripes(scan, scene.px, overwrite=True)
    res = str(folder / f"{scene.kind}-{spec}.json")
    rc, out, err = _run(
        ["verify", cal_path, scan, "--artefact", spec, "--observations", obs_path,
         "--sigma-px", "0.05", "--out", res, *extra],
        capsys,
    )  # fmt: skip
    print(out)
    assert rc in (0, 3), err  # 1 would be a refusal: show its reason
    with open(res) as fh:
        doc = json.load(fh)
    assert doc["format"] == "scheimflux.verification/1" and doc["kind"] == scene.kind
    return rc, out, doc


@pytest.mark.slow  # one joint calibration (≈ 30 min on 2 cores under load 20) and verifies
def test_verify_end_to_end_ring_and_sphere_pair(rig, calibrated, capsys):
    # Measured (load 20): ring +0.014 ± 0.029 µm, sphere pair −0.050 ± 0.115 µm: PASS.
    stage = calibrated[3]
    ring = ring_artefact(rig, stage, 17.2, noise_px=0.05, seed=7)
    spheres = sphere_pair_artefact(rig, stage, delta_omega_deg=1.0, noise_px=0.05, seed=8)
    for scene, spec, extra in (
        (ring, "cylinder:17.2", []),
        (spheres, f"sphere-pair:{spheres.nominal_mm[0]:.9f}", ["--delta-omega-deg", "1.0"]),
    ):
        rc, out, doc = _verify(calibrated, scene, spec, extra, capsys)
        for name, v in doc["values"].items():
            # the error is explained by U (k = 2): the verdict is PASS on every value
            assert abs(v["error"]) <= v["U"], (spec, name, v)
            assert 0 < v["U"] < 0.02, (spec, name, v)  # well under a µm, not a placeholder
        assert rc == 0 and "PASS" in out
    # the calibration's own gauge scan is refused (exit 1, one line): its radius was an
    # input of the calibration, so it would come back as its nominal value
    folder, cal_path, obs_path, _ = calibrated
    from scheimflux.io import read_observations

    own = str(folder / "own-gauge.json")
    write_stripes(own, read_observations(obs_path).stage.frames, overwrite=True)
    rc, _, err = _run(["verify", cal_path, own, "--artefact", "cylinder:17.5",
                       "--observations", obs_path], capsys)  # fmt: skip
    assert rc == 1 and "own ring-gauge scan" in err and len(err.strip().splitlines()) == 1
    # a wrong nominal (50 µm off, ≫ U) fails with exit status 3
    rc, out, doc = _verify(calibrated, ring, "cylinder:17.25", [], capsys)
    assert rc == 3 and "FAIL" in out and not doc["passed"]
    assert abs(doc["values"]["radius"]["error"] + 0.05) < 0.005


def test_camera_points_mark_invalid_pixels_nan(model):
    # the steps' camera points: NaN rows where the reconstruction's status is not 0 (it
    # once wrote into the read-only NumPy view of the JAX array and refused every scan)
    import types

    from scheimflux.metrology._stage_verify import _camera_points

    cam, plane = model
    cal = types.SimpleNamespace(camera=cam, params=types.SimpleNamespace(plane=plane))
    uv = np.array([[800.0, 600.0], [np.nan, 600.0], [820.0, 610.0]])
    X = _camera_points(cal, uv)
    assert np.isnan(X[1]).all() and np.isfinite(X[[0, 2]]).all()
    want = np.asarray(sf.stripe_to_camera(cam, plane, jnp.asarray(uv[[0, 2]])).points)
    np.testing.assert_array_equal(X[[0, 2]], want)


@pytest.mark.slow
def test_verify_end_to_end_stepped_gauge(rig, calibrated, capsys):
    st = stepped_gauge_artefact(rig, noise_px=0.05, seed=9)
    rc, out, doc = _verify(calibrated, st, "steps:1.0,1.5,2.0", [], capsys)
    for name, v in doc["values"].items():
        assert abs(v["error"]) <= v["U"] and 0 < v["U"] < 0.02, (name, v)
    assert rc == 0
