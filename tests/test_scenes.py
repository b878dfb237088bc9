"""Checkerboard geometry and the simulated scenes (ray-traced pixels, exact truth)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.camera import ThickLensScheimpflug
from scheimflux.io import read_observations, write_observations
from scheimflux.simulate import (
    BEARING_RADII_MM,
    board_poses,
    default_stage,
    gauge_scan,
    paper_rig,
    read_truth,
    simulate_observations,
    step_gauge,
    stripe_on_board,
    write_truth,
)
from scheimflux.targets import Checkerboard
from scheimflux.targets._board import parse_board_size


@pytest.fixture(scope="module")
def rig():
    # No focus refinement: fast, and the paraxial nominal parameters then equal the
    # sensor pose exactly, so model-vs-trace differences are the lens's alone.
    return paper_rig(refine=False)


@pytest.fixture(scope="module")
def board():
    return Checkerboard(11, 8, 0.3)


@pytest.fixture(scope="module")
def views(rig, board):
    return board_poses(rig, board, 15, seed=3)


@pytest.fixture(scope="module")
def sim(rig, board):
    return simulate_observations(rig, board, n_views=4, n_frames=4, delta_omega_deg=90.0, seed=1)


def _plane_distance(rig, X):
    n = np.asarray(rig.laser_plane)
    return np.abs(X @ n - 1.0) / np.linalg.norm(n)


# ----------------------------------------------------------------------------- board


def test_board_geometry():
    b = Checkerboard(11, 8, 0.3)
    p = b.points_mm
    assert p.shape == (88, 3) and np.all(p[:, 2] == 0)
    np.testing.assert_allclose(p[0], [0, 0, 0])
    np.testing.assert_allclose(p[1], [0.3, 0, 0])  # along the first row first
    np.testing.assert_allclose(p[11], [0, 0.3, 0])
    np.testing.assert_allclose(p[-1], [3.0, 2.1, 0])
    np.testing.assert_allclose(b.centre_mm, [1.5, 1.05, 0])
    assert b.extent_mm == pytest.approx((-0.3, 3.3, -0.3, 2.4))  # 12 x 9 squares
    assert b.square_colour(0, 0) == 0  # black, outside corner 0
    assert b.square_colour(1, 0) == 1 and b.square_colour(1, 1) == 0
    np.testing.assert_array_equal(b.square_colour(np.arange(3), 0), [0, 1, 0])
    assert b.colour_at([-0.1, -0.1]) == 0 and b.colour_at([0.1, -0.1]) == 1
    assert b.colour_at([5.0, 0.0]) == -1
    with pytest.raises(ValueError):
        b.square_colour(12, 0)


def test_board_parsing():
    assert parse_board_size("11x8") == (11, 8)
    assert parse_board_size(" 9 X 6 ") == (9, 6)
    b = Checkerboard.parse("11x8", 0.3)
    assert (b.cols, b.rows, b.square_mm, b.size) == (11, 8, 0.3, "11x8")
    for bad in ("11", "11x", "x8", "1x8", "11x8x2", "a x b", "-3x4"):
        with pytest.raises(ValueError):
            parse_board_size(bad)
    with pytest.raises(ValueError):
        Checkerboard(11, 8, 0.0)
    with pytest.raises(ValueError):
        Checkerboard(1, 8, 0.3)


# ----------------------------------------------------------------------------- poses


def test_board_poses_visible_and_cover_sensor(rig, board, views):
    w, h = rig.sensor_size
    assert len(views) == 15
    seen = np.concatenate([v.px_true[v.visible] for v in views])
    for v in views:
        assert v.visible.sum() >= 0.6 * board.num_corners
        assert np.all(np.isnan(v.px_true[~v.visible]))
        # seen upright: corner 0 top-left, running right along the first row
        p, k = v.px_true, board.cols - 1
        if v.visible[[0, k, -1]].all():
            assert p[0, 0] < p[k, 0] and p[0, 1] < p[-1, 1]
        # the board is near the laser plane (in focus): centre within ~0.3 mm
        centre = v.points_c.mean(axis=0)
        assert _plane_distance(rig, centre) < 0.31
    # every cell of a 4 x 4 grid over the sensor holds a corner of some view
    cells = set(map(tuple, np.floor(seen / [w / 4, h / 4]).astype(int)))
    assert cells >= {(i, j) for i in range(4) for j in range(4)}


def test_board_poses_deterministic_and_noise(rig, board, views):
    again = board_poses(rig, board, 15, seed=3)
    np.testing.assert_array_equal(again[4].px_true, views[4].px_true)
    other = board_poses(rig, board, 15, seed=4)
    assert not np.allclose(other[0].points_c, views[0].points_c)
    noisy = board_poses(rig, board, 15, seed=3, noise_px=0.5)
    d = np.concatenate([n.px - v.px_true for n, v in zip(noisy, views)])
    d = d[np.isfinite(d).all(axis=1)]
    assert len(d) > 1000
    assert np.std(d) == pytest.approx(0.5, rel=0.08)
    assert np.abs(np.mean(d, axis=0)).max() < 0.05


@pytest.fixture(scope="module")
def tessar_x2():
    """The 8 mm Tessar at ×2: the inclined laser plane's field is a strong trapezoid
    (2.3 mm on one side, 3.2 mm on the other), so drawn poses cut most boards."""
    from scheimflux.simulate import build_rig, load_lens

    return build_rig(load_lens("tessar"), 2.0, refine=False)


def test_whole_boards_are_slid_inside_the_sensor(tessar_x2):
    """`whole=True` moves each board the border cuts across the laser plane until every
    corner is inside: the same orientation and the same distance from the plane (so the
    same focus and laser line), and the boards that were whole stay bit-identical."""
    board = Checkerboard(11, 8, 0.184)
    drawn = board_poses(tessar_x2, board, 15, seed=0)
    kept = board_poses(tessar_x2, board, 15, seed=0, whole=True)
    cut = [k for k, v in enumerate(drawn) if not v.visible.all()]
    assert len(cut) >= 5  # the property under test is exercised
    n = np.asarray(tessar_x2.laser_plane)
    for k, (a, b) in enumerate(zip(drawn, kept)):
        assert b.visible.all(), k
        if k not in cut:
            np.testing.assert_array_equal(a.points_c, b.points_c)
            continue
        Ra, ta = (np.asarray(x) for x in (a.T_c_b.R, a.T_c_b.translation))
        Rb, tb = (np.asarray(x) for x in (b.T_c_b.R, b.T_c_b.translation))
        np.testing.assert_array_equal(Ra, Rb)
        assert not np.allclose(ta, tb)
        # the centre's signed distance from n · X = 1 is unchanged (to rounding)
        ca, cb = a.points_c.mean(axis=0), b.points_c.mean(axis=0)
        da, db = ((c @ n - 1.0) / np.linalg.norm(n) for c in (ca, cb))
        assert db == pytest.approx(da, abs=1e-9)


def test_a_board_larger_than_the_field_stays_cut(tessar_x2):
    big = board_poses(tessar_x2, Checkerboard(11, 8, 0.3), 6, seed=0, whole=True)
    assert not all(v.visible.all() for v in big)


def test_trace_is_not_the_model_but_close(rig, views):
    """The simulator is independent of the thick-lens model; they agree to a few px."""
    cam = ThickLensScheimpflug(**rig.nominal_thick_lens_params())
    X = np.concatenate([v.points_c[v.visible] for v in views])
    traced = np.concatenate([v.px_true[v.visible] for v in views])
    model = np.asarray(cam.project(X))
    err = np.linalg.norm(model - traced, axis=1)
    assert err.max() > 0.05  # a real lens is not an ideal thick lens
    assert err.max() < 5.0


# ----------------------------------------------------------------------------- stripes


def test_stripe_on_board_exact(rig, board, views):
    for v in views:
        s = stripe_on_board(rig, v.T_c_b, board)
        assert len(s.points_c) > 100
        assert _plane_distance(rig, s.points_c).max() < 1e-9
        R, t = np.asarray(v.T_c_b.R), np.asarray(v.T_c_b.translation)
        xb = (s.points_c - t) @ R
        assert np.abs(xb[:, 2]).max() < 1e-9  # on the board plane
        assert board.contains(xb[:, :2], margin_mm=-1e-9).all()
        w, h = rig.sensor_size
        assert np.all((s.px_true >= 0) & (s.px_true <= [w - 1, h - 1]))
        step = np.median(np.linalg.norm(np.diff(s.px_true, axis=0), axis=1))
        assert 1.5 < step < 2.6
        np.testing.assert_array_equal(s.px, s.px_true)  # no noise asked for


# ----------------------------------------------------------------------------- gauge


def test_default_stage_puts_gauge_through_focus(rig):
    stage = default_stage(rig, 17.5)
    x0, y0 = float(rig.x0), float(rig.y0)
    F0 = np.asarray(rig.laser_points(np.array([x0, y0])))
    X_m = np.asarray(stage.to_measurement(jnp.asarray(F0), 0))
    np.testing.assert_allclose(X_m, [17.5, 0.0, 0.0], atol=1e-9)
    # the table axis is tilted 30 degrees out of the laser plane
    n = np.asarray(rig.laser_plane) / np.linalg.norm(np.asarray(rig.laser_plane))
    assert abs(np.asarray(stage.R_m_c)[2] @ n) == pytest.approx(math.sin(math.radians(30)))


def test_gauge_scan_truth_on_cylinder_and_plane(rig):
    r = 17.5
    stage = default_stage(rig, r, math.radians(10.0))
    scan = gauge_scan(rig, stage, r, 6, points_per_frame=120)
    assert len(scan.frames) == 6
    for f in scan.frames:
        assert len(f.points_c) > 100
        assert _plane_distance(rig, f.points_c).max() < 1e-9
        np.testing.assert_allclose(np.hypot(f.points_m[:, 0], f.points_m[:, 1]), r, atol=1e-9)
        assert np.ptp(f.px_true[:, 0]) > 1000  # the stripe crosses the image
    # centred gauge: every frame sees the same arc
    np.testing.assert_allclose(scan.frames[3].px_true, scan.frames[0].px_true, atol=1e-6)


def test_gauge_scan_eccentric_wobbly(rig):
    r = BEARING_RADII_MM[0]
    stage = default_stage(rig, r, math.radians(60.0))
    scan = gauge_scan(
        rig, stage, r, 4, eccentricity_mm=(0.05, -0.03), wobble_rad=1e-3, points_per_frame=80
    )
    c, a = scan.axis_m()
    for f in scan.frames:
        assert _plane_distance(rig, f.points_c).max() < 1e-9
        rel = f.points_m - c
        radial = rel - np.outer(rel @ a, a)
        np.testing.assert_allclose(np.linalg.norm(radial, axis=1), r, atol=1e-9)
    # the eccentric gauge moves from frame to frame
    v0 = np.mean(scan.frames[0].px_true[:, 1])
    v2 = np.mean(scan.frames[2].px_true[:, 1])
    assert abs(v0 - v2) > 5.0


def test_gauge_scan_noise(rig):
    stage = default_stage(rig)
    clean = gauge_scan(rig, stage, n_frames=2, noise_px=0.3, seed=7)
    d = np.concatenate([f.px - f.px_true for f in clean.frames])
    assert np.std(d) == pytest.approx(0.3, rel=0.1)


# ----------------------------------------------------------------------------- steps


def test_step_gauge_profiles(rig):
    profiles = step_gauge(rig, (1.0, 1.5, 2.0))
    assert [p.height_mm for p in profiles] == [1.0, 1.5, 2.0]
    for p in profiles:
        assert set(np.unique(p.labels)) == {0, 1}
        assert _plane_distance(rig, p.points_c).max() < 1e-9
        heights = p.heights()
        np.testing.assert_allclose(heights[p.labels == 0], 0.0, atol=1e-9)
        np.testing.assert_allclose(heights[p.labels == 1], p.height_mm, atol=1e-9)
        for lab in (0, 1):
            assert np.ptp(p.px_true[p.labels == lab, 0]) > 500


# ----------------------------------------------------------------------------- dataset


def test_simulate_observations(rig, board, sim):
    obs, truth = sim
    assert obs.width == 1600 and obs.height == 1200
    assert obs.nominal.focal_length_mm == 97.0
    assert obs.nominal.magnification == pytest.approx(1.5)
    assert obs.nominal.tilt_deg == (3.0, 13.0)
    assert len(obs.views) == 4 and len(truth.board_poses) == 4
    np.testing.assert_array_equal(obs.board_points_mm, board.points_mm)
    uv, mask = obs.corners()
    np.testing.assert_array_equal(mask, np.isfinite(truth.corners_px).all(axis=-1))
    assert np.abs(uv[mask] - truth.corners_px[mask]).max() < 0.03 * 6
    for v, s in zip(obs.views, truth.stripe_px):
        assert v.stripe_px.shape == s.shape and len(s) > 50
    assert obs.stage is not None and len(obs.stage.frames) == 4
    assert obs.stage.gauge_radius_mm == 17.5
    for f in truth.scan_c:
        assert _plane_distance(rig, f).max() < 1e-9
    e = np.array(truth.eccentricity_mm)
    for f in truth.scan_m:
        np.testing.assert_allclose(np.hypot(*(f[:, :2] - e).T), 17.5, atol=1e-9)


def test_observations_and_truth_round_trip(sim, tmp_path):
    obs, truth = sim
    write_observations(tmp_path / "obs.json", obs)
    back = read_observations(tmp_path / "obs.json")
    a, ma = obs.corners()
    b, mb = back.corners()
    np.testing.assert_array_equal(ma, mb)
    np.testing.assert_array_equal(a[ma], b[mb])
    for v, w in zip(obs.views, back.views):
        np.testing.assert_array_equal(v.stripe_px, w.stripe_px)
    for f, g in zip(obs.stage.frames, back.stage.frames):
        np.testing.assert_array_equal(f, g)
    assert back.nominal == obs.nominal

    write_truth(tmp_path / "truth.json", truth)
    with pytest.raises(FileExistsError):
        write_truth(tmp_path / "truth.json", truth)
    t2 = read_truth(tmp_path / "truth.json")
    np.testing.assert_array_equal(t2.corners_px, truth.corners_px)
    np.testing.assert_array_equal(t2.scan_m[1], truth.scan_m[1])
    np.testing.assert_allclose(np.asarray(t2.stage.R_m_c), np.asarray(truth.stage.R_m_c))
    np.testing.assert_allclose(
        np.asarray(t2.board_poses[2].translation), np.asarray(truth.board_poses[2].translation)
    )
    assert t2.eccentricity_mm == truth.eccentricity_mm
