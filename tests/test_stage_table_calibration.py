"""The rotary-table axis from a target on the table, solved jointly with the camera and
the laser plane, on ray-traced observations (the simulator's lens, never the model under
test), from the observations file through `scheimflux calibrate` to the calibration file.

Scene: the paper rig (×1.5), 15 calibration boards (11 × 8, 0.3 mm squares, within
±0.3 mm of the laser plane), a 40 mm checkerboard (0.4 mm squares) lying on the table
2.2 mm off the axis, 12 table steps × 30° (a full turn), the table wobbling (σ 0.02 mrad
per step) and running out (σ 0.5 µm in the table plane), 0.03 px of corner noise. Its
visible corners lie up to ±6 mm off the laser plane: a camera from the boards alone
misplaced them by 4.2 px (docs/stage.md).

Comparisons are free of the calibration's gauges: the calibrated camera frame is moved
onto the true one by the rigid motion that best maps the calibrated reconstruction of a
laser-plane grid onto the true grid points (the model's projection centre sits at the
entrance pupil, 24.5 mm from the lens's H′); the axis is compared there; lengths between
points seen in different table frames need no alignment at all.
"""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.calibration import read_calibration
from scheimflux.calibration.core._blocks import _laser_points_safe
from scheimflux.cli._main import main
from scheimflux.io import StageTargetViews, read_observations
from scheimflux.io._observations import write_observations
from scheimflux.simulate import (
    default_stage,
    lying_target_pose,
    paper_rig,
    simulate_observations,
    stage_target_scan,
    trace_points,
)
from scheimflux.simulate._scenes import _board_stripe_points, _field, _trace_stripes
from scheimflux.targets import Checkerboard

pytestmark = pytest.mark.slow

DW_DEG = 30.0


def table_scene(
    rig, *, seed, n_views=15, noise_px=0.03, stripe_noise_px=0.05, wobble_mrad=0.02,
    runout_um=0.5, stripes=True,
):  # fmt: skip
    """Observations with a table target (and the laser line on it), and the true stage."""
    obs, _ = simulate_observations(
        rig, Checkerboard(11, 8, 0.3), n_views=n_views, stage_scan=False, seed=seed,
        corner_noise_px=noise_px, stripe_noise_px=stripe_noise_px,
    )  # fmt: skip
    stage = default_stage(rig, delta_omega=math.radians(DW_DEG))
    board = Checkerboard(100, 100, 0.4)
    scan = stage_target_scan(
        rig, stage, board, 12, T_t_b=lying_target_pose(rig, stage, board, offset_mm=(2.0, -1.0)),
        wobble_mrad=wobble_mrad, runout_um=runout_um, noise_px=noise_px, seed=seed,
    )  # fmt: skip
    lines = ()
    if stripes:  # the laser line on the target: 0.05 px, as on the boards
        field = _field(rig)
        sets = [_board_stripe_points(rig, field, v.T_c_b, board, 2.0) for v in scan.views]
        lines = tuple(p.px for p in _trace_stripes(rig, sets, stripe_noise_px, seed + 7, 5.0))
    views = StageTargetViews(
        DW_DEG, board.points_mm, scan.frame_index, scan.corners()[0], stripe_px=lines
    )
    return dataclasses.replace(obs, stage_target=views), stage


def _plane_grid(rig):
    """True laser-plane points (7 × 7 over 3 × 3 mm around the focus point) and pixels."""
    n = np.asarray(rig.laser_plane, dtype=np.float64)
    n = n / np.linalg.norm(n)
    a = np.cross(n, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    F0 = _field(rig).F0
    s = np.linspace(-1.5, 1.5, 7)
    X = np.array([F0 + x * a + y * b for x in s for y in s])
    uv, ok = trace_points(rig, X)
    return X[ok], uv[ok], F0


def _to_m(stage, X, i):
    R, t = np.asarray(stage.R_m_c), np.asarray(stage.t_m_c)
    c, s = math.cos(i * float(stage.delta_omega)), math.sin(i * float(stage.delta_omega))
    Ri = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (X @ R.T + t) @ Ri.T


def axis_errors(rig, true_stage, camera, plane, stage):
    """`(direction error rad, position error mm, across-frame errors mm (11, N, N))`.

    Position: the distance between the calibrated and the true axis at the focus point
    (the feet of the perpendiculars from F0). Across-frame: |X_a(frame 0) − X_b(frame j)|
    calibrated minus true for every pair of grid points and j = 1 … 11."""
    g, uv, F0 = _plane_grid(rig)
    X = np.asarray(_laser_points_safe(camera, plane, jnp.asarray(uv)))
    pm, qm = X.mean(0), g.mean(0)
    U, _, Vt = np.linalg.svd((X - pm).T @ (g - qm))
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    t = qm - R @ pm
    Rm, Rt = np.asarray(stage.R_m_c), np.asarray(true_stage.R_m_c)
    d, dt = R @ Rm[2], Rt[2]
    p = R @ (-Rm.T @ np.asarray(stage.t_m_c)) + t
    pt = -Rt.T @ np.asarray(true_stage.t_m_c)
    ang = math.atan2(np.linalg.norm(np.cross(d, dt)), float(d @ dt))
    foot = p + ((F0 - p) @ d) * d
    foot_t = pt + ((F0 - pt) @ dt) * dt
    errs = []
    for j in range(1, 12):
        Dm = np.linalg.norm(_to_m(stage, X, 0)[:, None] - _to_m(stage, X, j)[None], axis=-1)
        Dt = np.linalg.norm(_to_m(true_stage, g, 0)[:, None] - _to_m(true_stage, g, j)[None],
                            axis=-1)  # fmt: skip
        errs.append(Dm - Dt)
    return ang, float(np.linalg.norm(foot - foot_t)), np.array(errs)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    rig = paper_rig(refine=False)
    obs, stage = table_scene(rig, seed=4)
    root = tmp_path_factory.mktemp("table")
    obs_path, cal_path = root / "obs.json", root / "cal.json"
    write_observations(obs_path, obs)
    assert main(["calibrate", str(obs_path), "--out", str(cal_path)]) == 0
    cal = read_calibration(cal_path, observations=read_observations(obs_path))
    return rig, stage, cal, cal_path


def test_table_target_recovers_the_axis(calibrated, capsys):
    rig, stage, cal, _ = calibrated
    ang, pos, across = axis_errors(rig, stage, cal.camera, cal.plane, cal.stage)
    rms = float(np.sqrt(np.mean(across**2)))
    print(f"axis direction {ang * 1e3:.4f} mrad, position {pos * 1e3:.3f} um, across-frame "
          f"RMS {rms * 1e3:.3f} um (max {np.abs(across).max() * 1e3:.3f} um)")  # fmt: skip
    assert ang < 0.2e-3  # the targets
    assert pos < 5e-3
    assert rms < 1e-3
    tt = cal.diagnostics["table_target"]
    assert tt["steps"] == list(range(12))
    # the boards fit at their noise (0.03 px); the table target's misfit is the wobble a
    # rigid axis cannot follow: 0.02 mrad over ≈ 20 mm is ≈ 0.4 µm ≈ 0.13 px (measured
    # 0.141 and 0.152 px on two seeds; 0.030 px without wobble)
    assert cal.reprojection_rms_px < 0.035
    assert tt["rms_px"] < 0.2


def test_calibration_file_keeps_the_table_target(calibrated):
    rig, stage, cal, path = calibrated
    # read back with its observations: the joint fit is rebuilt with the table block
    from scheimflux.calibration.core._solve import parameter_labels

    fit = cal.fits["joint"]
    labels = parameter_labels(fit.params, fit.free_mask)
    assert "table_pose.rotvec[0]" in labels and "eccentricity[0]" not in labels
    # the rebuilt residuals (table block included) give the cost the solve wrote
    cost = 0.5 * float(np.sum(np.asarray(fit.residuals) ** 2))
    assert cost == pytest.approx(cal.diagnostics["solves"]["joint"]["cost"], rel=1e-6)
    assert cal.diagnostics["stage_axis"]["n_frames"] == 12
    assert cal.diagnostics["stage_axis"]["arc_deg"] == pytest.approx(330.0)


def _camera_frame_axis(cal, ref):
    """`(d, feet, L)`: the axis direction and the feet of the perpendiculars from the
    reference pixels' laser-plane points (camera frame, as `axis_conditioning` states
    them), and the lengths from each point in frame 0 to each half a turn later."""
    S = cal.stage
    Rm, tm = np.asarray(S.R_m_c), np.asarray(S.t_m_c)
    d, p = Rm[2], -Rm.T @ tm
    X = np.asarray(_laser_points_safe(cal.camera, cal.plane, jnp.asarray(ref)))
    feet = np.array([p + ((x - p) @ d) * d for x in X])
    L = np.linalg.norm(_to_m(S, X, 0)[:, None] - _to_m(S, X, 6)[None], axis=-1)
    return d, feet, L


def test_predicted_sigma_matches_monte_carlo_of_re_solves():
    """Predicted σ of the table axis (`diagnostics.stage_axis`: direction, position and
    a length across half a turn) against the spread of re-solves of one ray-traced scene
    whose pixels are re-noised each time (0.03 px corners, 0.05 px stripes; no table
    stripes, no wobble: pure pixel noise). The issue's target: within a factor 1.5.

    Measured (8 repeats, load 9–14): across 1.176 µm vs predicted 1.256 (ratio 1.07),
    direction 0.0271 vs 0.0304 mrad (1.12), position 25.9 vs 20.8 µm (0.80); the spread
    of a σ estimated from 8 draws is ±25 % (1σ), so 1.5 is ~2σ of that spread.
    """
    from scheimflux.calibration import calibrate
    from scheimflux.calibration.trust._stage_warning import (
        calibration_axis_conditioning,
        reference_pixels,
    )
    from scheimflux.io import View

    rig = paper_rig(refine=False)
    obs0, stage = table_scene(rig, seed=4, noise_px=0.0, stripe_noise_px=0.0, wobble_mrad=0.0,
                              runout_um=0.0, stripes=False)  # fmt: skip
    tpx = np.asarray(obs0.stage_target.corners_px)
    ref = reference_pixels(*rig.sensor_size)
    rng = np.random.default_rng(123)
    ds, feet, Ls, pred = [], [], [], []
    for _ in range(8):
        views = [
            View(
                v.corners_px + rng.normal(0, 0.03, v.corners_px.shape),
                v.stripe_px + rng.normal(0, 0.05, v.stripe_px.shape),
            )
            for v in obs0.views
        ]
        st = dataclasses.replace(obs0.stage_target,
                                 corners_px=tpx + rng.normal(0, 0.03, tpx.shape))  # fmt: skip
        cal = calibrate(dataclasses.replace(obs0, views=views, stage_target=st))
        c = calibration_axis_conditioning(cal)
        pred.append((c.sigma_across_um, c.sigma_direction_mrad, c.sigma_position_um))
        d, f, L = _camera_frame_axis(cal, ref)
        ds.append(d)
        feet.append(f)
        Ls.append(L)
    _assert_predicted_within_1_5_of_monte_carlo(pred, ds, feet, Ls)


def test_cli_refuses_table_steps_out_of_order(calibrated, tmp_path, capsys):
    """Two images swapped in the table folder: `calibrate` says so in one line and writes
    nothing (the closed-form start checks every pair's turn against the stated step)."""
    rig, _, _, _ = calibrated
    obs, _ = table_scene(rig, seed=4)
    st = obs.stage_target
    order = [0, 1, 2, 7, 4, 5, 6, 3, 8, 9, 10, 11]
    st = dataclasses.replace(st, corners_px=np.asarray(st.corners_px)[order],
                             stripe_px=tuple(st.stripe_px[k] for k in order))  # fmt: skip
    path, out = tmp_path / "obs.json", tmp_path / "cal.json"
    write_observations(path, dataclasses.replace(obs, stage_target=st))
    assert main(["calibrate", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "table order" in err and "stated 30.000°" in err
    assert not out.exists()


def test_rejection_pass_screens_the_table_target():
    """One table-target corner displaced by 1.5 px (50 σ) and one laser-line point on the
    target by 2 px: the rejection pass leaves out exactly those two (each block on its
    own robust scale, as the boards'), records them in `left_out` (re-applied on
    reading), and the axis comes out as without them (the issue's targets)."""
    from scheimflux.calibration import calibrate

    rig = paper_rig(refine=False)
    obs, stage = table_scene(rig, seed=4, wobble_mrad=0.0, runout_um=0.0)
    st = obs.stage_target
    px = np.array(st.corners_px)
    k, m = 5, int(np.flatnonzero(np.isfinite(px[5, :, 0]))[40])
    px[k, m, 0] += 1.5
    lines = [np.array(s) for s in st.stripe_px]
    j = len(lines[3]) // 2
    lines[3][j, 1] += 2.0
    obs = dataclasses.replace(obs, stage_target=dataclasses.replace(
        st, corners_px=px, stripe_px=tuple(lines)))  # fmt: skip
    cal = calibrate(obs)
    rej = cal.quality.rejected
    print({name: n for name, n in rej.items() if "outlier" in name})
    assert rej["table_corner_outliers"] == 1 and rej["table_stripe_outliers"] == 1
    np.testing.assert_array_equal(cal.left_out["table_corners"], [[k, m]])
    np.testing.assert_array_equal(cal.left_out["table_stripe"], [[3, j]])
    assert float(cal.data.table.w[k, m]) == 0.0 and float(cal.data.table.stripe_w[3, j]) == 0.0
    ang, pos, across = axis_errors(rig, stage, cal.camera, cal.plane, cal.stage)
    assert ang < 0.2e-3 and pos < 5e-3 and np.sqrt(np.mean(across**2)) < 1e-3
    # the clean scene's table block fits at its noise after the pass (0.03 px): the
    # displaced corner does not remain in the figure
    from scheimflux.calibration.core._table_block import table_target_rms_px

    assert table_target_rms_px(cal.params, cal.data) < 0.035


def test_predicted_sigma_with_table_wobble_matches_monte_carlo():
    """As above, with the table wobbling (σ 0.02 mrad per step) and running out (σ
    0.5 µm), both drawn anew for each re-solve with the pixel noise (corners only). The
    table target then fits at ≈ 0.14 px against the boards' 0.03 px: a pooled variance
    factor charged the boards' share of the σ with that misfit (3.5 µm predicted across
    half a turn). The prediction models the per-step motion as a random effect
    (`table_block_covariance`); the issue's target: within a factor 1.5 of the spread.

    Measured (8 draws, load 21–27): spread 2.10 µm across, 0.0529 mrad, 89.4 µm; the
    prediction 1.93–2.20 µm, 0.045–0.051 mrad, 79–112 µm on draws 0–2 (ratios of the
    means 0.99, 0.88, 1.11); the pooled factor's 1.47, 1.40, 0.57 and a white factor per
    block's 1.05, 0.70, 0.48 (docs/stage.md).
    """
    from scheimflux.calibration import calibrate
    from scheimflux.calibration.trust._stage_warning import (
        calibration_axis_conditioning,
        reference_pixels,
    )
    from scheimflux.io import View

    rig = paper_rig(refine=False)
    obs0, stage = table_scene(rig, seed=4, noise_px=0.0, stripe_noise_px=0.0, wobble_mrad=0.0,
                              runout_um=0.0, stripes=False)  # fmt: skip
    board = Checkerboard(100, 100, 0.4)
    T = lying_target_pose(rig, stage, board, offset_mm=(2.0, -1.0))
    ref = reference_pixels(*rig.sensor_size)
    rng = np.random.default_rng(321)
    ds, feet, Ls, pred = [], [], [], []
    for d in range(8):
        scan = stage_target_scan(rig, stage, board, 12, T_t_b=T, wobble_mrad=0.02,
                                 runout_um=0.5, noise_px=0.03, seed=1000 + d)  # fmt: skip
        views = [
            View(
                v.corners_px + rng.normal(0, 0.03, v.corners_px.shape),
                v.stripe_px + rng.normal(0, 0.05, v.stripe_px.shape),
            )
            for v in obs0.views
        ]
        st = dataclasses.replace(obs0.stage_target, corners_px=scan.corners()[0])
        cal = calibrate(dataclasses.replace(obs0, views=views, stage_target=st))
        c = calibration_axis_conditioning(cal)
        pred.append((c.sigma_across_um, c.sigma_direction_mrad, c.sigma_position_um))
        a, f, L = _camera_frame_axis(cal, ref)
        ds.append(a)
        feet.append(f)
        Ls.append(L)
    _assert_predicted_within_1_5_of_monte_carlo(pred, ds, feet, Ls)


def _assert_predicted_within_1_5_of_monte_carlo(pred, ds, feet, Ls):
    """The re-solves' spread of the across-half-turn length (µm), the axis direction
    (mrad) and the axis position (µm), each perpendicular to the mean axis, against the
    mean predicted σ of the same three: within a factor 1.5 (issue 12's target)."""
    ds, feet, Ls = np.array(ds), np.array(feet), np.array(Ls)
    dm = ds.mean(0) / np.linalg.norm(ds.mean(0))
    P = np.eye(3) - np.outer(dm, dm)

    def perp_max(A):  # as `_perp_max`: the largest σ perpendicular to the axis
        return math.sqrt(np.linalg.eigvalsh(np.cov((A @ P).T)).max())

    mc = (
        1e3 * Ls.std(0, ddof=1)[Ls.mean(0) > 1e-3].max(),
        1e3 * perp_max(ds),
        1e3 * max(perp_max(feet[:, k]) for k in range(feet.shape[1])),
    )
    pred = np.mean(pred, axis=0)
    print("predicted / Monte Carlo (across um, direction mrad, position um):", pred, mc)
    for p, m in zip(pred, mc):
        assert 1 / 1.5 < p / m < 1.5
