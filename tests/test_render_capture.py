"""The realistic capture renderer: its exact centre lines and image formation, checked
independently of the extractor."""

import math

import cv2
import numpy as np
import pytest

from scheimflux.simulate import CaptureTruth, render_capture, score_stripe

SHAPE = (240, 320)
QUIET = dict(read_noise=0.0, shot_noise=0.0, blur_px=(0.0, 0.0), ambient=0.0)


def test_plain_line_truth_matches_the_image_centroid():
    # A straight line at 12 degrees on a uniform surface, no ambient, no noise, 16 bit:
    # each column's intensity centroid (a symmetric profile about the true line) must
    # equal the truth's crossing of that column. Tolerance: the 2 x 2 sub-pixel sampling
    # of the profile and the 16-bit rounding give < 0.01 px.
    img, truth = render_capture(
        shape=SHAPE, target="plain", line_angle_deg=12.0, line_offset_px=7.3, peak=0.8,
        bit_depth=16, **QUIET,
    )
    assert isinstance(truth, CaptureTruth) and img.dtype == np.uint16
    a = math.radians(12.0)
    n = np.array([-math.sin(a), math.cos(a)])
    c = np.array([(SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2]) + 7.3 * n
    # the polyline lies on the analytic line
    np.testing.assert_allclose((truth.line_px - c) @ n, 0.0, atol=1e-9)
    cols = np.arange(40, 280)
    f = img[:, cols].astype(np.float64)
    v = np.arange(SHAPE[0])[:, None]
    centroid = (f * v).sum(0) / f.sum(0)
    expect = np.interp(cols, truth.line_px[:, 0], truth.line_px[:, 1])
    np.testing.assert_allclose(centroid, expect, atol=0.01)


def test_line_is_dimmer_on_black_squares_by_the_albedo_ratio():
    # brightness = albedo x (ambient + laser): with no ambient the laser's peak on black
    # squares over that on white squares is black / white.
    img, truth = render_capture(
        shape=SHAPE, line_angle_deg=3.0, line_offset_px=11.0, black=0.2, white=0.8,
        peak=0.9, bit_depth=16, **QUIET,
    )
    u = np.rint(truth.line_px[::8, 0]).astype(int)
    v = np.rint(truth.line_px[::8, 1]).astype(int)
    peaks = np.array([img[max(vi - 4, 0) : vi + 5, ui].max() for ui, vi in zip(u, v)]) / 65535
    hi, lo = np.percentile(peaks, 90), np.percentile(peaks, 10)
    assert lo / hi == pytest.approx(0.2 / 0.8, rel=0.05)
    assert hi == pytest.approx(0.9 * 0.8, rel=0.05)


def test_colour_white_light_is_grey_and_the_laser_is_red():
    kw = dict(shape=SHAPE, colour=True, line_angle_deg=20.0, read_noise=0.0, shot_noise=0.0,
              ambient=0.3, bit_depth=16)
    on, truth = render_capture(**kw)
    off, truth_off = render_capture(laser_on=False, **kw)
    assert on.shape == SHAPE + (3,) and not truth_off.laser_on
    # white ambient light on a grey target: B = G = R in the laser-off frame
    assert np.array_equal(off[..., 0], off[..., 1]) and np.array_equal(off[..., 1], off[..., 2])
    diff = on.astype(np.float64) - off
    b, g, r = (diff[..., k].max() for k in range(3))
    assert g / r == pytest.approx(0.08, abs=0.01) and b / r == pytest.approx(0.02, abs=0.01)


def test_glints_saturate_and_keep_away_from_the_line():
    img, truth = render_capture(shape=SHAPE, glints=6, line_angle_deg=5.0, seed=3)
    assert len(truth.glints_px) == 6
    d = np.min(np.linalg.norm(truth.glints_px[:, None] - truth.line_px[None], axis=2), axis=1)
    assert np.all(d >= 6 * truth.width_px + 10)
    spots = [img[int(round(v)), int(round(u))] for u, v in truth.glints_px]
    assert np.all(np.asarray(spots) >= 250)


def test_saturated_core_flag_and_jpeg_round_trip():
    img, truth = render_capture(shape=SHAPE, target="plain", peak=1.5, white=0.9)
    assert truth.saturated.all() and img.max() == 255
    jpg, _ = render_capture(shape=SHAPE, jpeg_quality=80)
    raw, _ = render_capture(shape=SHAPE)
    assert jpg.dtype == np.uint8 and jpg.shape == raw.shape and not np.array_equal(jpg, raw)
    assert np.abs(jpg.astype(int) - raw).mean() < 3


def test_truth_is_clipped_to_the_board():
    img, truth = render_capture(shape=SHAPE, line_angle_deg=0.0, line_offset_px=9.0)
    region = truth.region_px
    u0, u1 = region[:, 0].min(), region[:, 0].max()
    assert truth.line_px[:, 0].min() >= u0 - 1 and truth.line_px[:, 0].max() <= u1 + 1
    assert truth.line_px[:, 0].min() > 10  # the board does not fill the image


def test_score_against_the_truth_itself():
    img, truth = render_capture(shape=SHAPE, target="plain", line_angle_deg=8.0)
    cols = np.arange(SHAPE[1], dtype=np.float64)
    v = np.interp(cols, truth.line_px[:, 0], truth.line_px[:, 1])
    exact = np.stack([cols, v], 1)
    s = score_stripe(exact, "vertical-scan", truth, SHAPE)
    assert s.false_rate == 0 and s.coverage == 1.0 and s.rms < 1e-6
    off = score_stripe(exact + [0.0, 2.0], "vertical-scan", truth, SHAPE)
    assert off.false_rate == 1.0 and off.coverage == 0.0
    # perpendicular distance: a 0.5 px shift along v is 0.5 cos(8 deg) px off the line
    half = score_stripe(exact + [0.0, 0.5], "vertical-scan", truth, SHAPE)
    assert abs(half.bias) == pytest.approx(0.5 * math.cos(math.radians(8.0)), rel=1e-3)
    none = score_stripe(np.zeros((0, 2)), "vertical-scan", truth, SHAPE)
    assert none.n == 0 and none.coverage == 0.0


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"target": "dots"}, "target"),
        ({"bit_depth": 12}, "bit_depth"),
        ({"bit_depth": 16, "jpeg_quality": 90}, "jpeg"),
        ({"width_px": 0.0}, "width_px"),
    ],
)
def test_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        render_capture(shape=SHAPE, **kwargs)


def test_written_png_reads_back_as_bgr():
    img, _ = render_capture(shape=SHAPE, colour=True)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    np.testing.assert_array_equal(cv2.imdecode(buf, cv2.IMREAD_UNCHANGED), img)
