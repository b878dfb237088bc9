"""`calibrate --model opencv` against `cv2.calibrateCamera` with the same flags.

Ray-traced corners of an ordinary machine-vision camera (a double Gauss scaled to
f = 8 mm, untilted 1600 × 1200 × 4.4 µm sensor, |β| = 0.5, 0.03 px corner noise): both
calibrate the same model from the same corners; the table gives the reprojection RMS,
the largest difference of the camera matrices, the largest difference of all intrinsics in
units of OpenCV's reported σ, and the time (scheimflux: a second call, compiled; its first
call's extra time is "compile").

Run: `.venv/bin/python benchmarks/opencv_model.py [--views 15]`.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time

import cv2
import numpy as np

import scheimflux as sf
from scheimflux.calibrate import calibrate_camera, cv2_calibration_flags
from scheimflux.calibrate._calibrate import _rms_px
from scheimflux.calibrate._model import SystemParams, make_data


def _observations(n_views: int):
    base = sf.simulate.load_lens("double-gauss")
    lens = base.scaled(8.0 / float(sf.simulate.paraxial(base).efl), name="dg-f8")
    rig = sf.simulate.build_rig(
        lens.with_stop_semi_diameter(0.3), 0.5, laser_angle_deg=89.9, refine=False
    )
    obs, _ = sf.simulate.simulate_observations(
        rig, sf.Checkerboard(11, 8, 1.0), n_views=n_views, stage_scan=False, seed=3
    )
    return obs


def _cv2(obs, flags, repeats=3):
    obj = [obs.board_points_mm[v.corner_mask].astype(np.float32) for v in obs.views]
    img = [v.corners_px[v.corner_mask].astype(np.float32) for v in obs.views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 300, 1e-15)
    size = (obs.width, obs.height)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        K0, d0, cv_flags = None, None, cv2_calibration_flags(flags)
        if "tilted" in flags:
            K0 = cv2.calibrateCamera(obj, img, size, None, None, criteria=crit)[1]
            d0, cv_flags = np.zeros(14), cv_flags | cv2.CALIB_USE_INTRINSIC_GUESS
        out = cv2.calibrateCameraExtended(obj, img, size, K0, d0, flags=cv_flags, criteria=crit)
        times.append(time.perf_counter() - t0)
    rv = np.stack([np.ravel(r) for r in out[3]])
    tv = np.stack([np.ravel(t) for t in out[4]])
    return out[1], out[2].ravel(), out[5].ravel(), statistics.median(times), rv, tv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--views", type=int, default=15)
    args = ap.parse_args()
    obs = _observations(args.views)
    print(f"load average {os.getloadavg()[0]:.2f}; {args.views} views")
    print(
        "| flags | scheimflux RMS px | cv2 RMS px | max |dK| px | max |d|/σ_cv2 | time s "
        "| cv2 s | compile s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    data = make_data(dataclasses.replace(obs, stage=None))
    for flags in [(), ("tilted",), ("rational",)]:
        t0 = time.perf_counter()
        calibrate_camera(obs, model="opencv", opencv_flags=flags)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        cc = calibrate_camera(obs, model="opencv", opencv_flags=flags)
        second = time.perf_counter() - t0
        K, dist = cc.camera.to_opencv()
        K_cv, d_cv, std, t_cv, rv, tv = _cv2(obs, flags)
        n = len(d_cv)
        ours = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist[:n]])
        theirs = np.array([K_cv[0, 0], K_cv[1, 1], K_cv[0, 2], K_cv[1, 2], *d_cv])
        free = std[: 4 + n] > 0
        ratio = np.max(np.abs(ours - theirs)[free] / std[: 4 + n][free])
        cam = sf.camera.OpenCVCamera.from_opencv(K_cv, d_cv)
        rms_cv = _rms_px(SystemParams(cam, sf.Pose(rv, tv)), data)
        name = ",".join(flags) or "(default)"
        print(
            f"| {name} | {cc.reprojection_rms_px:.5f} | {rms_cv:.5f} "
            f"| {np.max(np.abs(K - K_cv)):.2e} | {ratio:.3f} | {second:.3f} | {t_cv:.3f} "
            f"| {first - second:.1f} |"
        )


if __name__ == "__main__":
    main()
