"""ChArUco boards and circle grids: geometry, and detection on images rendered through
the thick-lens camera (`render_target`) against the exact projected points."""

import cv2
import numpy as np
import pytest
from test_render_board import _focus_pose, _projector

import scheimflux as sf
from scheimflux.simulate._render_target import render_target
from scheimflux.targets import (
    CharucoBoard,
    Checkerboard,
    CircleGrid,
    detect_target,
    make_target,
)
from scheimflux.targets._circles import _handedness, _rows_reordered, _symmetries

CROP = (400.0, 300.0)  # an 800 x 600 crop of the 1600 x 1200 sensor keeps renders fast
SHAPE = (600, 800)
CHARUCO = CharucoBoard(8, 6, 0.2, 0.14)
GRID = CircleGrid(7, 6, 0.2, 0.08)
AGRID = CircleGrid(4, 7, 0.12, 0.08, asymmetric=True)


@pytest.fixture(scope="module")
def cam():
    return sf.paper_thick_lens()


def _view(cam, target, shift=(0.0, 0.0), **pose_kw):
    pose = _focus_pose(cam, target, **pose_kw)
    f = _projector(cam, pose, offset=(CROP[0] + shift[0], CROP[1] + shift[1]))
    return f, f(target.points_mm[:, :2])


def test_geometry_and_point_order():
    # ChArUco corner k is OpenCV's ChArUco ID k: compare with OpenCV's own board
    cb = CHARUCO.opencv_board()
    np.testing.assert_allclose(CHARUCO.points_mm, cb.getChessboardCorners(), atol=1e-6)
    assert CHARUCO.num_corners == 35
    np.testing.assert_allclose(CHARUCO.extent_mm, (0.0, 1.6, 0.0, 1.2))
    # asymmetric grid: OpenCV's calibration-sample layout ((2 i + j % 2) s, j s)
    p = AGRID.points_mm
    assert p.shape == (28, 3)
    np.testing.assert_allclose(p[4], [0.12, 0.12, 0]) and np.testing.assert_allclose(
        p[5], [0.36, 0.12, 0]
    )
    # symmetries: a rectangular symmetric grid has 4 (identity, 180°, 2 mirrors)
    dets = sorted(d for _, d in _symmetries(GRID.points_mm[:, :2]))
    assert dets == [-1.0, -1.0, 1.0, 1.0]
    square = CircleGrid(5, 5, 1.0, 0.3)
    assert len(_symmetries(square.points_mm[:, :2])) == 8


def test_bad_targets_are_refused():
    with pytest.raises(ValueError, match="DICT_4X4_50 has 50 markers but a 12x9-square board"):
        CharucoBoard(12, 9, 1.0, 0.7)
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_9X9'"):
        CharucoBoard(5, 4, 1.0, 0.7, "DICT_9X9")
    with pytest.raises(ValueError, match="marker_mm must be positive and smaller"):
        CharucoBoard(5, 4, 1.0, 1.0)
    with pytest.raises(ValueError, match="below the nearest-neighbour distance"):
        CircleGrid(4, 4, 1.0, 1.0)
    with pytest.raises(ValueError, match="target must be one of"):
        make_target("dots", "4x4", 1.0)
    with pytest.raises(ValueError, match="COLSxROWS"):
        make_target("circles", "4by4", 1.0)
    assert isinstance(make_target("checkerboard", "7x6", 0.2), Checkerboard)
    assert make_target("acircles", "4x7", 0.12).diameter_mm == 0.06


# Tolerance: OpenCV's ChArUco corners (cornerSubPix on the 8-bit image) are within
# 0.1 px on these renders, as for checkerboards (tests/test_detect.py); the renderer
# itself agrees with the analytic checkerboard renderer to one grey level. Circle centres
# (blob centroids) carry the perspective shift of a circle's centre, ~(r/Z)^2 of the
# circle's size: far below 0.05 px for 0.08 mm circles at ~160 mm.
@pytest.mark.parametrize("pose_kw", [dict(rot_deg=3.0), dict(rot_deg=30.0, tilt_deg=(25.0, -20.0))])
def test_charuco_matches_truth(cam, pose_kw):
    f, truth = _view(cam, CHARUCO, **pose_kw)
    img = render_target(CHARUCO, f, shape=SHAPE, blur_sigma_px=1.0, noise_sigma=0.01, seed=1)
    res = detect_target(img, CHARUCO)
    assert res.found and res.mask.all(), res.message
    assert np.hypot(*(res.corners_px - truth).T).max() <= 0.1


def test_charuco_partly_outside_and_colour_16bit(cam):
    # shifted so that part of the board lies beyond the left edge of the image
    f, truth = _view(cam, CHARUCO, shift=(-330.0, 0.0), rot_deg=3.0)
    inside = (truth[:, 0] > 5) & (truth[:, 0] < SHAPE[1] - 5)
    assert 8 < inside.sum() < len(truth)
    img = render_target(CHARUCO, f, shape=SHAPE, blur_sigma_px=1.0, bit_depth=16, seed=2)
    for image in (img, np.dstack([img] * 3)):
        res = detect_target(image, CHARUCO)
        assert res.found, res.message
        assert "corners seen" in res.message
        m = res.mask
        assert m.sum() >= 0.6 * inside.sum() and not m[~inside].any()
        assert np.hypot(*(res.corners_px[m] - truth[m]).T).max() <= 0.1


def test_charuco_not_found(cam):
    f, _ = _view(cam, CHARUCO, shift=(-700.0, 0.0), rot_deg=3.0)  # almost all outside
    img = render_target(CHARUCO, f, shape=SHAPE, blur_sigma_px=1.0)
    res = detect_target(img, CHARUCO)
    assert not res.found and "needed" in res.message and np.isnan(res.corners_px).all()
    other = CharucoBoard(8, 6, 0.2, 0.14, "DICT_5X5_100")  # wrong dictionary
    f, _ = _view(cam, CHARUCO, rot_deg=3.0)
    res = detect_target(render_target(CHARUCO, f, shape=SHAPE), other)
    assert not res.found and "DICT_5X5_100" in res.message


@pytest.mark.parametrize("grid", [GRID, AGRID], ids=["symmetric", "asymmetric"])
def test_circle_grid_matches_truth(cam, grid):
    # rot 183°: the lens inverts the image, so the board appears upright and point 0
    # (top-left on the printed board) is nearest the image's top-left: the documented
    # order is the truth's order
    f, truth = _view(cam, grid, rot_deg=183.0)
    img = render_target(grid, f, shape=SHAPE, blur_sigma_px=1.0, noise_sigma=0.01, seed=3)
    res = detect_target(img, grid)
    assert res.found, res.message
    assert np.hypot(*(res.corners_px - truth).T).max() <= 0.05
    # light circles on a dark board: found with polarity "auto"
    light = detect_target(255 - img, grid)
    assert light.found and np.hypot(*(light.corners_px - truth).T).max() <= 0.05


@pytest.mark.parametrize("grid", [GRID, AGRID], ids=["symmetric", "asymmetric"])
def test_circle_diameters_are_measured_in_the_image(cam, grid):
    # the printed diameter from each dot's area over the local area scale: blurred,
    # noisy, tilted, dark or light dots; rendered dots 18-27 px across, so a one-pixel
    # error of the area's rim would be ~5-8 %: the median is asserted within 2 %
    from scheimflux.targets import circle_diameters_mm

    f, truth = _view(cam, grid, rot_deg=183.0, tilt_deg=(20.0, 0.0))
    img = render_target(grid, f, shape=SHAPE, blur_sigma_px=1.0, noise_sigma=0.01, seed=3)
    for im in (img, 255 - img):
        d = circle_diameters_mm(im, grid, truth)
        assert np.isfinite(d).sum() >= 0.9 * grid.num_corners
        assert abs(np.nanmedian(d) / grid.diameter_mm - 1) < 0.02, np.nanmedian(d)
    nan = truth.copy()
    nan[0] = np.nan
    assert np.isnan(circle_diameters_mm(img, grid, nan)[0])  # not detected: not measured


def test_circle_grid_order_rule(cam):
    # turned so that the truth's point 0 is not nearest the top-left: the detection
    # returns the same circles relabelled by a proper symmetry of the grid
    f, truth = _view(cam, GRID, rot_deg=30.0, tilt_deg=(25.0, -20.0))
    img = render_target(GRID, f, shape=SHAPE, blur_sigma_px=1.0, seed=4)
    res = detect_target(img, GRID)
    assert res.found and "nearest the image's top-left" in res.message
    matches = []
    for perm, det in _symmetries(GRID.points_mm[:, :2]):
        relabelled = np.empty_like(truth)
        relabelled[perm] = truth
        err = np.hypot(*(res.corners_px - relabelled).T).max()
        matches.append((err, det, relabelled))
    err, det, relabelled = min(matches, key=lambda t: t[0])
    assert err <= 0.05 and det == 1.0  # a rotation, never a mirror
    proper = [m[2] for m in matches if m[1] == 1.0]
    nearest = min(np.hypot(*p[0]) for p in proper)
    assert np.hypot(*res.corners_px[0]) == pytest.approx(nearest, abs=0.1)
    mirrored = detect_target(img[:, ::-1], GRID, mirrored=True)
    assert mirrored.found


# A board → pixel homography under which OpenCV 4's `findCirclesGrid` returns the right
# rows of an 11 x 8 asymmetric grid in the wrong order (pairs of rows, the pairs taken in
# reverse): the first view of an 8 mm Tessar at x0.5 with its sensor tilted 22 degrees
# (`scheimflux simulate --lens tessar --magnification 0.5 --target acircles`), where
# every view of a capture was refused before the rows were re-ordered.
STEEP_H = np.array(
    [
        [119.7568, 38.40234, 520.2193],
        [-2.505639, 141.4379, 247.0355],
        [-5.147006e-3, 3.902186e-2, 1.0],
    ]
)
STEEP_GRID = CircleGrid(11, 8, 0.394, 0.197, asymmetric=True)


def _homography_map(H):
    return lambda xy: cv2.perspectiveTransform(np.asarray(xy, np.float64)[None], H)[0]


def test_circle_grid_rows_opencv_misorders_are_reordered():
    f = _homography_map(STEEP_H)
    img = render_target(STEEP_GRID, f, shape=(1200, 1600), blur_sigma_px=1.0, seed=7)
    xy = STEEP_GRID.points_mm[:, :2]
    res = detect_target(img, STEEP_GRID)
    assert res.found, res.message
    # truth independent of the detector: the centroid of each dot's image (an ellipse
    # under a homography), from its outline mapped at 256 points (polygon centroid)
    t = np.linspace(0.0, 2 * np.pi, 256, endpoint=False)
    ring = 0.5 * STEEP_GRID.diameter_mm * np.stack([np.cos(t), np.sin(t)], axis=1)
    truth = []
    for c in xy:
        p = f(c + ring)
        q = np.roll(p, -1, axis=0)
        cross = p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]
        truth.append(((p + q) * cross[:, None]).sum(0) / (3.0 * cross.sum()))
    truth = np.asarray(truth)
    best = min(
        (np.hypot(*(res.corners_px[perm] - truth).T).max() for perm, d in _symmetries(xy)
         if d == 1.0),
    )  # fmt: skip
    # blob centres on a blurred 8-bit render: within 0.05 px of the centroids (the
    # circle-grid tolerance of test_circle_grid_matches_truth); the centres' own images
    # are 0.1-0.2 px away here, so this also says the points are centroids
    assert best < 0.05, best
    # the repair itself: OpenCV's rows in its wrong order (pairs reversed) come back in
    # the grid's order, and an order that is wrong within the rows is not "repaired"
    right = f(xy)
    rows = right.reshape(8, 11, 2)
    wrong = rows[[6, 7, 4, 5, 2, 3, 0, 1]].reshape(-1, 2)
    assert _handedness(xy, wrong)[1] > 10.0
    fixed, _, worst = _rows_reordered(xy, wrong, STEEP_GRID.pattern_size)
    assert worst < 1e-3 and np.allclose(fixed, right)  # (the homography refit: ~1e-5 px)
    scrambled = rows[:, np.random.default_rng(0).permutation(11)].reshape(-1, 2)
    assert _rows_reordered(xy, scrambled, STEEP_GRID.pattern_size)[2] > 10.0


def test_circle_grid_not_found(cam):
    res = detect_target(np.full(SHAPE, 200, np.uint8), GRID)
    assert not res.found and "blank" in res.message
    f, _ = _view(cam, GRID, shift=(-300.0, 0.0), rot_deg=183.0)
    res = detect_target(render_target(GRID, f, shape=SHAPE, blur_sigma_px=1.0), GRID)
    assert not res.found and "no 7x6 circle grid found" in res.message


def test_formats_round_trip(cam, tmp_path):
    """PNG (8/16-bit), JPEG, TIFF and BMP, grey and colour, read back and detected."""
    from scheimflux.capture import read_image

    f, truth = _view(cam, CHARUCO, rot_deg=3.0)
    img16 = render_target(CHARUCO, f, shape=SHAPE, blur_sigma_px=1.0, bit_depth=16)
    img8 = (img16 >> 8).astype(np.uint8)
    cases = {
        "a.png": img16, "b.tif": img16, "c.bmp": img8, "d.jpg": img8,
        "e.png": np.dstack([img8] * 3), "f.jpeg": np.dstack([img8] * 3),
    }  # fmt: skip
    for name, img in cases.items():
        assert cv2.imwrite(str(tmp_path / name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        back = read_image(str(tmp_path / name))
        assert back.shape == img.shape and back.dtype == img.dtype, name
        res = detect_target(back, CHARUCO)
        # JPEG at quality 95 moves corners by a few hundredths of a pixel
        assert res.found and np.hypot(*(res.corners_px - truth).T).max() <= 0.15, name
