"""Export a calibration as OpenCV's camera model (`cv::FileStorage` YAML).

A camera calibrated with OpenCV's own model is written as it is. Any other central
camera (the thick-lens Scheimpflug model, the paper's pinhole with skew) is replaced by
the OpenCV model that best reproduces its pixel rays. The camera's rays through a grid
of pixels over the whole sensor meet five virtual planes (the plane of sharp focus, and
planes turned by ±20° about two axes); `cv2.calibrateCamera` fits OpenCV's model to
those virtual views; then a least-squares fit of `cv2.projectPoints` to the rays
themselves (with a free rotation between the two camera frames) removes the trade-off
between focal length and plane distance that views of a narrow-angle camera leave.

The fit's RMS and worst residual (px, over the grid) say how exact the equivalent is.
Without distortion a thick lens maps ray directions to pixels by a homography; OpenCV's
model (K without skew, the tilt τx, τy) holds every such homography without skew, up to
a rotation of the frame. A sensor tilted about both axes adds a small skew that OpenCV
cannot hold: for the paper's ×1.5 rig (φ = 2.9°, θ = 13.3°) the residual is 0.01 px RMS,
0.03 px worst. Distortion in the untilted image plane is approximated by OpenCV's
polynomial.

The equivalent's camera frame is OpenCV's (z along its own optical axis): it may be
rotated against the calibration's frame, so laser plane and stage do not carry over.
"""

from __future__ import annotations

import dataclasses
import os

import cv2
import numpy as np

__all__ = ["OpenCVFit", "opencv_equivalent", "export_opencv"]

_DISTORTION_FLAGS = {
    # name: (flags, number of coefficients that are free)
    "none": (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST),
    "k1k2p1p2k3": 0,
    "rational": cv2.CALIB_RATIONAL_MODEL,
}


@dataclasses.dataclass(frozen=True)
class OpenCVFit:
    """How well an OpenCV model reproduces a camera.

    **Fields:**
    - `rms_px`, `max_px`: reprojection RMS and worst residual on the virtual views (px).
    - `n_points`, `n_views`: virtual points and planes used.
    - `exact`: the camera was already an OpenCV model (no fit).
    - `flags`: the `cv2.calibrateCamera` flags used (0 when exact).
    """

    rms_px: float
    max_px: float
    n_points: int
    n_views: int
    exact: bool
    flags: int


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues((np.asarray(axis, np.float64) * angle).reshape(3, 1))[0]


def _virtual_views(camera, image_size, grid):
    import jax.numpy as jnp

    w, h = image_size
    gu, gv = np.meshgrid(np.linspace(0, w - 1, grid[0]), np.linspace(0, h - 1, grid[1]))
    uv = np.stack([gu.ravel(), gv.ravel()], axis=1)
    rays = camera.backproject(jnp.asarray(uv))
    d = np.asarray(rays.direction, np.float64)
    o = np.asarray(rays.origin, np.float64)
    if np.abs(o[np.all(np.isfinite(o), axis=1)]).max(initial=0.0) > 1e-9:
        raise ValueError("the camera is not central (rays do not share one origin)")
    centre = np.asarray(
        camera.backproject(jnp.asarray([[0.5 * (w - 1), 0.5 * (h - 1)]])).direction
    )[0]
    depth = 1000.0
    if hasattr(camera, "object_point"):
        depth = float(
            np.linalg.norm(np.asarray(camera.object_point(jnp.asarray(uv[len(uv) // 2]))))
        )
        n0 = np.asarray(camera.focus_plane().normal, np.float64)
    else:
        n0 = centre
    n0 = n0 / np.linalg.norm(n0)
    p0 = depth * centre
    e1 = np.cross([0.0, 1.0, 0.0], n0)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n0, e1)
    obj, img = [], []
    for axis, angle in ((e1, 0.0), (e1, 0.35), (e1, -0.35), (e2, 0.35), (e2, -0.35)):
        R = _rotation(axis, angle)
        n, a, b = R @ n0, R @ e1, R @ e2
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (n @ p0) / (d @ n)
        X = t[:, None] * d
        ok = np.all(np.isfinite(X), axis=1) & (t > 0)
        q = X[ok] - p0
        obj.append(np.stack([q @ a, q @ b, np.zeros(ok.sum())], axis=1).astype(np.float32))
        img.append(uv[ok].astype(np.float32))
    d_all = d[np.all(np.isfinite(d), axis=1)]
    uv_all = uv[np.all(np.isfinite(d), axis=1)]
    return obj, img, d_all, uv_all


def opencv_equivalent(
    camera,
    image_size: tuple[int, int],
    *,
    distortion: str | None = None,
    tilt: bool | None = None,
    grid: tuple[int, int] = (17, 13),
):
    """The OpenCV camera model equivalent to `camera`, and how well it fits.

    **Arguments:**
    - `camera`: an `OpenCVCamera` (returned as it is), or any central camera with
      `backproject` (`ThickLensScheimpflug`, `Pinhole`).
    - `image_size`: `(width, height)` px.
    - `distortion`: `"none"`, `"k1k2p1p2k3"` or `"rational"` (k1–k6); default
      `"k1k2p1p2k3"` for a camera with distortion, `"none"` otherwise.
    - `tilt`: fit OpenCV's tilted sensor (τx, τy); default: when the camera's sensor is
      tilted (`phi` or `theta` not zero) or it has skew.
    - `grid`: pixels per row and column sampled on the sensor.

    **Returns:** `(OpenCVCamera, OpenCVFit)`.
    """
    from ..camera._distortion import NoDistortion
    from ..camera._opencv import OpenCVCamera

    if isinstance(camera, OpenCVCamera):
        return camera, OpenCVFit(0.0, 0.0, 0, 0, True, 0)
    w, h = (int(v) for v in image_size)
    distorted = not isinstance(getattr(camera, "distortion", NoDistortion()), NoDistortion)
    name = distortion or ("k1k2p1p2k3" if distorted else "none")
    if name not in _DISTORTION_FLAGS:
        raise ValueError(f"distortion must be one of {', '.join(_DISTORTION_FLAGS)}, got {name!r}")
    if tilt is None:
        tilted = abs(float(getattr(camera, "phi", 0.0))) + abs(float(getattr(camera, "theta", 0.0)))
        tilt = tilted > 0 or abs(float(getattr(camera, "gamma", 0.0))) > 0
    flags = _DISTORTION_FLAGS[name] | (cv2.CALIB_TILTED_MODEL if tilt else 0)
    if tilt:  # τx, τy live beside s1..s4: fix the thin-prism terms
        flags |= cv2.CALIB_FIX_S1_S2_S3_S4
    obj, img, d, uv = _virtual_views(camera, (w, h), grid)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    _, K, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), None, None, flags=flags, criteria=crit)
    K, dist14, R = _refine_on_rays(K, np.asarray(dist, np.float64).ravel(), d, uv, flags)
    p, _ = cv2.projectPoints((d @ R.T).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist14)
    r = np.linalg.norm(p.reshape(-1, 2) - uv, axis=1)
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist14)) and np.all(np.isfinite(r))):
        raise ValueError("the OpenCV fit did not give finite parameters")
    return OpenCVCamera.from_opencv(K, dist14), OpenCVFit(
        float(np.sqrt(np.mean(r**2))), float(r.max()), len(uv), len(obj), False, int(flags)
    )


def _free_distortion(flags: int) -> np.ndarray:
    """Indices (into OpenCV's 14 coefficients) that the flags leave free."""
    free = []
    if not flags & cv2.CALIB_FIX_K1:
        free.append(0)
    if not flags & cv2.CALIB_FIX_K2:
        free.append(1)
    if not flags & cv2.CALIB_ZERO_TANGENT_DIST:
        free += [2, 3]
    if not flags & cv2.CALIB_FIX_K3:
        free.append(4)
    if flags & cv2.CALIB_RATIONAL_MODEL:
        free += [5, 6, 7]
    if flags & cv2.CALIB_TILTED_MODEL:
        free += [12, 13]
    return np.asarray(free, int)


def opencv_rays(K: np.ndarray, dist14: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Unit ray directions of pixels `(N, 2)` under OpenCV's model (`cv2.undistortPoints`,
    iterated to 1e-14)."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    xy = cv2.undistortPoints(
        np.asarray(uv, np.float64).reshape(-1, 1, 2),
        K,
        dist14,
        R=np.eye(3),
        P=np.eye(3),
        criteria=crit,
    ).reshape(-1, 2)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _refine_on_rays(K, dist, d, uv, flags):
    """Least squares of OpenCV's projection of the camera's ray directions `d` (rotated
    by a free rotation: OpenCV's frame) against their pixels `uv`, started from the
    virtual-view fit. Views alone leave the focal length free against the distance of
    a narrow-angle camera's virtual planes; the rays fix it."""
    from scipy.optimize import least_squares

    dist14 = np.zeros(14)
    dist14[: len(dist)] = dist
    free = _free_distortion(flags)
    # the rotation from the camera's frame to OpenCV's: Kabsch on the fitted rays
    d_cv = opencv_rays(K, dist14, uv)
    ok = np.all(np.isfinite(d_cv), axis=1)
    U, _, Vt = np.linalg.svd(d_cv[ok].T @ d[ok])
    R0 = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    rvec0 = cv2.Rodrigues(R0)[0].ravel()
    x0 = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist14[free], rvec0])
    scale = np.concatenate(
        [[K[0, 0], K[1, 1], 1.0, 1.0], np.full(len(free), 0.1), np.full(3, 1e-3)]
    )
    pts = d.reshape(-1, 1, 3)

    def unpack(x):
        Kx = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
        dx = dist14.copy()
        dx[free] = x[4 : 4 + len(free)]
        return Kx, dx, x[4 + len(free) :]

    def residual(x):
        Kx, dx, rv = unpack(x)
        p, _ = cv2.projectPoints(pts, rv, np.zeros(3), Kx, dx)
        return (p.reshape(-1, 2) - uv).ravel()

    sol = least_squares(residual, x0, x_scale=scale, method="lm", xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, max_nfev=2000)  # fmt: skip
    Kx, dx, rv = unpack(sol.x)
    return Kx, dx, cv2.Rodrigues(rv)[0]


def export_opencv(
    calibration_path: str | os.PathLike,
    out_path: str | os.PathLike,
    *,
    image_size: tuple[int, int] | None = None,
    distortion: str | None = None,
    overwrite: bool = False,
):
    """Write the OpenCV YAML of a calibration file.

    **Arguments:**
    - `calibration_path`: a `scheimflux.calibration/1` file.
    - `out_path`: the `.yml`/`.yaml` (or `.xml`, `.json`) file to write.
    - `image_size`: `(width, height)`; needed unless the file records its sensor size.
    - `distortion`: the OpenCV distortion model of the fit (see `opencv_equivalent`).
    - `overwrite`: replace an existing `out_path`.

    **Returns:** `(OpenCVCamera, OpenCVFit, (width, height))`.
    """
    from ..io._calibration import read_calibration_document
    from ..io._opencv_yaml import write_opencv_yaml

    if os.path.exists(out_path) and not overwrite:
        raise FileExistsError(f"{os.fspath(out_path)} exists; pass --overwrite to replace it")
    cal = read_calibration_document(calibration_path)
    if image_size is None:
        if cal.sensor_size is not None:
            image_size = cal.sensor_size
        else:
            raise ValueError(
                f"{os.fspath(calibration_path)} does not record the image size; give "
                "--image-size WIDTH HEIGHT"
            )
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"--image-size must be two positive integers, got {image_size}")
    cam, fit = opencv_equivalent(cal.camera, (w, h), distortion=distortion)
    write_opencv_yaml(out_path, cam, (w, h), overwrite=overwrite)
    return cam, fit, (w, h)
