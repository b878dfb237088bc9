"""The rotary-table axis from RENDERED images, through the command line: board views and a
ChArUco target lying on the table, rendered through the ray tracer (the simulator's lens,
never the model under test), `scheimflux detect` (board views + `--stage-target DIR
--delta-omega-deg D`), `scheimflux calibrate`, then the calibrated axis and lengths
between points seen in different table frames against the renderer's truth.

Scene: the paper rig (×1.5); 15 board views of a 12 × 9-square ChArUco board (0.3 mm
squares), each with its laser-line image (the `pair` layout); a 44 × 44-square ChArUco
board (1 mm squares, 968 markers of DICT_4X4_1000) lying printed side up on the table,
2.2 mm off the axis, at 12 table steps × 30°, each step one image with the laser line on
the target and one with the laser off (`step_<k>.png`, `step_<k>_off.png`). The field
sees 4.7 × 3.5 mm of the laser plane 17.5 mm from the axis: ≈ 40 of the table target's
corners per step, of which OpenCV finds those whose two markers are whole (16–21).

Measured (load 14–15 on 2 cores): render 470 s, detect 119 s, calibrate 444 s (the joint
solve 206 s); see docs/stage.md for the numbers.
"""

import math
import os
import time

import numpy as np
import pytest
from test_stage_table_calibration import axis_errors

from scheimflux.calibration import read_calibration
from scheimflux.cli._main import main
from scheimflux.io import read_observations
from scheimflux.simulate import (
    default_stage,
    lying_target_pose,
    paper_rig,
    simulate_observations,
    stage_target_scan,
    write_scene_images,
    write_stage_target_images,
)
from scheimflux.simulate._observe import nominal_of
from scheimflux.targets import CharucoBoard

pytestmark = pytest.mark.slow

DW_DEG = 30.0
DICT = "DICT_4X4_1000"


def render_session(root, *, seed=4, n_views=15, n_steps=12, wobble_mrad=0.0, runout_um=0.0):
    """Render the board views (`root/images`) and the table steps (`root/table`);
    returns `(rig, true stage, table scan)`."""
    rig = paper_rig(refine=False)
    board = CharucoBoard(12, 9, 0.3, 0.21, DICT)
    _, truth = simulate_observations(
        rig, board, n_views=n_views, stage_scan=False, seed=seed, corner_noise_px=0.0,
        stripe_noise_px=0.0,
    )  # fmt: skip
    write_scene_images(root / "images", rig, board, truth, layout="pair", seed=seed)
    stage = default_stage(rig, delta_omega=math.radians(DW_DEG))
    table = CharucoBoard(44, 44, 1.0, 0.7, DICT)
    scan = stage_target_scan(
        rig, stage, table, n_steps,
        T_t_b=lying_target_pose(rig, stage, table, offset_mm=(2.0, -1.0)),
        wobble_mrad=wobble_mrad, runout_um=runout_um, seed=seed,
    )  # fmt: skip
    write_stage_target_images(root / "table", rig, scan, seed=seed + 1)
    return rig, stage, scan


def detect_argv(rig, root, out):
    nom = nominal_of(rig)
    return [
        "detect", str(root / "images"), "--target", "charuco", "--board", "12x9",
        "--square-mm", "0.3", "--dictionary", DICT, "--out", str(out),
        "--pixel-pitch-mm", str(float(rig.dx)), str(float(rig.dy)),
        "--focal-length-mm", str(nom.focal_length_mm), "--magnification",
        str(nom.magnification), "--tilt-deg", *(str(a) for a in nom.tilt_deg),
        "--stage-target", str(root / "table"), "--delta-omega-deg", str(DW_DEG),
        "--stage-target-board", "44x44", "--stage-target-square-mm", "1.0",
    ]  # fmt: skip


def run_session(root, **kw):
    """Render, detect and calibrate through the CLI; `(rig, stage, scan, obs, cal, times)`."""
    times = {}
    t0 = time.perf_counter()
    rig, stage, scan = render_session(root, **kw)
    times["render"] = time.perf_counter() - t0
    obs_path, cal_path = root / "obs.json", root / "cal.json"
    t0 = time.perf_counter()
    assert main(detect_argv(rig, root, obs_path)) == 0
    times["detect"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    assert main(["calibrate", str(obs_path), "--out", str(cal_path)]) == 0
    times["calibrate"] = time.perf_counter() - t0
    obs = read_observations(obs_path)
    cal = read_calibration(cal_path, observations=obs)
    return rig, stage, scan, obs, cal, times


def table_corner_errors(obs, scan):
    """Detected table-target corners minus the renderer's exact ones (px), all steps."""
    st = obs.stage_target
    errs = []
    for k, step in enumerate(st.table_steps):
        px = np.asarray(st.corners_px[k])
        m = np.isfinite(px).all(axis=1)
        errs.append(np.linalg.norm(px[m] - scan.views[int(step)].px_true[m], axis=1))
    return np.concatenate(errs)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return run_session(tmp_path_factory.mktemp("table_render"))


def test_rendered_table_target_recovers_the_axis(session):
    rig, stage, scan, obs, cal, times = session
    st = obs.stage_target
    # every step found (≈ 20 corners each: the ones whose two markers are whole)
    np.testing.assert_array_equal(st.table_steps, np.arange(12))
    e = table_corner_errors(obs, scan)
    ang, pos, across = axis_errors(rig, stage, cal.camera, cal.plane, cal.stage)
    rms = float(np.sqrt(np.mean(across**2)))
    print(
        f"\ntimes {times}\ntable corners {len(e)}: RMS {np.sqrt(np.mean(e**2)):.4f} px, "
        f"max {e.max():.4f} px; line points {sum(len(p) for p in st.stripe_px)}\n"
        f"reprojection {cal.reprojection_rms_px:.4f} px, table target "
        f"{cal.diagnostics['table_target']['rms_px']:.4f} px\n"
        f"axis direction {ang * 1e3:.4f} mrad, position {pos * 1e3:.3f} um, across-frame "
        f"RMS {rms * 1e3:.3f} um (max {np.abs(across).max() * 1e3:.3f} um)\n"
        f"predicted {cal.diagnostics['stage_axis']}"
    )
    # detection on the renders: the pair layout's ChArUco tolerance (0.1 px max);
    # measured 222 corners, RMS 0.024 px, max 0.055 px
    assert e.max() < 0.1
    # the targets; measured 0.0056 mrad, 0.20 µm, 0.024 µm RMS (max 0.072 µm)
    assert ang < 0.2e-3
    assert pos < 5e-3
    assert rms < 1e-3
    # the boards and the table target fit at the renders' corner noise (measured 0.0245
    # and 0.0166 px; the corner errors against the truth above are 0.024 px RMS)
    assert cal.reprojection_rms_px < 0.035
    assert cal.diagnostics["table_target"]["rms_px"] < 0.035


if __name__ == "__main__":  # a measurement run: python tests/test_stage_table_render.py DIR
    import pathlib
    import sys

    root = pathlib.Path(sys.argv[1])
    os.makedirs(root, exist_ok=True)
    kw = dict(a.split("=") for a in sys.argv[2:])
    kw = {k: float(v) if "." in v else int(v) for k, v in kw.items()}
    s = run_session(root, **kw)
    test_rendered_table_target_recovers_the_axis(s)
