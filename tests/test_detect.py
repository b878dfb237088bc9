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


@pytest.mark.parametrize("rot_deg", [3.0, 93.0, 273.0])
def test_orientation_of_a_board_that_fills_the_image(cam, rot_deg):
    """The image cropped 0.3 square beyond the outer corners: the squares diagonally
    outside them (half a square beyond) are off the image, the pattern is still found.
    Its orientation is read from every square: before, from those four only, it fell
    back on "corner 0 nearest the top-left" and reversed two of these three boards
    (corners 511 px off)."""
    f, truth = _render(cam, SMALL, rot_deg=rot_deg)
    img = render_checkerboard(
        SMALL, f, shape=(600, 800), blur_sigma_px=1.0, noise_sigma=0.01, seed=1
    )
    step = np.median(np.linalg.norm(np.diff(truth.reshape(6, 7, 2), axis=1), axis=-1))
    lo = np.floor(truth.min(axis=0) - 0.3 * step).astype(int)
    hi = np.ceil(truth.max(axis=0) + 0.3 * step).astype(int)
    res = detect_checkerboard(img[lo[1] : hi[1], lo[0] : hi[0]], SMALL)
    assert res.found and "ambiguous" not in res.message, res.message
    assert np.hypot(*(res.corners_px + lo - truth).T).max() <= 0.1


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

    # the scan folder inside the capture folder, as `simulate --images` writes it: read
    # as the scan, not listed among the names ignored
    images = tmp_path / "images"
    scan = images / "scan"
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
    # view 1 has no stripe image; view 2's board image is corrupt; view 10's board image is
    # blank (no board found); view 11 has only a stripe image
    (images / "view_2_board.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    cv2.imwrite(str(images / "view_2_stripe.png"), stripe)
    cv2.imwrite(str(images / "view_10_board.png"), np.full((600, 800), 128, np.uint8))
    cv2.imwrite(str(images / "view_11_stripe.png"), stripe)
    (images / "notes.txt").write_text("hello")
    for i in range(3):
        cv2.imwrite(str(scan / f"frame{i}.png"), stripe)
    out = tmp_path / "obs.json"
    argv = [
        "detect", str(images), "--board", "7x6", "--square-mm", "0.2", "--out", str(out),
        "--focal-length-mm", "97", "--magnification", "1.5", "--tilt-deg", "0", "13",
        "--scan", str(scan), "--delta-omega-deg", "10", "--gauge-radius-mm", "17.5",
        "--stripe-width-px", "5", "--pixel-pitch-mm", "0.0044", "0.0045",
    ]  # fmt: skip
    assert main(argv) == 0
    cap = capsys.readouterr()
    err = cap.err
    assert "view 2 (view_2_board.png, view_2_stripe.png) dropped: view_2_board.png cannot" in err
    assert "view 10 (view_10_board.png) dropped: image is blank" in err
    assert "view 11 (view_11_stripe.png) dropped: no board image" in err
    assert "view 1: no stripe image" in err
    assert "ignored 1 name(s) not like a capture" in err and "notes.txt" in err
    assert "scan/" not in err
    assert "found in 2 of 5 view(s)" in cap.out and "dropped 3 view(s)" in cap.out

    obs = read_observations(out)
    assert (obs.width, obs.height) == (800, 600)
    assert obs.pixel_pitch_mm == (0.0044, 0.0045)
    assert obs.nominal.magnification == 1.5 and obs.nominal.tilt_deg == (0.0, 13.0)
    np.testing.assert_allclose(obs.board_points_mm, SMALL.points_mm)
    assert len(obs.views) == 2  # views 0 and 1: the others are dropped, not kept empty
    for view, truth in zip(obs.views, truths):
        assert np.hypot(*(view.corners_px - truth).T).max() <= 0.1
    assert obs.views[0].source == ("view_0_board.png", "view_0_stripe.png")
    assert obs.views[1].source == ("view_1_board.png",)
    assert [d.view for d in obs.dropped] == [2, 10, 11]
    assert obs.dropped[1].images == ("view_10_board.png",)
    # the horizontal test stripe crosses the whole image; only the part on the board
    # region (board outline from the truth corners, grown by half a square) is kept
    from scheimflux.capture import board_region

    region, _ = board_region(
        truths[0], (600, 800), margin_px=0.5 * np.linalg.norm(truths[0][1] - truths[0][0]),
        board_xy_mm=SMALL.points_mm[:, :2], extent_mm=SMALL.extent_mm,
    )  # fmt: skip
    st = obs.views[0].stripe_px
    on_board = region[np.rint(st[:, 1]).astype(int), np.rint(st[:, 0]).astype(int)]
    assert on_board.mean() > 0.99 and len(st) > 0.9 * region.any(axis=0).sum()
    assert len(obs.views[1].stripe_px) == 0
    assert len(obs.stage.frames) == 3 and obs.stage.gauge_radius_mm == 17.5
    doc = json.loads(out.read_text())
    assert doc["dropped_views"][0]["reason"].startswith("view_2_board.png cannot be read")

    # refuses to overwrite; then an image or a scan frame of another size is left out,
    # named, and the rest kept
    before = out.read_bytes()
    assert main(argv) == 1
    assert "exists" in capsys.readouterr().err
    assert out.read_bytes() == before
    cv2.imwrite(str(images / "view_3_board.png"), np.zeros((100, 100), np.uint8))
    cv2.imwrite(str(scan / "frame3.png"), np.zeros((100, 100), np.uint8))
    assert main(argv + ["--overwrite"]) == 0
    err = capsys.readouterr().err
    assert ("view 3 (view_3_board.png) dropped: view_3_board.png is 100x100 px but "
            "view_0_board.png is 800x600 px (not the same sensor)") in err  # fmt: skip
    assert "scan frame frame3.png is 100x100 px" in err and "kept as an empty frame" in err
    again = read_observations(out)
    assert [d.view for d in again.dropped] == [2, 3, 10, 11] and len(again.views) == 2
    assert len(again.stage.frames) == 4 and len(again.stage.frames[3]) == 0


def test_cli_detect_nothing_found(tmp_path, capsys):
    (tmp_path / "im").mkdir()
    cv2.imwrite(str(tmp_path / "im" / "view_0_board.png"), np.zeros((64, 64), np.uint8))
    argv = ["detect", str(tmp_path / "im"), "--board", "7x6", "--square-mm", "0.2"]
    assert main(argv + ["--out", str(tmp_path / "o.json")]) == 1
    err = capsys.readouterr().err
    assert "error: no checkerboard 7x6 found in any image" in err
    assert "view 0: image is blank" in err
    assert not (tmp_path / "o.json").exists()
    assert main(argv + ["--out", str(tmp_path / "o.json"), "--scan", str(tmp_path)]) == 1
    assert "--delta-omega-deg" in capsys.readouterr().err


def test_detection_does_not_depend_on_opencvs_random_state():
    """`findChessboardCornersSB` samples with OpenCV's global random generator: on a hard
    image (a clipped line at 135 degrees across the board, the scene of
    test_stripe_capture.test_clipped_diagonal_line_on_checkerboard) it found the board
    after some earlier OpenCV calls and not after others (unseeded: 6 of 8 repeated
    calls; seeds 3, 4, 5 and 9 of 0-9 failed). Seeded attempts make the detection depend
    on the image alone: the same corners, on the truth, whatever state OpenCV was in."""
    from scheimflux.simulate import homography_map, render_capture

    shape, board = (600, 800), Checkerboard(7, 5, 0.5)
    base = homography_map(shape, board_size_mm=(5.0, 4.0), roll_deg=4.0, fill=0.8)

    def to_pixel(xy):
        return base(np.asarray(xy) + 1.0)

    on, _ = render_capture(to_pixel, shape=shape, board=board, line_angle_deg=135.0,
                           line_offset_px=13.0, peak=153.0, ambient=0.55, black=0.08,
                           white=0.85, seed=3)  # fmt: skip
    truth = to_pixel(board.points_mm[:, :2])
    found = []
    for state in (3, 4, 5, 9):  # seeds with which an unseeded search failed here
        cv2.setRNGSeed(state)
        res = detect_checkerboard(on, board)
        assert res.found, res.message
        found.append(res.corners_px)
    for uv in found[1:]:
        np.testing.assert_array_equal(uv, found[0])
    # on the renderer's corners: the line crosses some (its light pulls them), so the
    # bound is the capture's drop radius's order, not the clean board's 0.05 px
    assert np.median(np.hypot(*(found[0] - truth).T)) < 0.05


def test_dropped_views_are_summarised_by_reason():
    """The summary line names each reason once with its views (the trial's five boards
    cut by the border repeated one 120-character reason five times)."""
    from scheimflux.cli._detect import _by_reason
    from scheimflux.io._observations import DroppedView

    cut = "no 11x8 checkerboard found (the whole pattern must be visible)"
    dropped = [DroppedView(1, ("a",), cut), DroppedView(2, ("b",), "image is blank"),
               DroppedView(4, ("c",), cut)]  # fmt: skip
    assert _by_reason(dropped, "view") == f"views 1, 4: {cut}; view 2: image is blank"
    assert _by_reason(dropped[1:2], "step") == "step 2: image is blank"
