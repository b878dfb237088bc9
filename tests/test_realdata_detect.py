"""Target detection on real photographs (`../shared/realdata`, public captures nobody on
this project made; each folder's README states camera, target and layout) against
OpenCV's own detectors on the same images, in the same test.

The captures are linked into capture folders by `benchmarks/realdata_detect.py` (the
benchmark that prints the table in docs/capture.md); per capture:
- the library uses at least as many views as OpenCV's best detector (the classic
  `findChessboardCorners` + `cornerSubPix`, or the sector-based
  `findChessboardCornersSB`; `findCirclesGrid` for circle grids);
- its points are at least as precise: `cv2.calibrateCamera` (same model) fits them
  per view, over the views every set has, with a median RMS no worse than the best
  OpenCV set's (within `_RMS_SLACK`, below);
- every view kept has points that determine a pose (at least 6, not on one line), and a
  symmetric grid's order agrees across the views (the board's x axis within 90 degrees
  of its mean direction in the image);
- in srv-turntable-webcam's 27 laser-free board images no laser line is reported.

Skipped, with the reason, where `../shared/realdata` is absent (the images are not part
of the repository).
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from scheimflux.capture._workflow import _turns

pytestmark = pytest.mark.slow

ROOT = Path(__file__).parents[1].parent / "shared" / "realdata"
NAMES = [
    "taubin-laserplane",
    "zcy",
    "mozhi-lightplane",
    "hjamal3-greenstripe",
    "srv-turntable-webcam/laser_calib",
    "srv-turntable-webcam/camera_calib",
]

# Per-view RMS is a median over the same views of the same images, each from its own
# calibration. Measured (the benchmark): where OpenCV's two detectors differ, they differ
# by 5-29 % (taubin 0.202 / 0.213 px, srv 0.151 / 0.117 px); on mozhi's hand-held paper
# print every detector is at 0.753-0.757 px (the print's irregularity, not the
# detection). "As precise" is held to 2 % of OpenCV's best: below every detector
# difference that is not the print's, above the 0.5 % spread on mozhi.
_RMS_SLACK = 0.02


def _bench():
    path = Path(__file__).parents[1] / "benchmarks" / "realdata_detect.py"
    spec = importlib.util.spec_from_file_location("realdata_detect", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("name", NAMES)
def test_real_capture_detection(name, tmp_path):
    if not ROOT.is_dir():
        pytest.skip(f"real captures not present at {ROOT} (not part of the repository)")
    bench = _bench()
    caps = {c["name"]: c for c in bench.captures(ROOT)}
    if name not in caps:
        pytest.skip(f"{name} not present under {ROOT}")
    cap = caps[name]
    images = bench.link_folder(cap, tmp_path)
    sf = bench.run_scheimflux(cap, tmp_path)
    cv = bench.run_opencv(cap, images)
    board = np.asarray(sf["target"].points_mm, np.float64)

    # views: at least OpenCV's best detector's
    best = max(len(v) for v in cv.values())
    assert len(sf["corners"]) >= best, (len(sf["corners"]), {k: len(v) for k, v in cv.items()})

    # every view kept determines a pose: enough points, spanning the board's plane
    pitch = board[1, 0] - board[0, 0]
    for k, uv in sf["corners"].items():
        ok = np.all(np.isfinite(uv), axis=1)
        assert ok.sum() >= 6, (k, ok.sum())
        c = board[ok, :2] - board[ok, :2].mean(axis=0)
        assert np.linalg.svd(c, compute_uv=False)[-1] / math.sqrt(ok.sum()) > 0.25 * pitch, k

    # a consistent order across views where the target's looks cannot fix it (a turn
    # that leaves it looking the same: the order is the library's choice; every capture
    # here has one)
    if len(_turns(sf["target"])) > 1:
        ang = bench.x_axis_deg(sf["corners"], board)
        mean = np.degrees(np.angle(np.mean(np.exp(1j * np.radians(ang)))))
        assert np.abs((ang - mean + 180.0) % 360.0 - 180.0).max() < 90.0, ang

    # precision: calibrateCamera's per-view RMS over the views every set has
    h, w = bench.image_shape(next(iter(images.values())))
    cal = {n: bench.calibrate(p, board, (h, w))[1] for n, p in {"sf": sf["corners"], **cv}.items()}
    common = sorted(set.intersection(*(set(p) for p in cal.values())))
    assert len(common) >= 3, common
    med = {n: float(np.median([p[k] for k in common])) for n, p in cal.items()}
    best_cv = min(v for n, v in med.items() if n != "sf")
    assert med["sf"] <= best_cv * (1.0 + _RMS_SLACK), med

    # no laser line where there is none
    if cap.get("laser_free"):
        with_line = {k: n for k, n in sf["stripes"].items() if n > 0}
        assert not with_line, with_line
