"""The rotary-table axis from a target fixed to the table: the ray-traced scene and the
closed form (exact poses: no camera model enters)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.calibration import axis_from_poses, stage_from_axis
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


# ----------------------------------------------------------------------------- the block


def test_block_geometry_is_the_scenes(scan):
    """`table_points_c` (the residual block's map: stage, table pose, step) puts the board
    where the ray-traced scene put it, for the scene's own stage and table pose."""
    from scheimflux.calibration.core._table_block import table_points_c

    for k, i in enumerate(scan.frame_index):
        X = np.asarray(
            table_points_c(scan.stage, scan.T_t_b, jnp.asarray(scan.board.points_mm), float(i))
        )
        assert np.abs(X - scan.views[k].points_c).max() < 1e-9


def _target_views(scan, steps=None, dw_deg=30.0):
    from scheimflux.io import StageTargetViews

    px, _ = scan.corners()
    steps = scan.frame_index if steps is None else np.asarray(steps)
    return StageTargetViews(dw_deg, scan.board.points_mm, steps, px[: len(steps)])


def _obs(rig, views):
    from scheimflux.io import Observations
    from scheimflux.simulate import nominal_of

    w, h = rig.sensor_size
    return Observations(
        int(w), int(h), (float(rig.dx), float(rig.dy)), np.zeros((4, 3)), [],
        nominal_of(rig), stage_target=views,
    )  # fmt: skip


def test_observations_file_keeps_the_table_target(rig, scan, tmp_path):
    from scheimflux.io import DroppedView, read_observations, write_observations

    views = _target_views(scan)
    views = type(views)(
        30.0, views.board_points_mm, views.table_steps[[0, 1, 3]], views.corners_px[[0, 1, 3]],
        (("a.png",), ("b.png",), ("d.png",)), [DroppedView(2, ("c.png",), "not found")],
    )  # fmt: skip
    path = tmp_path / "obs.json"
    write_observations(path, _obs(rig, views))
    back = read_observations(path).stage_target
    assert back.delta_omega_deg == 30.0
    np.testing.assert_array_equal(back.table_steps, [0, 1, 3])
    np.testing.assert_array_equal(back.corners_px, views.corners_px)  # NaN where not seen
    assert back.sources[2] == ("d.png",)
    assert back.dropped[0].view == 2 and back.dropped[0].reason == "not found"


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["stage_target"].update(delta_omega_deg=0), "non-zero"),
        (lambda d: d["stage_target"]["views"][1].update(table_step=0), "not strictly increasing"),
        (lambda d: d["stage_target"]["views"][0].update(table_step=-1), "table step >= 0"),
        (lambda d: d["stage_target"].update(spam=1), "spam"),
        (
            lambda d: d["stage_target"].update(dropped_views=[{"table_step": 1, "reason": "x"}]),
            "also a kept view",
        ),
    ],
)
def test_observations_file_refuses_bad_table_targets(rig, scan, edit, message):
    from scheimflux.io import ObservationsError
    from scheimflux.io._observations import observations_to_dict, parse_observations

    doc = observations_to_dict(_obs(rig, _target_views(scan)))
    parse_observations(doc)
    edit(doc)
    with pytest.raises(ObservationsError, match=message):
        parse_observations(doc)


def test_start_refuses_wrong_order_and_wrong_step(rig, scan):
    """The start of the block (per-view poses with a camera held, then the closed form)
    says in one line that the views are not in table order or Δω is wrong. The camera is
    the rig's paraxial model: good enough for poses, not the truth."""
    from scheimflux.calibration.core._stage_table import initial_table_target
    from scheimflux.camera import ThickLensScheimpflug

    cam = ThickLensScheimpflug(**rig.nominal_thick_lens_params())
    init = initial_table_target(cam, _obs(rig, _target_views(scan)))
    assert init.step_deg == pytest.approx(30.0, abs=0.05)
    d_true = np.asarray(scan.stage.R_m_c)[2]
    # the paraxial model's depth error tilts the poses: the start is within ~10 mrad
    assert _angle(np.asarray(init.stage.R_m_c)[2], d_true) < 0.02
    px, _ = scan.corners()
    swapped = _target_views(scan)
    swapped = type(swapped)(30.0, swapped.board_points_mm, swapped.table_steps,
                            px[[0, 1, 5, 3, 4, 2, 6, 7, 8, 9, 10, 11]])  # fmt: skip
    with pytest.raises(ValueError, match=r"table order") as err:
        initial_table_target(cam, _obs(rig, swapped))
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match=r"stated 20.000°"):
        initial_table_target(cam, _obs(rig, _target_views(scan, dw_deg=20.0)))
    few = _target_views(scan)
    corners = few.corners_px.copy()
    corners[4, 3:] = np.nan
    few = type(few)(30.0, few.board_points_mm, few.table_steps, corners)
    with pytest.raises(ValueError, match=r"table steps \[4\] have fewer than 6"):
        initial_table_target(cam, _obs(rig, few))


def test_motion_covariance_recovers_the_drawn_covariance():
    """`_motion_covariance` (the table's per-step wobble and runout, `table_block_
    covariance`): from estimates q_i = motion_i + estimation noise, drawn with a known
    correlated 4 × 4 covariance C and a known noise covariance N, it returns C (not C + N),
    positive semi-definite; pure noise gives ≈ 0, never a negative variance."""
    from scheimflux.calibration.core._stage_table import _motion_covariance

    rng = np.random.default_rng(7)
    L = np.array([[2.0, 0, 0, 0], [0.5, 1.5, 0, 0], [1.8, 0.2, 0.6, 0], [0, -1.0, 0, 0.8]])
    C = L @ L.T
    F, s_n = 4000, 0.7
    q = rng.normal(size=(F, 4)) @ L.T + rng.normal(0, s_n, (F, 4))
    N = np.broadcast_to(s_n**2 * np.eye(4), (F, 4, 4))
    got = _motion_covariance(q, N)
    # a covariance from F draws: each entry to ≈ sqrt(2 / F) of the scale (≈ 2 %); 10 %
    # of the largest variance is > 4 such σ
    np.testing.assert_allclose(got, C, atol=0.1 * np.diag(C).max())
    assert np.linalg.eigvalsh(got).min() >= -1e-12
    pure = _motion_covariance(rng.normal(0, s_n, (12, 4)), N[:12])
    assert np.linalg.eigvalsh(pure).min() >= -1e-12
    # 12 noise draws: what is left is a sampling fluctuation of N (≲ N), not N itself
    assert np.trace(pure) < np.trace(s_n**2 * np.eye(4))


def test_left_out_table_observations_are_re_applied(rig, scan):
    """`diagnostics.left_out`'s table-target entries (`table_corners`, `table_stripe`:
    `[step row, index]`) zero exactly those weights when a calibration file is read with
    its observations; an index beyond the data and table entries for observations without
    a table target are refused in one line."""
    import dataclasses

    from scheimflux.calibration.core._model import make_data
    from scheimflux.calibration.core._rejection import apply_left_out
    from scheimflux.io import View

    def obs(target):  # one placeholder board view: the weights need only the shapes
        uv = np.array([[100.0, 100.0], [200.0, 100.0], [100.0, 200.0], [200.0, 200.0]])
        return dataclasses.replace(_obs(rig, target), views=[View(uv, np.zeros((0, 2)))])

    data = make_data(obs(_target_views(scan)))
    seen = np.argwhere(np.asarray(data.table.w) > 0)
    out = apply_left_out(data, {"table_corners": seen[[0, 7]].tolist()})
    w0, w1 = np.asarray(data.table.w), np.asarray(out.table.w)
    assert w1.sum() == w0.sum() - 2 and w1[tuple(seen[0])] == 0 and w1[tuple(seen[7])] == 0
    with pytest.raises(ValueError, match="left-out table_corners index out of range"):
        apply_left_out(data, {"table_corners": [[99, 0]]})
    bare = make_data(obs(None))
    with pytest.raises(ValueError, match="observations hold no table target"):
        apply_left_out(bare, {"table_stripe": [[0, 0]]})
