"""Measure from files: a points file from `reconstruct`, or a calibration and stripes.

What `scheimflux measure` does, as a library function a notebook can call too.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ._gum import Measurement, measure_points
from ._labels import label_steps
from ._shapes import DEGENERATE_RTOL, Cylinder, Distance, Plane, Sphere, Steps

__all__ = ["SHAPES", "make_shape", "measure_files", "read_points"]

SHAPES = ("cylinder", "plane", "sphere", "circle", "steps", "distance")
# shapes whose points must spread in 3-D: camera-frame stripe points (one laser plane) cannot
_NEEDS_3D = ("cylinder", "sphere")


def read_points(path: str | os.PathLike) -> tuple[np.ndarray, str | None]:
    """Valid points of a `reconstruct` output file: `(points (N, 3), frame or None)`.

    `.json` (`scheimflux.points/1`: the frame is recorded), `.ply`, `.npy` (NaN rows, the
    invalid points and padding, are left out; no frame recorded).
    """
    from ..io._pointcloud import POINTS_FORMAT, read_ply

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    frame = None
    if ext == ".json":
        try:
            with open(path, encoding="utf-8") as fh:
                doc = json.load(fh)
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ValueError(f"{path}: not a readable JSON points file ({err})") from None
        except RecursionError:
            raise ValueError(
                f"{path}: not a points file (JSON nested too deeply to read)"
            ) from None
        if not isinstance(doc, dict) or doc.get("format") != POINTS_FORMAT:
            raise ValueError(f"{path}: not a {POINTS_FORMAT} file")
        frame = doc.get("frame")
        try:
            frames = [np.asarray(f, dtype=np.float64).reshape(-1, 3) for f in doc["frames"]]
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{path}: 'frames' must be lists of [x, y, z]") from None
        pts = np.concatenate([np.zeros((0, 3))] + frames)
    elif ext == ".ply":
        pts = read_ply(path)
    elif ext == ".npy":
        try:
            pts = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise ValueError(f"{path}: not a readable .npy file ({err})") from None
        if pts.ndim < 2 or pts.shape[-1] != 3:
            raise ValueError(f"{path}: expected points of shape (..., 3), got {pts.shape}")
        if np.issubdtype(pts.dtype, np.floating) and pts.dtype.itemsize < 4:
            # as the library refuses them (`_checks.as_points`): float16 holds 150 mm to
            # ~0.06 mm, the precision is already lost
            raise ValueError(
                f"{path}: points are {pts.dtype.name}, too coarse for metrology; "
                "write them as float32 or float64"
            )
        pts = pts.reshape(-1, 3).astype(np.float64)
        pts = pts[~np.isnan(pts).any(axis=1)]
    else:
        raise ValueError(f"{path}: unknown points file type {ext!r} (.json, .ply or .npy)")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: points contain infinite values")
    return pts, frame


def _read_labels(path: str, n: int) -> np.ndarray:
    ext = os.path.splitext(path)[1].lower()
    try:
        if ext == ".npy":
            lab = np.load(path, allow_pickle=False)
        else:
            with open(path, encoding="utf-8") as fh:
                lab = np.asarray(json.load(fh))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such labels file") from None
    except (OSError, ValueError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable labels file ({err})") from None
    except RecursionError:
        raise ValueError(f"{path}: not a labels file (JSON nested too deeply to read)") from None
    lab = np.ravel(lab)
    if lab.shape != (n,) or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"{path}: expected {n} integer labels (one per valid point)")
    return lab.astype(np.int32)


def make_shape(kind: str, points, *, n_faces: int = 2, distance=(0, 1)):
    """The shape model for `kind` (one of `SHAPES`); for steps, lines (a single profile:
    every point in one plane, as camera-frame stripe points) or planes (a scan)."""
    from ._shapes import Circle

    if kind == "steps":
        X = np.asarray(points, dtype=np.float64)
        s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False) if len(X) >= 3 else [1, 0, 0]
        flat = s[0] == 0 or s[2] <= DEGENERATE_RTOL * s[0]
        return Steps(n_faces=int(n_faces), model="lines" if flat else "planes")
    if kind == "distance":
        return Distance(i=int(distance[0]), j=int(distance[1]))
    table = {"cylinder": Cylinder, "plane": Plane, "sphere": Sphere, "circle": Circle}
    if kind not in table:
        raise ValueError(f"unknown shape {kind!r} (one of {', '.join(SHAPES)})")
    return table[kind]()


def measure_files(
    kind: str,
    *,
    points: str | None = None,
    calibration: str | None = None,
    stripes: str | None = None,
    observations: str | None = None,
    frame: str | None = None,
    labels: str | None = None,
    n_faces: int = 2,
    distance=(0, 1),
    sigma_px: float | None = None,
    frozen_sigma="nominal",
) -> Measurement:
    """Measure `kind` from a points file, or from a calibration and a stripes file.

    **Arguments:**
    - `points`: a `reconstruct` output (budget: fit residual only).
    - `calibration`, `stripes`, `observations`: CAL.json, STRIPES.json and the
      observations the calibration was computed from (needed for its covariance).
    - `frame`: `"camera"` or `"measurement"`; with `points`, the frame the file must be in
      (checked when it records one); with stripes, the frame to reconstruct in (default
      camera; measurement turns frame i of STRIPES by i × Δω).
    - `labels`: a `.json`/`.npy` file of one integer face per point (steps); default: found
      by [`label_steps`][] with `n_faces`.
    - `distance`: the two point indices for `kind="distance"`.
    - `sigma_px`: stripe noise (px) for the stripe-noise term (stripes only).
    - `frozen_sigma`: σ of the held parameters (stripes only; see `measure_stripes`).

    **Returns:** a [`Measurement`][]. **Raises:** `ValueError` / `FileNotFoundError` with
    a one-line reason.
    """
    if kind not in SHAPES:
        raise ValueError(f"unknown shape {kind!r} (one of {', '.join(SHAPES)})")
    if frame not in (None, "camera", "measurement"):
        raise ValueError(f"frame must be 'camera' or 'measurement', got {frame!r}")
    if (points is None) == (calibration is None and stripes is None):
        raise ValueError("give either POINTS or --calibration CAL with --stripes STRIPES")
    if points is not None:
        X, file_frame = read_points(points)
        if frame is not None and file_frame is not None and file_frame != frame:
            raise ValueError(
                f"{points} holds {file_frame}-frame points, not {frame}-frame (wrong frame: "
                f"reconstruct with --frame {frame})"
            )
        if kind in _NEEDS_3D and file_frame == "camera":
            raise ValueError(
                f"{points} holds camera-frame points, which all lie in the laser plane: a "
                f"{kind} needs a rotary scan in the measurement frame (reconstruct --frame "
                "measurement)"
            )
        if len(X) == 0:
            raise ValueError(f"{points} holds no valid points")
        lab = _labels_for(kind, X, labels, n_faces)
        return measure_points(X, make_shape(kind, X, n_faces=n_faces, distance=distance),
                              labels=lab)
    if calibration is None or stripes is None:
        raise ValueError("measuring from stripes needs both --calibration and --stripes")
    if sigma_px is not None and sigma_px < 0:
        raise ValueError(f"--sigma-px must be >= 0, got {sigma_px}")
    return _measure_stripes_files(
        kind, calibration, stripes, observations, frame or "camera", labels, n_faces,
        distance, sigma_px, frozen_sigma,
    )


def _labels_for(kind, X, labels, n_faces):
    if kind != "steps":
        return None
    if labels is not None:
        return _read_labels(labels, len(X))
    return label_steps(X, n_faces)


def _measure_stripes_files(kind, cal_path, stripes_path, obs_path, frame, labels, n_faces,
                           distance, sigma_px, frozen_sigma="nominal"):
    from ..calibration import read_calibration
    from ..io import read_observations
    from ..io._stripes import read_stripes
    from ..reconstruct import stripe_to_camera, stripe_to_measurement
    from ._stripes import measure_stripes

    for path in (cal_path, stripes_path, obs_path):
        if path is not None and not os.path.exists(path):
            raise FileNotFoundError(f"{path}: no such file")
    if obs_path is None:
        raise ValueError(
            f"{cal_path}: a calibration file holds no parameter covariance; give the "
            "observations it was calibrated from (--observations OBS.json) for the "
            "calibration term"
        )
    obs = read_observations(obs_path)
    cal = read_calibration(cal_path, observations=obs)
    if cal.params.plane is None:
        raise ValueError(f"{cal_path} is a camera-only calibration (no laser plane)")
    if frame == "measurement" and cal.params.stage is None:
        raise ValueError(f"{cal_path} has no rotary stage: use --frame camera")
    frames = read_stripes(stripes_path)
    if not frames or sum(len(f) for f in frames) == 0:
        raise ValueError(f"{stripes_path} holds no stripe pixels")
    uv = np.concatenate(frames)
    fi = np.concatenate([np.full(len(f), i, np.float64) for i, f in enumerate(frames)])
    if frame == "measurement":
        rec = stripe_to_measurement(cal.camera, cal.params.plane, cal.params.stage, uv, fi)
    else:
        rec = stripe_to_camera(cal.camera, cal.params.plane, uv)
    ok = np.asarray(rec.status) == 0
    X = np.asarray(rec.points)[ok]
    if len(X) == 0:
        raise ValueError(f"no pixel of {stripes_path} gives a point with {cal_path}")
    lab_ok = _labels_for(kind, X, labels, n_faces)
    lab = None
    if lab_ok is not None:
        lab = np.full(len(uv), -1, np.int32)
        lab[ok] = lab_ok
    shape = make_shape(kind, X, n_faces=n_faces, distance=distance)
    return measure_stripes(
        cal, uv[ok], shape, frame=frame, frame_index=fi[ok],
        labels=None if lab is None else lab[ok], sigma_px=sigma_px, source=cal_path,
        frozen_sigma=frozen_sigma,
    )
