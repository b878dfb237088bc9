"""The rotary-table axis from a target fixed to the table: the ray-traced scene and the
closed form (exact poses: no camera model enters)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.calibrate import axis_from_poses, stage_from_axis
from scheimflux.simulate import default_stage, paper_rig, stage_target_scan
from scheimflux.targets import Checkerboard

DELTA = math.radians(30.0)


@pytest.fixture(scope="module")
def rig():
    return paper_rig(refine=False)


@pytest.fixture(scope="module")
def scan(rig):
    stage = default_stage(rig, delta_omega=DELTA)
    # 0.4 mm squares over 40 mm: the field (≈ 17.5 mm from the axis) sees ~250 corners
    # at every angle of a full turn.
    return stage_target_scan(rig, stage, Checkerboard(100, 100, 0.4), 12, noise_px=0.05)


def _poses(scan):
    R = np.stack([np.asarray(v.T_c_b.R) for v in scan.views])
    t = np.stack([np.asarray(v.T_c_b.translation) for v in scan.views])
    return R, t


def _angle(a, b):
    return math.atan2(np.linalg.norm(np.cross(a, b)), a @ b)


def test_scene_sees_the_board_at_every_angle_and_poses_map_the_corners(scan):
    px, mask = scan.corners()
    assert mask.sum(axis=1).min() > 100
    assert np.isnan(px[~mask]).all() and np.isfinite(px[mask]).all()
    # Each view's pose carries the board points to the traced 3-D points (to rounding).
    for v in scan.views:
        X = np.asarray(v.T_c_b.apply(jnp.asarray(scan.board.points_mm)))
        assert np.abs(X - v.points_c).max() < 1e-9


def test_axis_from_exact_poses_is_the_true_axis(scan):
    R, t = _poses(scan)
    d, C, step = axis_from_poses(R, t, scan.frame_index, DELTA)
    R_true = np.asarray(scan.stage.R_m_c)
    d_true, p_true = R_true[2], -R_true.T @ np.asarray(scan.stage.t_m_c)
    assert _angle(d, d_true) < 1e-9  # float64 rounding of 12 poses
    off = C - p_true
    assert np.linalg.norm(off - (off @ d_true) * d_true) < 1e-9
    assert step == pytest.approx(DELTA, abs=1e-10)
    # The gauge-fixed stage maps any two frames of a table-fixed point alike (distances
    # between frames are gauge invariant).
    stage = stage_from_axis(d, C, DELTA)
    X = jnp.asarray(scan.views[0].points_c[scan.views[0].visible][:5])
    for i in (1, 5):
        a, b = (
            np.linalg.norm(np.asarray(s.to_measurement(X[0], 0) - s.to_measurement(X[1], i)))
            for s in (stage, scan.stage)
        )
        assert abs(a - b) < 1e-9


def test_wobble_and_runout_change_the_poses_but_not_the_axis_on_average(rig):
    stage = default_stage(rig, delta_omega=DELTA)
    scan = stage_target_scan(
        rig, stage, Checkerboard(100, 100, 0.4), 12, wobble_mrad=0.1, runout_um=2.0, seed=3
    )
    R, t = _poses(scan)
    d, C, _ = axis_from_poses(R, t, scan.frame_index, DELTA)
    d_true = np.asarray(stage.R_m_c)[2]
    # σ 0.1 mrad of wobble per frame averages over 66 pairs to well below its size,
    # but is not zero: the poses are not of a perfect axis.
    assert 1e-7 < _angle(d, d_true) < 0.1e-3


def test_axis_from_poses_refuses_wrong_steps(scan):
    R, t = _poses(scan)
    with pytest.raises(ValueError, match="non-zero"):
        axis_from_poses(R, t, scan.frame_index, 0.0)
    with pytest.raises(ValueError, match="stated 20.000°"):
        axis_from_poses(R, t, scan.frame_index, math.radians(20.0))
    shuffled = scan.frame_index.copy()
    shuffled[[2, 5]] = shuffled[[5, 2]]
    with pytest.raises(ValueError, match="table order"):
        axis_from_poses(R, t, shuffled, DELTA)
    with pytest.raises(ValueError, match="two or more"):
        axis_from_poses(R[:1], t[:1], scan.frame_index[:1], DELTA)


def test_scene_refuses_a_board_the_camera_cannot_see(rig):
    stage = default_stage(rig, delta_omega=DELTA)
    with pytest.raises(ValueError, match="fewer than 6 corners"):
        stage_target_scan(rig, stage, Checkerboard(5, 5, 0.4), 3)
    with pytest.raises(ValueError, match="wobble_mrad"):
        stage_target_scan(rig, stage, Checkerboard(5, 5, 0.4), 3, wobble_mrad=-1.0)
