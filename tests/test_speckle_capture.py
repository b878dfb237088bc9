"""A speckled laser line in a capture folder: `detect` reports its centres' scatter per
view and tells the user the stripe noise to give `calibrate`, whose default (a clean
line's) is several times smaller.

The pairs: a checkerboard rendered by `render_capture` with the laser on and off (same
room light, no noise, 16 bits), the laser light (on less off) multiplied by a lognormal
speckle field (grains of 1.5 px), then 1 grey level of read noise, 8 bits."""

import argparse

import cv2
import numpy as np
import pytest

from scheimflux.calibrate._calibrate import SIGMA_STRIPE_PX
from scheimflux.capture import detect_captures
from scheimflux.cli._main import main
from scheimflux.simulate import homography_map, render_capture
from scheimflux.targets import Checkerboard

BOARD = Checkerboard(7, 5, 0.5)
SHAPE = (600, 800)


def _write_pairs(folder, contrast):
    base = homography_map(SHAPE, board_size_mm=(5.0, 4.0), roll_deg=4.0, fill=0.8)

    def to_pixel(xy):
        return base(np.asarray(xy) + 1.0)

    for k, angle in enumerate((30.0, 150.0)):
        kw = dict(shape=SHAPE, board=BOARD, line_angle_deg=angle, line_offset_px=13.0,
                  read_noise=0.0, shot_noise=0.0, bit_depth=16, blur_px=(1.2, 1.2),
                  seed=k)  # fmt: skip
        on, _ = render_capture(to_pixel, **kw)
        off, _ = render_capture(to_pixel, **kw, laser_on=False)
        on, off = on / 257.0, off / 257.0
        rng = np.random.default_rng(k)
        z = cv2.GaussianBlur(rng.standard_normal(SHAPE), (0, 0), 1.5)
        s = np.sqrt(np.log1p(contrast**2))  # lognormal with std / mean = contrast
        on = off + (on - off) * np.exp(s * z / z.std() - 0.5 * s**2)
        for name, img in (("board", off), ("stripe", on)):
            img = np.clip(np.rint(img + rng.normal(0.0, 1.0, SHAPE)), 0, 255)
            cv2.imwrite(str(folder / f"view_{k}_{name}.png"), img.astype(np.uint8))


@pytest.mark.parametrize("contrast", [0.0, 0.6])
def test_detect_reports_a_speckled_lines_scatter(tmp_path, capsys, contrast):
    _write_pairs(tmp_path, contrast)
    obs, report = detect_captures(tmp_path, BOARD)
    assert report.kept == [0, 1] and all(len(v.stripe_px) > 300 for v in obs.views)
    if not contrast:
        assert report.speckle_px == {} and report.speckle_summary() == ""
        return
    # 0.42 and 0.48 px measured; speckle of this contrast scatters a 5 px line's centres
    # by 0.3-0.7 px (docs/stripe.md): several times the default stripe noise
    assert set(report.speckle_px) == {0, 1}
    assert all(0.2 < px < 1.0 for px in report.speckle_px.values())
    med = float(np.median(list(report.speckle_px.values())))
    assert f"--sigma-stripe-px {med:.2f}" in report.speckle_summary()
    main(["detect", str(tmp_path), "--board", "7x5", "--square-mm", "0.5",
          "--out", str(tmp_path / "obs.json")])  # fmt: skip
    assert report.speckle_summary() in capsys.readouterr().out


def test_calibrate_cli_default_stripe_noise_is_the_librarys():
    from scheimflux.cli import _calibrate

    parser = argparse.ArgumentParser()
    _calibrate.register(parser.add_subparsers())
    args = parser.parse_args(["calibrate", "obs.json", "--out", "cal.json"])
    assert args.sigma_stripe_px == SIGMA_STRIPE_PX
