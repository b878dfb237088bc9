"""Side by side with OpenCV: `cv2.calibrateCamera` on the same corners.

OpenCV's model is a pinhole with distortion in the normalised image plane and, with
`CALIB_TILTED_MODEL`, a tilted sensor (τx, τy). `compare_with_opencv` runs it plainly
(5 coefficients) and tilted (14), times it, and carries OpenCV's camera and board poses
through the laser-plane step of the paper (stripe pixels → board planes → TLS plane) so
its accuracy can be read beside scheimflux's.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time

import cv2
import numpy as np

from ...camera._opencv import OpenCVCamera
from ...geometry._transforms import Pose
from ...io._observations import Observations
from ._plane import fit_laser_plane
from ._result import Calibration

__all__ = ["compare_with_opencv", "opencv_calibrate"]

MIN_CORNERS = 6
_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)


def _opencv_views(obs: Observations):
    """Per-view object / image points of the detected corners (views with < 6 dropped)."""
    obj, img, kept, dropped = [], [], [], []
    board = np.asarray(obs.board_points_mm, dtype=np.float64)
    for i, v in enumerate(obs.views):
        m = v.corner_mask
        if m.sum() < MIN_CORNERS:
            dropped.append(i)
            continue
        obj.append(board[m].astype(np.float32).reshape(-1, 1, 3))
        img.append(
            np.asarray(v.corners_px, dtype=np.float64)[m].astype(np.float32).reshape(-1, 1, 2)
        )
        kept.append(i)
    if len(kept) < 3:
        raise ValueError(f"OpenCV needs at least 3 views with {MIN_CORNERS}+ corners")
    return obj, img, kept, dropped


def _rms_per_coordinate(obj, img, K, dist, rvecs, tvecs) -> float:
    """Reprojection RMS per coordinate (px), the definition scheimflux reports.

    (cv2.calibrateCamera's own return value is the RMS of the 2-D error length, √2 larger
    for isotropic errors.)
    """
    sq, n = 0.0, 0
    for o, p, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o.astype(np.float64), r, t, K, dist)
        e = proj.reshape(-1, 2) - p.reshape(-1, 2).astype(np.float64)
        sq += float(np.sum(e**2))
        n += e.size
    return math.sqrt(sq / n)


def _calibrate_once(obj, img, size, K, dist, flags):
    K = None if K is None else K.copy()
    dist = None if dist is None else dist.copy()
    return cv2.calibrateCamera(obj, img, size, K, dist, flags=flags, criteria=_CRITERIA)


def opencv_calibrate(
    obs: Observations, *, tilted: bool = False, repeats: int = 3, flags: int = 0
) -> dict:
    """`cv2.calibrateCamera` on the observations' detected corners.

    Plain: default flags, 5 coefficients (k1, k2, p1, p2, k3). Tilted:
    `CALIB_TILTED_MODEL` (OpenCV's 14-coefficient vector; k1, k2, p1, p2, k3, τx, τy are
    fitted, the rational and thin-prism terms stay 0 unless `flags` adds
    `CALIB_RATIONAL_MODEL | CALIB_THIN_PRISM_MODEL`), started with
    `CALIB_USE_INTRINSIC_GUESS` from the plain solution's focal lengths and the image
    centre as principal point (the plain pinhole's principal point lies far outside the
    image for a tilted sensor, which OpenCV refuses as a guess).

    **Returns:** a dict with `rms_px` (per coordinate), `rms_px_cv2` (OpenCV's return
    value), `time_s` (median of `repeats` runs; the tilted time excludes the plain
    run that initialises it), `camera_matrix`, `dist_coeffs`, `rvecs`, `tvecs`, `views`
    (indices kept) and `dropped_views`.
    """
    obj, img, kept, dropped = _opencv_views(obs)
    size = (int(obs.width), int(obs.height))
    K0 = dist0 = None
    if tilted:
        plain = _calibrate_once(obj, img, size, None, None, 0)
        K0 = np.asarray(plain[1], dtype=np.float64).copy()
        K0[0, 2], K0[1, 2] = (size[0] - 1) / 2, (size[1] - 1) / 2
        dist0 = np.zeros((14, 1))
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_TILTED_MODEL
    times = []
    for _ in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        out = _calibrate_once(obj, img, size, K0, dist0, flags)
        times.append(time.perf_counter() - t0)
    rms_cv, K, dist, rvecs, tvecs = out
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    return {
        "model": "tilted (14-coefficient vector)" if tilted else "plain (5 coefficients)",
        "rms_px": _rms_per_coordinate(obj, img, K, dist, rvecs, tvecs),
        "rms_px_cv2": float(rms_cv),
        "time_s": float(statistics.median(times)),
        "camera_matrix": np.asarray(K, dtype=np.float64),
        "dist_coeffs": dist,
        "rvecs": np.stack([np.asarray(r, dtype=np.float64).reshape(3) for r in rvecs]),
        "tvecs": np.stack([np.asarray(t, dtype=np.float64).reshape(3) for t in tvecs]),
        "views": kept,
        "dropped_views": dropped,
    }


def opencv_plane_rms_um(obs: Observations, result: dict) -> float:
    """Laser-plane TLS fit RMS (µm) with OpenCV's camera and board poses.

    Each kept view's stripe pixels are back-projected with
    `OpenCVCamera.from_opencv(K, dist)` and intersected with that board's plane
    (cv2's rvec/tvec); one plane is fitted through all points by total least squares.
    """
    cam = OpenCVCamera.from_opencv(result["camera_matrix"], result["dist_coeffs"])
    poses = Pose(result["rvecs"], result["tvecs"])
    sub = dataclasses.replace(obs, views=[obs.views[i] for i in result["views"]], stage=None)
    pf = fit_laser_plane(cam, poses, sub)
    res = pf.residuals_mm[np.isfinite(pf.residuals_mm)]
    return float(np.sqrt(np.mean(res**2)) * 1e3)


def compare_with_opencv(
    obs: Observations, cal: Calibration | None = None, *, tilted: bool = True, repeats: int = 3
) -> dict:
    """OpenCV's calibration of the same corners, beside scheimflux's (if `cal` is given).

    **Returns:** `{"opencv": {...}, "opencv_tilted": {...} (if tilted), "scheimflux":
    {...} (if cal)}`; each entry holds `rms_px` (reprojection RMS per coordinate),
    `time_s` and `plane_rms_um` (laser-plane TLS fit RMS with that camera and its
    poses). OpenCV entries also hold the camera matrix, distortion vector and poses
    (see [`opencv_calibrate`][]). scheimflux's `time_s` is the sum of its LM solves as
    recorded (compilation included on a first call).
    """
    out = {}
    runs = [("opencv", False)] + ([("opencv_tilted", True)] if tilted else [])
    for name, tilt in runs:
        res = opencv_calibrate(obs, tilted=tilt, repeats=repeats)
        try:
            res["plane_rms_um"] = opencv_plane_rms_um(obs, res)
        except ValueError:
            res["plane_rms_um"] = math.nan
        out[name] = res
    if cal is not None:
        out["scheimflux"] = {
            "model": f"{cal.model} + {cal.distortion}" + (" (joint)" if cal.joint else ""),
            "rms_px": float(cal.reprojection_rms_px),
            "plane_rms_um": float(cal.plane_rms_mm) * 1e3,
            "time_s": float(sum(f.time_s for f in cal.fits.values())),
        }
    return out
