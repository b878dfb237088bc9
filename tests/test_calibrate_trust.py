"""Calibrations that must not lie: outliers and off-sensor pixels left out and counted,
wrong cameras refused by the quality gates, undetermined planes and parameters named.

All data are ray traced through the paper's lens (`sf.simulate`), never made by the
model under test. One small scene (4 views, 6 × 5 corners) keeps the compiled solver
shared between the tests.
"""

import dataclasses
import json
import re

import numpy as np
import pytest

from scheimflux.calibration import (
    QualityError,
    RankDeficientError,
    calibrate,
    diagnostics,
    fit_diagnostics,
)
from scheimflux.cli import main
from scheimflux.io import Nominal, View, write_observations
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard


@pytest.fixture(scope="module")
def scene():
    rig = paper_rig(refine=False)
    obs, truth = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    return obs, truth


def _perpendicular(px):
    """Unit image direction across a view's stripe (normal to its principal axis)."""
    c = px - px.mean(axis=0)
    d = np.linalg.svd(c, full_matrices=False)[2][0]
    return np.array([-d[1], d[0]])


def _contaminated(obs):
    """3 corners off by 2 px (66 σ), 5 stripe pixels 10 px across their line, and 50
    stripe pixels left of the sensor (u = −300)."""
    rng = np.random.default_rng(7)
    views = []
    for i, v in enumerate(obs.views):
        c = np.array(v.corners_px, dtype=float)
        s = np.array(v.stripe_px, dtype=float)
        if i == 1:
            c[[2, 9, 17]] += [1.2, -1.6]
        if i == 2:
            s[[10, 60, 110, 160, 210]] += 10.0 * _perpendicular(s)
            off = np.stack([np.full(50, -300.0), rng.uniform(0, 1199, 50)], 1)
            s = np.concatenate([s, off])
        views.append(View(c, s))
    return dataclasses.replace(obs, views=views)


@pytest.fixture(scope="module")
def clean(scene):
    return calibrate(scene[0], distortion="none")


def test_outliers_and_off_sensor_pixels_are_left_out_and_counted(scene, clean):
    obs, _ = scene
    cal = calibrate(_contaminated(obs), distortion="none")
    q = cal.quality
    assert q.passed, q.summary()
    assert q.rejected["stripe_outside_sensor"] == 50
    assert q.rejected["corners_outside_sensor"] == 0
    assert q.rejected["corner_outliers"] == 3
    assert q.rejected["stripe_outliers"] == 5
    assert q.rejected["threshold_sigma"] == 5.0
    # without them the solve lands where the clean data put it: the reprojection RMS
    # agrees to a few % (3 of 120 corners fewer), the plane within its σ (with the
    # outliers kept it is off by 10⁴ σ: the 5 stripe points are 10 px off their line)
    assert cal.reprojection_rms_px == pytest.approx(clean.reprojection_rms_px, rel=0.05)
    d = fit_diagnostics(clean)
    for k in range(3):
        i = d.index(f"plane.n[{k}]")
        assert abs(float(cal.plane.n[k] - clean.plane.n[k])) < d.std[i]
    # the clean calibration rejects nothing and passes every gate
    assert clean.quality.passed
    assert clean.quality.rejected["corner_outliers"] == 0
    assert clean.quality.rejected["stripe_outliers"] == 0


def test_left_out_observations_come_back_from_the_file(scene, tmp_path):
    # The file records what the rejection pass left out; read back with the same
    # observations, the residual arrays (screened, weighted, without the outliers) are
    # those the calibration was solved on, so diagnostics agree.
    from scheimflux.calibration import read_calibration, write_calibration

    contaminated = _contaminated(scene[0])
    cal = calibrate(contaminated, distortion="none")
    assert sum(len(v) for v in cal.left_out.values()) == 3 + 5
    path = tmp_path / "cal.json"
    write_calibration(path, cal)
    loaded = read_calibration(path, observations=contaminated)
    for name in ("corner_w", "stripe_w", "gauge_w", "corners", "stripe"):
        np.testing.assert_array_equal(
            np.asarray(getattr(loaded.data, name)), np.asarray(getattr(cal.data, name))
        )


def test_understated_noise_fails_the_reprojection_gate(scene):
    # the simulated corner noise is 0.03 px: stated as 0.005 px (and taken as stated),
    # the RMS is 6× the σ
    with pytest.raises(QualityError, match=r"reprojection RMS 0.03\d* px is 6.\d*× the stated"):
        calibrate(scene[0], distortion="none", sigma_corner_px=0.005, noise="stated")
    # by default the σ is estimated from the data: the calibration passes and says so
    cal = calibrate(scene[0], distortion="none", sigma_corner_px=0.005)
    assert cal.quality.noise["corner_px"] == pytest.approx(0.03, rel=0.15)
    said = [w for w in cal.quality.warnings if "corners scatter 0.03" in w]
    assert said and "the stated 0.005" in said[0]


def test_uncertainty_of_every_free_parameter_is_reported(clean):
    d = fit_diagnostics(clean)
    assert d.block == "joint"
    assert {"camera.e", "camera.z0", "camera.x0", "plane.n[0]"} <= set(d.labels)
    assert np.all(np.isfinite(d.std)) and np.all(d.std > 0)
    # the same statistics from the residual Jacobian by forward-mode autodiff and its SVD
    # (`diagnostics`), independent of the solver's block normal matrix
    # (which scales Σ by s² itself; fit_diagnostics by max(1, s²))
    ref = diagnostics(clean)
    assert ref.labels == d.labels
    s2 = ref.variance_factor
    assert d.variance_factor == pytest.approx(s2, rel=1e-9)
    # JᵀJ squares the condition number (~1e5 of the scaled J here): along the weakest
    # directions its inverse is known to ~1e-3 relative (measured 1.2e-3), the SVD of J
    # to ~1e-8; 0.5 % of a σ is far below its statistical meaning (±13 % at 30 samples)
    np.testing.assert_allclose(d.std, ref.std * np.sqrt(max(1.0, s2) / s2), rtol=5e-3)
    doc = d.to_dict()
    assert set(doc["std"]) >= {"camera.e", "camera.z0", "plane.n[2]"}
    json.dumps(doc)  # JSON-ready
    # both report the calibration's own coverage (the summary printed "unknown" beside
    # the coverage line while the calibration had one)
    assert clean.coverage is not None
    assert d.coverage == ref.coverage == clean.coverage.fraction
    assert f"{100 * clean.coverage.fraction:.0f} %" in d.summary()


def test_plane_line_states_the_joint_sigma_beside_the_points_noise_alone(clean):
    """The summary's laser-plane line gave only the σ the stripe points' noise leaves with
    camera and board poses exact (0.003 µm offset on a tessar x1 capture, where the joint
    solve's covariance of plane.n gives 7 µm): it now states both, the joint one
    propagated from plane.n's covariance (checked by sampling n from it)."""
    from scheimflux.calibration import format_trust

    d = fit_diagnostics(clean)
    line = next(x for x in format_trust(clean).splitlines() if x.startswith("laser plane"))
    assert "noise alone (camera and board poses exact)" in line and "this solve's" in line
    nums = re.search(r"with them .*normal (\S+) / (\S+) urad, of the offset (\S+) um", line)
    big, small, offset = (float(x) for x in nums.groups())
    idx = d.select("plane.n")
    n0, C = np.asarray(d.values)[idx], np.asarray(d.covariance)[np.ix_(idx, idx)]
    rng = np.random.default_rng(0)
    n = rng.multivariate_normal(n0, C, size=20000)
    dist = 1.0 / np.linalg.norm(n, axis=1)
    u0 = n0 / np.linalg.norm(n0)
    u = n / np.linalg.norm(n, axis=1)[:, None]
    tang = u - (u @ u0)[:, None] * u0  # the normal's turn (rad), its 2-D spread
    turn = np.sqrt(np.linalg.eigvalsh(np.cov(tang.T))[1:])
    # 20000 samples: standard deviations to 0.5 %; the printout has 3 digits
    assert offset * 1e-3 == pytest.approx(np.std(dist), rel=0.02)
    assert [big * 1e-6, small * 1e-6] == pytest.approx(turn[::-1], rel=0.02)
    # the points' noise alone is far below what the board poses leave
    p = clean.quality.plane
    assert p["offset_sigma_mm"] < 0.1 * offset * 1e-3


@pytest.mark.slow
def test_gate_refuses_a_bad_start_that_converges_to_a_wrong_camera(scene, tmp_path, capsys):
    # The case: a nominal tilt that is off (here θ by −4°), held fixed by the
    # nominal start. The joint solve converges, and its reprojection RMS is at the noise
    # level (0.030 px, measured): the wrong tilt is absorbed by moving the axis point
    # ~4,400 px off the 1600 px wide sensor. Only the axis-point gate catches it.
    obs, _ = scene
    n = obs.nominal
    tilt = (n.tilt_deg[0], n.tilt_deg[1] - 4.0)
    bad = dataclasses.replace(obs, nominal=Nominal(n.focal_length_mm, n.magnification, tilt))
    cal = calibrate(bad, distortion="none", init="nominal", throw=False)
    assert cal.fits["joint"].converged  # "converged" ...
    assert cal.reprojection_rms_px < 3 * 0.03  # ... with a plausible RMS ...
    failed = {g.name: g for g in cal.quality.failures}  # ... on a wrong camera
    assert "axis point" in failed, cal.quality.summary()
    assert not (-0.5 <= float(cal.camera.x0) <= 1599.5)
    assert "outside the 1600 × 1200 px sensor" in failed["axis point"].message
    # the CLI writes nothing and says what to try; --force writes it, marked as failed
    path = tmp_path / "obs.json"
    write_observations(path, bad)
    out = tmp_path / "cal.json"
    argv = ["calibrate", str(path), "--out", str(out), "--distortion", "none", "--init", "nominal"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "quality gates: axis point" in err[0], err
    assert "--init closed-form" in err[0] and "no file written" in err[0]
    assert not out.exists()
    assert main([*argv, "--force", "--allow-unconverged"]) == 0
    doc = json.loads(out.read_text())
    assert doc["diagnostics"]["quality"]["passed"] is False
    assert "FAILED its quality gates" in capsys.readouterr().out


@pytest.mark.slow
def test_laser_plane_from_one_board_pose_is_refused(scene):
    obs, _ = scene
    views = [obs.views[0]] + [View(v.corners_px, np.zeros((0, 2))) for v in obs.views[1:]]
    with pytest.raises(ValueError, match="on 1 board pose"):
        calibrate(dataclasses.replace(obs, views=views), distortion="none")


@pytest.mark.slow
def test_rank_deficiency_is_named(scene):
    obs, _ = scene
    # all nine lens parameters free: f, e, z0, dx, dy, the tilt and the axis point share
    # gauge freedoms (DEFAULT_FREEZE); the error names them instead of a wild "solution"
    with pytest.raises(RankDeficientError, match="do not determine") as err:
        calibrate(obs, distortion="none", freeze=())
    msg = str(err.value)
    # judged at the solution; at least the three gauge freedoms of DEFAULT_FREEZE
    n_null = int(re.search(r"(\d+) such direction\(s\)", msg).group(1))
    assert n_null >= 3 and "freeze one of them" in msg, msg
    named = {w for w in msg.replace(",", " ").split() if w.startswith("camera.")}
    assert len(named) >= 3, msg


@pytest.mark.slow
def test_freeze_stage_parameters(tmp_path):
    rig = paper_rig(refine=False)
    obs, _ = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, n_frames=6, delta_omega_deg=45.0, seed=1
    )
    from scheimflux.calibration import DEFAULT_FREEZE

    freeze = (*DEFAULT_FREEZE[("thick-lens", "nominal")], "stage.R_m_c")
    cal = calibrate(obs, distortion="none", freeze=freeze, throw=False)
    st = cal.fits["stage"].params.stage
    np.testing.assert_array_equal(cal.stage.T_m_c.rotvec, st.T_m_c.rotvec)
    assert "stage.T_m_c.rotvec[0]" not in cal.fits["joint"].labels
    with pytest.raises(ValueError, match="no rotary-stage scan"):
        calibrate(dataclasses.replace(obs, stage=None), freeze=freeze)


@pytest.mark.slow
def test_a_wrong_table_step_is_named_when_the_calibration_is_refused():
    """A table step typed wrong (25° for 30°) was refused naming only what the joint solve
    then lost (a null direction of plane, stage and boards, or a gate of the camera),
    never the step. The stage solve, before the camera is moved, already leaves the gauge
    scan far from its cylinder (7.5 µm against 0.14 µm with the right step; the gate is
    3 σ): the refusal now says to check the step and the gauge radius first. With the
    right step nothing is said. Ray-traced scene."""
    rig = paper_rig(refine=False)
    obs, _ = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, n_frames=12, delta_omega_deg=30.0, seed=1
    )
    cal = calibrate(obs, distortion="none")
    assert not any("before the joint solve" in w for w in cal.quality.warnings)
    wrong = dataclasses.replace(obs, stage=dataclasses.replace(obs.stage, delta_omega_deg=25.0))
    with pytest.raises((RankDeficientError, QualityError)) as err:
        calibrate(wrong, distortion="none")
    said = str(err.value)
    assert "--delta-omega-deg" in said and "(25 deg" in said and "--gauge-radius-mm" in said


def test_free_spec_accepts_stage_paths():
    import jax.numpy as jnp

    import scheimflux as sf
    from scheimflux.calibration import SystemParams, free_spec
    from scheimflux.geometry import LaserPlane, Pose, RotaryStage

    cam = sf.ThickLensScheimpflug(97.0, -2.4, 249.5, 0.05, 0.23, 796.2, 594.0, 0.0044, 0.0044)
    poses = Pose(jnp.zeros((2, 3)), jnp.ones((2, 3)))
    camera_only = SystemParams(cam, poses)
    # the stage block is not there yet (camera solve): a stage path is skipped
    spec = free_spec(camera_only, ("camera.dx", "stage.R_m_c", "stage.delta_omega"))
    assert spec.camera.dx is False and spec.camera.e is True
    stage = RotaryStage(jnp.eye(3), jnp.ones(3), 0.1)
    full = SystemParams(cam, poses, LaserPlane(jnp.array([0.0, 0.0, 0.01])), stage)
    spec = free_spec(full, ("stage.R_m_c", "stage.t_m_c"))
    assert spec.stage.T_m_c.rotvec is False and spec.stage.T_m_c.translation is False
    assert spec.stage.delta_omega is True and spec.plane.n is True
    with pytest.raises(ValueError, match="no parameter 'omega' there .*delta_omega"):
        free_spec(full, ("stage.omega",))


# Calibrating inside a field radius: the corners beyond it are pushed 0.5 px outward
# (17 σ), as a vignetted lens's clipped bundles shift them at the field's edge; none of
# them may reach the solve.
FIELD_RADIUS_PX = 600.0


def _beyond(obs, px):
    centre = np.array([(obs.width - 1) / 2.0, (obs.height - 1) / 2.0])
    return np.linalg.norm(np.asarray(px) - centre, axis=-1) > FIELD_RADIUS_PX


def _outer_field_shifted(obs):
    centre = np.array([(obs.width - 1) / 2.0, (obs.height - 1) / 2.0])
    views = []
    for v in obs.views:
        c = np.array(v.corners_px, dtype=float)
        far = _beyond(obs, c)
        r = c[far] - centre
        c[far] += 0.5 * r / np.linalg.norm(r, axis=1, keepdims=True)
        views.append(View(c, np.array(v.stripe_px, dtype=float)))
    return dataclasses.replace(obs, views=views)


def _cut_by_hand(obs):
    views = []
    for v in obs.views:
        c = np.array(v.corners_px, dtype=float)
        c[_beyond(obs, c)] = np.nan
        s = np.array(v.stripe_px, dtype=float)
        views.append(View(c, s[~_beyond(obs, s)]))
    return dataclasses.replace(obs, views=views)


@pytest.fixture(scope="module")
def inside_radius(scene):
    return calibrate(
        _outer_field_shifted(scene[0]), distortion="none", max_radius_px=FIELD_RADIUS_PX
    )


def test_a_field_radius_leaves_the_outer_field_out_and_counts_it(scene, inside_radius):
    obs = scene[0]
    cal = inside_radius
    q = cal.quality
    assert q.passed, q.summary()
    n_corners = sum(int(_beyond(obs, v.corners_px).sum()) for v in obs.views)
    n_stripe = sum(int(_beyond(obs, v.stripe_px).sum()) for v in obs.views)
    assert n_corners >= 10 and n_stripe > 50  # the radius does cut the scene
    assert q.rejected["field_radius_px"] == FIELD_RADIUS_PX
    assert q.rejected["corners_beyond_radius"] == n_corners
    assert q.rejected["stripe_beyond_radius"] == n_stripe
    assert q.rejected["gauge_beyond_radius"] == 0
    assert f"beyond 600 px from the sensor's centre {n_corners} corners" in q.summary()
    # the shifted corners never reach the solve: the result is the calibration of the
    # observations cut by hand (the same arrays, so the same numbers)
    by_hand = calibrate(_cut_by_hand(obs), distortion="none")
    np.testing.assert_array_equal(np.asarray(cal.plane.n), np.asarray(by_hand.plane.n))
    assert cal.reprojection_rms_px == by_hand.reprojection_rms_px
    # the coverage ends at the radius (the data's hulls, grown by a margin, would reach
    # beyond it): on a grid of cells, so every pixel of the data kept is covered and
    # none farther than the radius + one cell diagonal
    centre = np.array([(obs.width - 1) / 2.0, (obs.height - 1) / 2.0])
    cov = cal.coverage
    kept = np.concatenate([np.asarray(v.corners_px) for v in obs.views])
    kept = kept[~_beyond(obs, kept)]
    assert np.all(np.asarray(cov.contains(kept)))
    u, v = np.meshgrid(np.arange(0, obs.width, 4.0), np.arange(0, obs.height, 4.0))
    grid = np.stack([u.ravel(), v.ravel()], axis=1)
    inside = np.asarray(cov.contains(grid))
    assert np.linalg.norm(grid[inside] - centre, axis=1).max() <= (
        FIELD_RADIUS_PX + np.sqrt(2) * cov.cell_px
    )
    assert cov.margin_px > np.sqrt(2) * cov.cell_px  # without the clip it would fail


def test_a_field_radius_comes_back_from_the_file(scene, inside_radius, tmp_path):
    # read back with the full observations, the residual arrays are those solved on
    from scheimflux.calibration import read_calibration, write_calibration

    path = tmp_path / "cal.json"
    write_calibration(path, inside_radius)
    loaded = read_calibration(path, observations=_outer_field_shifted(scene[0]))
    for name in ("corner_w", "stripe_w", "corners", "stripe"):
        np.testing.assert_array_equal(
            np.asarray(getattr(loaded.data, name)), np.asarray(getattr(inside_radius.data, name))
        )


def test_a_field_radius_that_leaves_too_little_is_refused(scene, tmp_path, capsys):
    obs = scene[0]
    with pytest.raises(ValueError, match="leaves 0 views with 6 or more corners"):
        calibrate(obs, distortion="none", max_radius_px=20.0)
    with pytest.raises(ValueError, match="positive number of pixels"):
        calibrate(obs, distortion="none", max_radius_px=-1.0)
    # the corners inside, every laser-line pixel in the sensor's corner beyond the radius
    far_line = [View(v.corners_px, np.array([[1500.0, 1100.0 + k] for k in range(20)]))
                for v in obs.views]  # fmt: skip
    with pytest.raises(ValueError, match="leaves no stripe pixel on the boards"):
        calibrate(dataclasses.replace(obs, views=far_line), distortion="none",
                  max_radius_px=FIELD_RADIUS_PX)  # fmt: skip
    path = tmp_path / "obs.json"
    write_observations(path, obs)
    code = main(["calibrate", str(path), "--out", str(tmp_path / "c.json"),
                 "--max-radius-px", "0"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1 and "--max-radius-px must be positive" in err
    assert not (tmp_path / "c.json").exists()


def test_a_line_whose_board_motion_was_not_measured_is_named(scene, clean):
    # `detect` could not tell whether view 1's board moved between its laser-off and
    # laser-on images (NaN): the calibration uses its line and says so
    obs = scene[0]
    views = [dataclasses.replace(v, source=(f"view_{i}_board.png", f"view_{i}_stripe.png"),
                                 board_motion_px=float("nan") if i == 1 else 0.01)
             for i, v in enumerate(obs.views)]  # fmt: skip
    cal = calibrate(dataclasses.replace(obs, views=views), distortion="none")
    said = [w for w in cal.quality.warnings if "could not be measured" in w]
    assert len(said) == 1 and "view(s) 1 (view_1_stripe.png)" in said[0], cal.quality.warnings
    assert said[0] in cal.quality.summary()
    # without a recorded motion nothing is said
    assert not any("could not be measured" in w for w in clean.quality.warnings)


def test_a_square_size_typed_10x_off_is_named(scene, clean):
    # Pixel rays do not fix the scene's scale: with every board point 10x (a square size
    # typed 10x off) the boards are placed 10x farther and every gate passes (the x0.5
    # achromat world: the boards at 3 m, where f = 100 mm at |beta| = 0.5 focuses at
    # 0.3 m, every length 10x). The nominal f and magnification say where the object is:
    # the calibration names the mismatch. Ray-traced corners and lines.
    obs = scene[0]
    wrong = dataclasses.replace(obs, board_points_mm=10.0 * np.asarray(obs.board_points_mm))
    cal = calibrate(wrong, distortion="none")
    assert cal.quality.passed  # nothing else tells
    said = [w for w in cal.quality.warnings if "--square-mm" in w]
    assert len(said) == 1, cal.quality.warnings
    # 10x, to the thin-lens distance f (1 + 1/|beta|) against the camera frame's origin
    # (here 0.96 of it at the right size)
    ratio = float(re.search(r"mm from the lens, ([0-9.]+)x the", said[0]).group(1))
    assert 8.0 < ratio < 12.0
    assert said[0] in cal.quality.summary()
    # the right size: the boards where the nominal lens images, nothing said
    assert not any("--square-mm" in w for w in clean.quality.warnings)


def test_correlated_neighbouring_centres_are_named(clean):
    """Stripe centres extracted from images share their errors with their neighbours
    (rendered colour JPEG: ρ₁ = 0.88 on the gauge); the calibration's σ assume
    independent centres, so such residuals are named with √τ. AR(1) rows with ρ = 0.8
    (τ = 1 + 2 Σ 0.8ᵏ = 9, estimated from 20 × 300 residuals to ~0.01 in ρ₁) are; white
    rows and the ray-traced scene's own residuals (independent noise) are not."""
    from scheimflux.calibration.trust._quality import correlated_centres_warning

    rng = np.random.default_rng(4)
    rows, n, rho = 20, 300, 0.8
    e = rng.standard_normal((rows, n))
    ar = np.empty_like(e)
    ar[:, 0] = e[:, 0]
    for k in range(1, n):
        ar[:, k] = rho * ar[:, k - 1] + np.sqrt(1 - rho**2) * e[:, k]
    used = np.ones((rows, n), bool)
    used[:, -40:] = False  # padding
    said = correlated_centres_warning([("gauge", ar, used)])
    assert said is not None
    m = re.search(r"gauge rho1 = ([\d.]+), tau = ([\d.]+)", said)
    assert m and abs(float(m.group(1)) - rho) < 0.05 and 6 < float(m.group(2)) < 12, said
    assert correlated_centres_warning([("gauge", e, used)]) is None
    assert not any("share their errors" in w for w in clean.quality.warnings)


def test_counted_correlation_warning_states_the_tau_of_the_sigma():
    """Where the σ count the correlation, the warning gives the τ they were raised by
    (`Diagnostics.correlation_time`, from the residuals standardised by their pixel
    gains), not its own plain lag estimate: one summary and report, one τ (a colour-JPEG
    capture said tau = 9.3 on the σ line and tau = 9.03 in the warning)."""
    from helpers import ar1_noise

    from scheimflux.calibration.trust._quality import correlated_centres_warning

    ar = ar1_noise(np.random.default_rng(4), (20, 300), 0.8)
    blocks = [("board stripes", ar, np.ones(ar.shape, bool))]
    own = re.search(r"tau = ([\d.]+)", correlated_centres_warning(blocks, counted=True))
    stated = 2.0 * float(own.group(1))  # any τ other than the warning's own estimate
    said = correlated_centres_warning(blocks, counted=True, taus={"stripes": stated})
    m = re.search(r"board stripes rho1 = ([\d.]+), tau = ([\d.]+)", said)
    assert m and float(m.group(2)) == float(f"{stated:.3g}"), said


@pytest.fixture(scope="module")
def correlated(scene):
    """The scene with AR(1) noise (ρ = 0.8) along each board stripe, and its calibration."""
    from helpers import ar1_noise

    obs, truth = scene
    rng = np.random.default_rng(3)
    views = [
        View(
            c + 0.03 * rng.standard_normal(c.shape), s + 0.05 * ar1_noise(rng, s.shape[::-1], 0.8).T
        )
        for c, s in zip(truth.corners_px, truth.stripe_px)
    ]
    obs = dataclasses.replace(obs, views=views)
    # as stated (0.05 px): the correlation, not a re-estimated σ, is what raises the σ
    return calibrate(obs, distortion="none", noise="stated"), obs


def test_sigma_count_correlated_centres_and_nothing_else_changes(correlated, clean):
    """The calibration's σ count stripe centres that share their errors along their line
    (tests/test_correlated_sigma.py has the known-answer and Monte Carlo checks). Here, on
    the ray-traced scene: with its independent noise the covariance is the former
    max(1, s²)(JᵀJ)⁺ bit for bit (the lag screen finds nothing, no Jacobian is built);
    with AR(1) noise (ρ = 0.8) along each board stripe it is raised (never lowered in
    any direction), the board stripes' τ is recorded (estimated from ~1800 residuals:
    truncated at ρ_k < 0.07, about 8.5 for the 9 of the full sum, minus what the fit
    absorbs), and the warning, the file and the summary say that the σ include it."""
    from helpers import former_fit_covariance

    from scheimflux.calibration import calibration_summary, trust_entries
    from scheimflux.calibration.trust import correlated_groups

    d = fit_diagnostics(clean)
    assert d.correlation_time == {} and correlated_groups(clean) is None
    assert np.array_equal(d.covariance, former_fit_covariance(clean.fits["joint"]))
    assert "correlation_time" in d.to_dict() and not d.to_dict()["correlation_time"]

    cal = correlated[0]
    d = fit_diagnostics(cal)
    assert set(d.correlation_time) == {"stripes"}
    assert 4.0 < d.correlation_time["stripes"] < 9.0, d.correlation_time
    old = former_fit_covariance(cal.fits["joint"])
    # Σ_new − Σ_old ⪰ 0: no linear function of the parameters (the parameters themselves,
    # random combinations in units of their σ) has a smaller variance than before
    g = np.vstack([np.eye(len(d.std)), np.random.default_rng(0).standard_normal((500, len(d.std)))])
    g = g / np.sqrt(np.diag(old))
    v_old, v_new = (np.einsum("ni,ij,nj->n", g, C, g) for C in (old, d.covariance))
    assert np.all(v_new >= v_old * (1 - 1e-9)) and np.max(v_new / v_old) > 1.05
    plane = d.select("plane.n")
    assert np.all(d.std[plane] > np.sqrt(np.diag(old))[plane])
    said = [w for w in cal.quality.warnings if "share their errors" in w]
    assert len(said) == 1 and "counted in the σ of this calibration" in said[0]
    assert "too small" not in said[0]
    # the τ the σ were raised by, the one the summary's σ line states
    tau = float(re.search(r"tau = ([\d.]+)", said[0]).group(1))
    assert tau == float(f"{d.correlation_time['stripes']:.3g}"), (said[0], d.correlation_time)
    doc = trust_entries(cal)["uncertainty"]
    assert doc["correlation_time"] == {"stripes": pytest.approx(d.correlation_time["stripes"])}
    assert doc["std"]["plane.n[2]"] == pytest.approx(d.std_of("plane.n[2]"))
    assert "σ count the correlation of neighbouring stripe centres" in calibration_summary(cal)


def test_a_calibration_read_back_states_the_same_uncertainties(correlated, tmp_path):
    """Read back from its file with its observations, a calibration states the σ it was
    written with: `fit_diagnostics` (the file keeps no JᵀJ: assembled from the residuals'
    Jacobian at the stored optimum; it raised "kept no normal matrix" before), with the
    correlated stripe centres counted, and so `length_uncertainty` and `point_uncertainty`.
    `point_uncertainty` states that covariance by default (it used `diagnostics`, which
    neither floors s² at 1 nor counts the correlation: σ too small by √τ and 1/s)."""
    from scheimflux.calibration import (
        length_uncertainty,
        point_uncertainty,
        read_calibration,
        write_calibration,
    )

    cal, obs = correlated
    path = tmp_path / "cal.json"
    write_calibration(path, cal)
    loaded = read_calibration(path, observations=obs)
    a, b = fit_diagnostics(cal), fit_diagnostics(loaded)
    assert b.labels == a.labels and b.n_residuals == a.n_residuals
    assert b.variance_factor == pytest.approx(a.variance_factor, rel=1e-9)
    assert set(b.correlation_time) == {"stripes"}
    assert b.correlation_time["stripes"] == pytest.approx(a.correlation_time["stripes"], rel=1e-6)
    # the solver's block-assembled JᵀJ against Jᵀ J from forward-mode autodiff: equal to
    # rounding, which the inverse amplifies by the scaled condition number (~1e5² here)
    # along the weakest directions; 1e-3 of a σ is far below its statistical meaning
    np.testing.assert_allclose(b.std, a.std, rtol=1e-3)
    uv = np.concatenate([v.stripe_px for v in obs.views])
    ua, ub = uv[:40], uv[-40:]
    la, lb = length_uncertainty(cal, ua, ub), length_uncertainty(loaded, ua, ub)
    np.testing.assert_allclose(lb["sigma"], la["sigma"], rtol=1e-3)
    Xa, sa, _ = point_uncertainty(cal, ua)
    Xb, sb, _ = point_uncertainty(loaded, ua)
    np.testing.assert_allclose(Xb, Xa, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sb, sa, rtol=1e-3)
    # the default is the stated covariance, the one length_uncertainty uses...
    np.testing.assert_array_equal(sa, point_uncertainty(cal, ua, diag=a)[1])
    # ...larger than the unfloored, uncorrelated one of `diagnostics` (s² < 1 here)
    old = point_uncertainty(cal, ua, diag=diagnostics(cal, block="joint"))[1]
    assert np.all(sa >= old * (1 - 1e-6)) and np.median(sa / old) > 1.2
    with pytest.raises(ValueError, match="joint problem"):
        point_uncertainty(cal, ua, diag=diagnostics(cal, block="camera"))


def test_a_read_back_calibration_linearises_its_joint_problem_once(
    correlated, tmp_path, monkeypatch
):
    """Its `fit_diagnostics` (every call: the file keeps no JᵀJ), the correlated-centres
    covariance and `measure`'s group covariance share one Jacobian of the joint residuals
    per solve (`_calcov.joint_linearisation`); they computed it on every call."""
    from scheimflux.calibration import (
        length_uncertainty,
        point_uncertainty,
        read_calibration,
        write_calibration,
    )
    from scheimflux.calibration.trust import _calcov  # private: the cache is the invariant
    from scheimflux.metrology import group_covariance

    cal, obs = correlated
    write_calibration(tmp_path / "cal.json", cal)
    loaded = read_calibration(tmp_path / "cal.json", observations=obs)
    calls = []
    real = _calcov.linearised
    monkeypatch.setattr(_calcov, "linearised", lambda *a, **k: calls.append(1) or real(*a, **k))
    first = fit_diagnostics(loaded)
    uv = np.concatenate([v.stripe_px for v in obs.views])[:20]
    point_uncertainty(loaded, uv)
    length_uncertainty(loaded, uv[:10], uv[10:])
    again = fit_diagnostics(loaded)
    group_covariance(loaded)
    assert len(calls) == 1
    np.testing.assert_array_equal(again.covariance, first.covariance)
    r, J, gains = _calcov.joint_linearisation(loaded)
    assert not (r.flags.writeable or J.flags.writeable or gains.flags.writeable)
