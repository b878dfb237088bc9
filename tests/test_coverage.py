"""Coverage of the sensor by calibration data: the grid, the file, and flagged points."""

import dataclasses
import json
import math

import numpy as np
import pytest

from scheimflux.calibration import (
    calibrate,
    calibration_to_dict,
    diagnostics,
    parse_calibration,
    read_calibration,
    trust_entries,
    write_calibration,
)
from scheimflux.calibration.trust._summary import format_trust
from scheimflux.geometry._coverage import Coverage, count_outside, coverage_of
from scheimflux.io import CalibrationFileError, View, write_observations, write_stripes
from scheimflux.reconstruct import stripe_to_camera
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard


def _square(u0, v0, side, n=5):
    g = np.linspace(0.0, side, n)
    u, v = np.meshgrid(u0 + g, v0 + g)
    return np.stack([u.ravel(), v.ravel()], axis=1)


def test_grid_is_the_dilated_union_of_hulls():
    # two views: squares [100, 300]² and [600, 700] x [100, 200]; margin 20 px; 10 px cells
    a, b = _square(100, 100, 200), _square(600, 100, 100)
    cov = coverage_of([a, b], [np.zeros((0, 2)), np.zeros((0, 2))], (800, 400), margin_px=20,
                      cell_px=10)
    assert cov.grid.shape == (40, 80)
    # the covered area: two squares grown by 20 px with rounded corners (area of a
    # square of side s dilated by m: s² + 4 s m + π m²), to the grid's resolution (one
    # cell row along each perimeter: 10 px × perimeter)
    expected = sum(s * s + 4 * s * 20 + math.pi * 20**2 for s in (200, 100))
    perimeter = sum(4 * (s + 40) for s in (200, 100))
    assert abs(cov.fraction * 800 * 400 - expected) < 10 * perimeter / 2
    inside = np.array([[200.0, 200.0], [650.0, 150.0], [85.0, 200.0], [315.0, 200.0]])
    outside = np.array([[450.0, 200.0], [200.0, 350.0], [75.0, 75.0], [790.0, 390.0]])
    assert np.all(np.asarray(cov.contains(inside)))
    assert not np.any(np.asarray(cov.contains(outside)))
    # NaN and off-sensor pixels are never covered
    assert not np.any(np.asarray(cov.contains(np.array([[np.nan, 200.0], [-5.0, 200.0]]))))
    # the default margin is one board square as imaged: 200 / 4 = 50 px for view a
    cov_d = coverage_of([a], [np.zeros((0, 2))], (800, 400), cell_px=10)
    assert cov_d.margin_px == pytest.approx(50.0, rel=1e-12)


def test_stripe_pixels_widen_a_view_and_outliers_do_not_count():
    a = _square(100, 100, 100)
    stripe = np.array([[150.0, 150.0], [400.0, 150.0]])  # stripe beyond the corners
    cov = coverage_of([a], [stripe], (600, 300), margin_px=0, cell_px=5)
    assert bool(cov.contains(np.array([350.0, 160.0])))  # in the hull with the stripe
    assert not bool(cov.contains(np.array([350.0, 260.0])))


def test_json_form_round_trips_and_refuses_what_does_not_fit():
    cov = coverage_of([_square(10, 10, 300)], [np.zeros((0, 2))], (1001, 333), margin_px=7)
    doc = json.loads(json.dumps(cov.to_dict()))
    back = Coverage.from_dict(doc, (1001, 333))
    assert np.array_equal(back.grid, cov.grid) and back.margin_px == cov.margin_px
    assert back.fraction == pytest.approx(doc["fraction"], abs=0)
    with pytest.raises(ValueError, match="does not match the sensor"):
        Coverage.from_dict(doc, (1600, 1200))
    with pytest.raises(ValueError, match="bits holds"):
        Coverage.from_dict({**doc, "bits": "AAAA"}, (1001, 333))
    with pytest.raises(ValueError, match="format"):
        Coverage.from_dict({**doc, "format": "x"}, (1001, 333))


def test_count_outside_agrees_with_the_jax_lookup():
    cov = coverage_of([_square(100, 100, 200)], [np.zeros((0, 2))], (500, 400), margin_px=10)
    rng = np.random.default_rng(0)
    frames = [rng.uniform(-20, 520, (50, 2)) for _ in range(3)] + [np.full((2, 2), np.nan)]
    out, n = count_outside(cov, frames)
    allpx = np.concatenate(frames)
    on = np.all(np.isfinite(allpx), 1) & np.all((allpx >= -0.5) & (allpx <= [499.5, 399.5]), 1)
    assert n == on.sum()
    assert out == int(np.sum(on & ~np.asarray(cov.contains(allpx))))


@pytest.fixture(scope="module")
def left_half():
    """A ray-traced calibration, and the coverage of its boards' corners and stripes kept
    only in the left 45 % of the sensor (what boards that never reached the right side
    give). Calibrating from the left-half pixels alone was tried and refused on this
    small scene (4 views of a 6 × 5 board: the joint solve stopped unconverged at 300
    steps, the sequential one failed the stripe gate at 74 σ); the calibration here uses
    all the pixels, the coverage only the left ones."""
    rig = paper_rig(refine=False)
    obs, _ = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    full = calibrate(obs, distortion="none")
    # calibrate() records the coverage of the data it used: every used pixel is covered
    used = np.asarray(full.data.corners)[np.asarray(full.data.corner_w) > 0]
    assert full.coverage is not None and np.asarray(full.coverage.contains(used)).all()
    cut = 0.45 * obs.width

    def left(px):
        px = np.array(px, dtype=np.float64)
        px[px[:, 0] > cut] = np.nan
        return px

    views = [View(left(v.corners_px), v.stripe_px[v.stripe_px[:, 0] <= cut]) for v in obs.views]
    cov = coverage_of([v.corners_px for v in views], [v.stripe_px for v in views],
                      full.sensor_size)
    assert cov.fraction < full.coverage.fraction
    return dataclasses.replace(full, coverage=cov), dataclasses.replace(obs, views=views), cut, obs


@pytest.mark.slow  # a calibration (about a minute idle on 2 cores, 10 under load)
def test_left_half_coverage_flags_right_half_points(left_half, tmp_path, capsys):
    cal, obs, cut, _ = left_half
    cov = cal.coverage
    assert cov is not None and cov.sensor_size == (obs.width, obs.height)
    # nothing right of the cut plus the margin (one imaged board square) is covered
    assert 0.05 < cov.fraction < (cut + cov.margin_px + cov.cell_px) / obs.width
    u = np.linspace(10, obs.width - 10, 40)
    uv = np.stack([u, np.full_like(u, obs.height / 2)], axis=1)
    plain = stripe_to_camera(cal.camera, cal.plane, uv, sensor_size=cal.sensor_size)
    rec = stripe_to_camera(
        cal.camera, cal.plane, uv, sensor_size=cal.sensor_size, coverage=cal.coverage
    )
    assert plain.in_coverage is None
    # the flag changes nothing else: same points and status, bit for bit
    assert np.array_equal(np.asarray(rec.points), np.asarray(plain.points), equal_nan=True)
    assert np.array_equal(np.asarray(rec.status), np.asarray(plain.status))
    flags = np.asarray(rec.in_coverage)
    assert not flags[u > cut + cov.margin_px + cov.cell_px].any()
    # the boards' stripes ran through the middle rows: the left part is covered
    used = np.concatenate([v.stripe_px for v in obs.views])
    used = used[used[:, 0] <= cut]
    assert np.asarray(cov.contains(used)).all()

    # reported: diagnostics, the summary, the file; the file round trip keeps the grid
    d = diagnostics(cal)
    assert d.coverage == pytest.approx(cov.fraction)
    assert "sensor covered by calibration data" in d.summary()
    assert "of the sensor" in format_trust(cal)
    path = tmp_path / "cal.json"
    write_calibration(path, cal, diagnostics=trust_entries(cal))
    back = read_calibration(path)
    assert np.array_equal(back.coverage.grid, cov.grid)
    assert back.coverage.margin_px == cov.margin_px

    # the CLI says how many pixels were outside
    from scheimflux.cli._main import main

    stripes = tmp_path / "stripes.json"
    write_stripes(stripes, [uv])
    assert main(["reconstruct", str(path), str(stripes), "--out", str(tmp_path / "p.ply")]) == 0
    text = capsys.readouterr().out
    n_out = int(np.sum(~np.asarray(cov.contains(uv))))
    assert f"outside the calibration's coverage ({100 * cov.fraction:.0f} % of the sensor): " \
           f"{n_out} of 40 stripe pixels" in text


def _doc_without_coverage():
    from test_calibration_file import CASES

    cal = CASES["thick-lens-division-no-stage"]()
    return cal, calibration_to_dict(cal)


def test_old_file_without_coverage_loads_and_says_unknown(tmp_path, capsys):
    cal, doc = _doc_without_coverage()
    assert "coverage" not in doc  # what files before coverage look like
    loaded = parse_calibration(doc)
    assert loaded.coverage is None
    # the CLI says it does not know, rather than counting everything as covered
    from scheimflux.cli._main import main

    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    stripes = tmp_path / "s.json"
    write_stripes(stripes, [np.array([[800.0, 600.0], [900.0, 650.0]])])
    assert main(["reconstruct", str(path), str(stripes), "--out", str(tmp_path / "p.ply")]) == 0
    assert "coverage: unknown" in capsys.readouterr().out


def test_file_with_coverage_round_trips_and_bad_coverage_is_refused():
    cal, _ = _doc_without_coverage()
    cov = coverage_of([_square(300, 200, 600)], [np.zeros((0, 2))], cal.sensor_size,
                      margin_px=12)
    cal = dataclasses.replace(cal, coverage=cov)
    doc = calibration_to_dict(cal)
    back = parse_calibration(json.loads(json.dumps(doc)))
    assert np.array_equal(back.coverage.grid, cov.grid)
    # written again from the loaded calibration, the grid is kept
    assert calibration_to_dict(back)["coverage"] == doc["coverage"]
    bad = json.loads(json.dumps(doc))
    bad["coverage"]["shape"] = [1, 1]
    with pytest.raises(CalibrationFileError, match="coverage.shape"):
        parse_calibration(bad)
    del bad["sensor"]
    with pytest.raises(CalibrationFileError, match="coverage"):
        parse_calibration(bad)


@pytest.mark.slow  # shares the calibration above
def test_report_draws_coverage_and_the_model_error_map(left_half, tmp_path, capsys):
    import base64

    import cv2

    from scheimflux.cli._main import main
    from scheimflux.report._model_error import model_error_map

    cal, _, _, full_obs = left_half
    m = model_error_map(cal)
    # only bins with corners carry a value, and none right of the covered region
    assert np.array_equal(np.isfinite(m.error_um), m.counts > 0)
    # µm per px of residual: between the smallest and largest object-side size of one
    # pixel on the laser plane over the covered bins (a linearisation of the same map)
    vv, uu = np.nonzero(m.counts > 0)
    cu = 0.5 * (m.edges_u[1:] + m.edges_u[:-1])[uu]
    cv = 0.5 * (m.edges_v[1:] + m.edges_v[:-1])[vv]
    c = np.stack([cu, cv], 1)
    p0, pu, pv = (
        np.asarray(stripe_to_camera(cal.camera, cal.plane, c + d).points)
        for d in ([0.0, 0.0], [1.0, 0.0], [0.0, 1.0])
    )
    foot = 1e3 * np.stack([np.linalg.norm(pu - p0, axis=1), np.linalg.norm(pv - p0, axis=1)])
    ratio = m.error_um[vv, uu] / np.linalg.norm(m.mean_px[vv, uu], axis=1)
    assert np.all(ratio >= 0.99 * foot.min(0)) and np.all(ratio <= 1.01 * foot.max(0))

    cal_path, obs_path = tmp_path / "cal.json", tmp_path / "obs.json"
    write_calibration(cal_path, cal, diagnostics=trust_entries(cal))
    write_observations(obs_path, full_obs)
    out = tmp_path / "r.html"
    rc = main(["report", str(cal_path), "--observations", str(obs_path), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    text = out.read_text()
    for name in ("sensor coverage", "model error over the field"):
        assert f'alt="{name}"' in text
    for src in text.split('src="data:image/png;base64,')[1:]:
        png = base64.b64decode(src.split('"', 1)[0])
        assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR) is not None
