"""Checkerboard detection on rendered images with known corners, and `scheimflux detect`."""

import json

import cv2
import numpy as np
import pytest
from test_render_board import _focus_pose, _projector

import scheimflux as sf
from scheimflux.cli._main import main
from scheimflux.io._observations import read_observations
from scheimflux.simulate._render_board import render_checkerboard
from scheimflux.targets._board import Checkerboard
from scheimflux.targets._detect import detect_checkerboard

# a 800 x 600 crop of the paper's 1600 x 1200 sensor around the optical axis keeps the
# tests fast; one test uses the full sensor
CROP = (400.0, 300.0)
SMALL = Checkerboard(7, 6, 0.2)


@pytest.fixture(scope="module")
def cam():
    return sf.paper_thick_lens()


def _render(cam, board, *, shape=(600, 800), offset=CROP, shift=(0.0, 0.0), **pose_kw):
    pose = _focus_pose(cam, board, **pose_kw)
    f = _projector(cam, pose, offset=(offset[0] + shift[0], offset[1] + shift[1]))
    return f, f(board.points_mm[:, :2])


@pytest.mark.parametrize(
    "pose_kw",
    [
        dict(rot_deg=3.0),  # the lens inverts: corner 0 bottom-right in the image
        dict(rot_deg=183.0),  # board upside down: corner 0 top-left in the image
        dict(rot_deg=30.0, tilt_deg=(25.0, -20.0)),  # tilted out of the focus plane
    ],
)
def test_corners_match_truth(cam, pose_kw):
    f, truth = _render(cam, SMALL, **pose_kw)
    img = render_checkerboard(
        SMALL, f, shape=(600, 800), blur_sigma_px=1.2, noise_sigma=0.01, seed=1
    )
    res = detect_checkerboard(img, SMALL)
    assert res.found, res.message
    err = np.hypot(*(res.corners_px - truth).T)
    assert err.max() <= 0.1, err.max()  # also proves the order: a swap would be > 10 px


def test_full_sensor_12bit_tilted(cam):
    board = Checkerboard(11, 8, 0.3)
    f, truth = _render(
        cam, board, shape=(1200, 1600), offset=(0.0, 0.0), rot_deg=-15.0, tilt_deg=(-20.0, 15.0)
    )
    img = render_checkerboard(
        board, f, blur_sigma_px=1.5, noise_sigma=0.01, seed=2, bit_depth=12, vignetting=0.2
    )
    assert img.dtype == np.uint16 and img.max() < 4096
    res = detect_checkerboard(img, board)
    assert res.found, res.message
    assert np.hypot(*(res.corners_px - truth).T).max() <= 0.1


def test_bit_depths_and_refine_off(cam):
    f, truth = _render(cam, SMALL, rot_deg=10.0)
    img16 = render_checkerboard(SMALL, f, shape=(600, 800), blur_sigma_px=1.0, bit_depth=16)
    images = {
        "16-bit": img16,
        "8-bit": (img16 >> 8).astype(np.uint8),
        "float": img16.astype(np.float64) / 65535,
        "colour": np.dstack([(img16 >> 8).astype(np.uint8)] * 3),
    }
    for name, img in images.items():
        res = detect_checkerboard(img, SMALL)
        assert res.found, name
        assert np.hypot(*(res.corners_px - truth).T).max() <= 0.1, name
    res = detect_checkerboard(img16, SMALL, refine=False)  # findChessboardCornersSB alone
    assert res.found
    assert np.hypot(*(res.corners_px - truth).T).max() <= 0.5


def test_board_partly_outside_is_not_found(cam):
    f, _ = _render(cam, SMALL, shift=(-300.0, 0.0), rot_deg=5.0)
    img = render_checkerboard(SMALL, f, shape=(600, 800), blur_sigma_px=1.0)
    res = detect_checkerboard(img, SMALL)
    assert not res.found
    assert "7x6" in res.message
    assert res.corners_px.shape == (42, 2) and np.all(np.isnan(res.corners_px))
    blank = detect_checkerboard(np.full((600, 800), 7, np.uint8), SMALL)
    assert not blank.found and "blank" in blank.message


def test_mirrored_image(cam):
    f, truth = _render(cam, SMALL, rot_deg=10.0)
    img = render_checkerboard(SMALL, f, shape=(600, 800), blur_sigma_px=1.0)
    res = detect_checkerboard(img[:, ::-1], SMALL, mirrored=True)
    assert res.found
    truth_m = truth.copy()
    truth_m[:, 0] = 799 - truth_m[:, 0]
    assert np.hypot(*(res.corners_px - truth_m).T).max() <= 0.1


def test_cli_detect(tmp_path, cam, capsys):
    from scheimflux.simulate._render_stripe import render_stripe

    images, scan = tmp_path / "images", tmp_path / "scan"
    images.mkdir()
    scan.mkdir()
    truths = []
    for k, rot in ((0, 3.0), (1, 183.0)):
        f, truth = _render(cam, SMALL, rot_deg=rot)
        truths.append(truth)
        img = render_checkerboard(SMALL, f, shape=(600, 800), blur_sigma_px=1.0, seed=k)
        cv2.imwrite(str(images / f"view_{k}_board.png"), img)
    stripe, _ = render_stripe((600, 800), width_px=5.0, seed=0)
    cv2.imwrite(str(images / "view_0_stripe.png"), stripe)
    # view 1 has no stripe image; view 2's board image is corrupt; view 10 has no board
    (images / "view_2_board.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    cv2.imwrite(str(images / "view_2_stripe.png"), stripe)
    cv2.imwrite(str(images / "view_10_board.png"), np.full((600, 800), 128, np.uint8))
    (images / "notes.txt").write_text("hello")
    for i in range(3):
        cv2.imwrite(str(scan / f"frame{i}.png"), stripe)
    out = tmp_path / "obs.json"
    argv = [
        "detect", str(images), "--board", "7x6", "--square-mm", "0.2", "--out", str(out),
        "--focal-length-mm", "97", "--magnification", "1.5", "--tilt-deg", "0", "13",
        "--scan", str(scan), "--delta-omega-deg", "10", "--gauge-radius-mm", "17.5",
        "--stripe-width-px", "5",
    ]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "view_2_board.png" in err  # the corrupt file is named
    assert "view_10_board.png" in err and "not found" in err
    assert "view 1" in err and "no stripe image" in err

    obs = read_observations(out)
    assert (obs.width, obs.height) == (800, 600)
    assert obs.pixel_pitch_mm == (0.0044, 0.0044)
    assert obs.nominal.magnification == 1.5 and obs.nominal.tilt_deg == (0.0, 13.0)
    np.testing.assert_allclose(obs.board_points_mm, SMALL.points_mm)
    assert len(obs.views) == 3  # views 0, 1 and 10 (view 2 skipped)
    for view, truth in zip(obs.views[:2], truths):
        assert np.hypot(*(view.corners_px - truth).T).max() <= 0.1
    assert not obs.views[2].corner_mask.any()
    assert len(obs.views[0].stripe_px) > 700 and len(obs.views[1].stripe_px) == 0
    assert len(obs.stage.frames) == 3 and obs.stage.gauge_radius_mm == 17.5
    assert json.loads(out.read_text())["views"][2]["corners_px"][0] is None

    # refuses to overwrite; then a different sensor size is an error naming the file
    assert main(argv) == 1
    assert "exists" in capsys.readouterr().err
    cv2.imwrite(str(images / "view_3_board.png"), np.zeros((100, 100), np.uint8))
    assert main(argv + ["--overwrite"]) == 1
    assert "view_3_board.png is 100x100 px" in capsys.readouterr().err


def test_cli_detect_nothing_found(tmp_path, capsys):
    (tmp_path / "im").mkdir()
    cv2.imwrite(str(tmp_path / "im" / "view_0_board.png"), np.zeros((64, 64), np.uint8))
    argv = ["detect", str(tmp_path / "im"), "--board", "7x6", "--square-mm", "0.2"]
    assert main(argv + ["--out", str(tmp_path / "o.json")]) == 1
    assert "no checkerboard 7x6 found" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()
    assert main(argv + ["--out", str(tmp_path / "o.json"), "--scan", str(tmp_path)]) == 1
    assert "--delta-omega-deg" in capsys.readouterr().err
