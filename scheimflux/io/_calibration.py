"""The calibration file, `"format": "scheimflux.calibration/1"` (JSON).

```
{"format": "scheimflux.calibration/1",
 "model": "thick-lens",                # or "thick-lens-noncentral", "pinhole", "opencv"
 "sensor": {"width": 1600, "height": 1200},                # px
 "camera": {"f": {"value": 97.0, "unit": "mm"}, "e": {...}, "z0": {...},
            "phi": {"value": 2.87, "unit": "deg"}, "theta": {...},
            "x0": {"value": 800.1, "unit": "px"}, "y0": {...},
            "dx": {"value": 0.0044, "unit": "mm"}, "dy": {...},
            "distortion": {"model": "radial-tangential",
                           "k1": {"value": 0.0, "unit": "1"}, "k2": ..., "k3": ...,
                           "p1": ..., "p2": ...}},
 "laser_plane": {"n_per_mm": [A, B, C], "unit_normal": [nx, ny, nz], "distance_mm": d},
 "stage": {"R_m_c": [[...], [...], [...]], "t_m_c_mm": [tx, ty, tz],     # optional
           "delta_omega_deg": 10.0, "gauge_eccentricity_mm": [ex, ey]},
 "board_poses": {"rotvec": [[rx, ry, rz], ...], "translation_mm": [[tx, ty, tz], ...]},
 "table_target_pose": {"rotvec": [rx, ry, rz], "translation_mm": [tx, ty, tz]},  # optional
 "coverage": {"format": "scheimflux.coverage/1", "cell_px": 8, "margin_px": 23.6,  # optional
              "shape": [rows, cols], "fraction": 0.41, "bits": "<base64 packbits>"},
 "diagnostics": {"reprojection_rms_px": ..., "laser_plane_rms_mm": ..., "gauge_rms_mm": ...,
                 "solves": {"camera": {"steps": 12, "converged": true, "time_s": 3.1}, ...},
                 "frozen": ["camera.dx", ...], "converged": true,
                 "sigma_corner_px": 0.03, "sigma_stripe_mm": 1.4e-4, "robust": null,
                 "stripe_sigma_scale": [1.0, 4.2, ...],             # optional
                 "stripe_gain": [0.17, 0.33, ...],                  # optional
                 "field_radius_px": 900.0, ...},                    # optional
 "software": {"name": "scheimflux", "version": "0.1.0"}}
```

The non-central thick lens (`"model": "thick-lens-noncentral"`) has the thick lens's
parameters, `c1`, `c2` (mm): the entrance pupil's shift along the axis,
`c1 ρ² + c2 ρ⁴`, `ax`, `ay` (mm): the ray origin's lateral offset, and `b1`, `b2` (mm):
the origin's further shift `b1 ρ² + b2 ρ⁴` about the in-focus point (see
`ThickLensNonCentral`; files without `ax`, `ay` or `b1`, `b2` load them as 0). The
pinhole model (paper eq. 14) has `alpha`, `beta`, `gamma`, `x0`, `y0` (px) and
`"distortion": {"model": "none"}`. OpenCV's model (`"model": "opencv"`, equal to
`cv2.projectPoints`) has `fx`, `fy`, `cx`, `cy` (px), `tau_x`, `tau_y` (deg: the sensor
tilt) and `"distortion": {"model": "opencv", "k1", "k2", "p1", "p2", "k3", "k4", "k5",
"k6", "s1", "s2", "s3", "s4"}` (OpenCV's order). Distortion models of the thick lens:
`"none"`, `"radial-tangential"` (k1, k2, k3, p1, p2) and `"division"` (kappa), all
dimensionless (unit `"1"`), acting in the untilted image plane.

`coverage` (optional; files before it load with `coverage = None`, unknown) is the
sensor region the calibration data covered (`scheimflux.geometry.Coverage`,
docs/coverage.md): an occupancy grid of `cell_px` cells, which must match `sensor`.

`laser_plane` is absent in a camera-only calibration (no stripe pixels on the boards):
such a file serves OpenCV export, not reconstruction. `board_poses` (`T_c_b` of each
view: rotation vector in rad, translation in mm) and the noise weights in `diagnostics`
(and `table_target_pose`, the pose `T_t_b` of a target fixed to the rotary table, when
the stage was calibrated from one) let `scheimflux.read_calibration` rebuild the full
calibration from the observations
(`scheimflux.read_calibration(path, observations=obs)`: diagnostics, point uncertainty,
refinement).

Angles are written in degrees and read back in radians; the degree values are chosen
so that the conversion back reproduces the radians bit for bit. The laser plane is
`n · X = 1` in the camera frame; `unit_normal` and `distance_mm` are written for people
and, when present, must agree with `n_per_mm`. `R_m_c`, `t_m_c_mm` map camera to
measurement coordinates (`X_m = R_m_c X_c + t_m_c`, frame 0 of a scan).

Reading checks every key (unknown keys are refused, with the closest valid name) and
every value's range: f, z0, pixel pitch, α, β, fx, fy positive; |φ|, |θ|, |τx|, |τy|
below 90°; all numbers finite; a laser plane at least `MIN_PLANE_DISTANCE_MM` from the
projection centre; `R_m_c` a rotation. `diagnostics` and `software` are free-form.

This module only serialises: a document ⇄ a [`CalibrationDocument`][] of the file's values
(camera, plane, stage, poses, coverage, diagnostics). Turning a `Calibration` into a
document, and a document back into a `Calibration` (residuals rebuilt from the
observations), is `scheimflux.calibration`'s (`write_calibration`, `read_calibration`).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import math
import os
import warnings
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..geometry._coverage import Coverage
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ._calibration_schema import (
    _CAMERA_CLASSES,
    _DISTORTION_CLASSES,
    _MODEL_DISTORTIONS,
    _SOFTWARE_KEYS,
    _TOP_KEYS,
    CAMERA_PARAMETERS as CAMERA_PARAMETERS,
    DISTORTION_PARAMETERS as DISTORTION_PARAMETERS,
    FORMAT as FORMAT,
    MIN_PLANE_DISTANCE_MM as MIN_PLANE_DISTANCE_MM,
    ROTATION_TOLERANCE as ROTATION_TOLERANCE,
    CalibrationFileError as CalibrationFileError,
    UnconvergedCalibrationWarning as UnconvergedCalibrationWarning,
    _camera,
    _check_keys,
    _diagnostics,
    _floats,
    _plane,
    _poses,
    _require,
    _sensor,
    _stage,
    table_pose,
)
from ._files import load_json, write_json

# ----------------------------------------------------------------------------- writing


def _degrees(rad: float) -> float:
    """Degrees of `rad`, nudged by a few ulps so that `math.radians` gives `rad` back."""
    d = math.degrees(rad)
    if math.radians(d) == rad:
        return d
    up = down = d
    for _ in range(8):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        for cand in (up, down):
            if math.radians(cand) == rad:
                return cand
    return d


def _value(v, unit: str) -> dict:
    v = float(v)
    return {"value": _degrees(v) if unit == "deg" else v, "unit": unit}


def distortion_name(distortion) -> str:
    for name, cls in _DISTORTION_CLASSES.items():
        if type(distortion) is cls:
            return name
    raise ValueError(
        f"cannot store distortion {type(distortion).__name__}: the calibration file holds "
        f"{', '.join(DISTORTION_PARAMETERS)}"
    )


def camera_model(camera) -> str:
    """The file's model name of a camera (`"thick-lens"`, `"pinhole"`, `"opencv"`)."""
    for model, cls in _CAMERA_CLASSES.items():
        if isinstance(camera, cls):
            return model
    raise ValueError(
        f"cannot store a {type(camera).__name__} camera: the calibration file holds "
        f"{', '.join(CAMERA_PARAMETERS)} cameras"
    )


def camera_to_dict(camera) -> dict:
    """The `camera` section of the file for a thick-lens, pinhole or OpenCV camera."""
    model = camera_model(camera)
    doc = {name: _value(getattr(camera, name), unit) for name, unit in CAMERA_PARAMETERS[model]}
    if model == "pinhole":
        dist = {"model": "none"}
    else:
        dname = distortion_name(camera.distortion)
        if dname not in _MODEL_DISTORTIONS[model]:
            raise ValueError(f"cannot store a {model} camera with {dname} distortion")
        dist = {"model": dname}
        for p in DISTORTION_PARAMETERS[dname]:
            dist[p] = _value(getattr(camera.distortion, p), "1")
    doc["distortion"] = dist
    return doc


def plane_to_dict(plane: LaserPlane) -> dict:
    n = np.asarray(plane.n, dtype=np.float64)
    return {
        "n_per_mm": _floats(n),
        "unit_normal": _floats(n / np.linalg.norm(n)),
        "distance_mm": float(1.0 / np.linalg.norm(n)),
    }


def stage_to_dict(stage: RotaryStage, eccentricity_mm=None) -> dict:
    doc = {
        "R_m_c": _floats(stage.R_m_c),
        "t_m_c_mm": _floats(stage.t_m_c),
        "delta_omega_deg": _degrees(float(stage.delta_omega)),
    }
    if eccentricity_mm is not None:
        doc["gauge_eccentricity_mm"] = _floats(np.reshape(eccentricity_mm, (2,)))
    return doc


def pose_to_dict(pose: Pose) -> dict:
    """One pose (`table_target_pose`): rotation vector (rad) and translation (mm)."""
    return {
        "rotvec": _floats(np.asarray(pose.rotvec, dtype=np.float64)),
        "translation_mm": _floats(np.asarray(pose.translation, dtype=np.float64)),
    }


def poses_to_dict(poses: Pose) -> dict:
    rv = np.asarray(poses.rotvec, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(poses.translation, dtype=np.float64).reshape(-1, 3)
    return {"rotvec": [_floats(r) for r in rv], "translation_mm": [_floats(r) for r in t]}


def jsonable(v: Any) -> Any:
    """Diagnostics values as plain JSON types (NumPy/JAX scalars and arrays included)."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, np.integer)) and not isinstance(v, np.bool_):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    a = np.asarray(v)
    if a.dtype == bool:
        return a.tolist()
    if a.ndim == 0:
        f = float(a)
        return f if math.isfinite(f) else None
    return [jsonable(x) for x in a]


def software_version() -> str:
    try:
        return importlib.metadata.version("scheimflux")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - source checkout
        return "unknown"


# ----------------------------------------------------------------------------- reading


@dataclasses.dataclass(frozen=True)
class CalibrationDocument:
    """A validated calibration file, as values: what the file holds, nothing restored.

    **Fields:** `model` (`"thick-lens"`, …), `distortion` (its distortion model's name),
    `sensor_size` `(width, height)` px or None (not recorded), `camera`, `board_poses`
    (`Pose`, `(V, 3)` arrays; `(0, 3)` when the file holds none), `plane` and `stage`
    (None when absent), `eccentricity_mm` `(2,)` or None, `table_pose` (`Pose` or None),
    `coverage` (`Coverage` or None), `diagnostics` (a dict, as written) and `raw` (the
    whole decoded document).
    """

    model: str
    distortion: str
    sensor_size: tuple[int, int] | None
    camera: Any
    board_poses: Pose
    plane: LaserPlane | None
    stage: RotaryStage | None
    eccentricity_mm: np.ndarray | None
    table_pose: Pose | None
    coverage: Coverage | None
    diagnostics: dict
    raw: dict

    @property
    def converged(self) -> bool:
        """Whether every solve converged, as the file records it."""
        return bool(self.diagnostics.get("converged", True))


def parse_calibration_document(doc) -> CalibrationDocument:
    """Validate a decoded calibration document; raises `CalibrationFileError` (one line,
    naming the key and the problem)."""
    if not isinstance(doc, dict):
        raise CalibrationFileError("a calibration file must hold a JSON object")
    fmt = doc.get("format")
    if fmt != FORMAT:
        raise CalibrationFileError(f"format must be {FORMAT!r}, got {fmt!r}")
    _check_keys(doc, _TOP_KEYS, "")
    model = _require(doc, "model", "")
    if model not in CAMERA_PARAMETERS:
        raise CalibrationFileError(f"model must be one of {list(CAMERA_PARAMETERS)}, got {model!r}")
    if isinstance(doc.get("software"), dict):
        _check_keys(doc["software"], _SOFTWARE_KEYS, "software")
    sensor = _sensor(doc)
    camera, dname = _camera(doc, model)
    plane = _plane(doc)
    stage, ecc = _stage(doc)
    if stage is not None and plane is None:
        raise CalibrationFileError("missing key laser_plane (the stage needs the laser plane)")
    poses = _poses(doc)
    if doc.get("table_target_pose") is not None and stage is None:
        raise CalibrationFileError("table_target_pose needs a stage")
    coverage = None
    if doc.get("coverage") is not None:
        try:
            coverage = Coverage.from_dict(doc["coverage"], sensor)
        except ValueError as err:
            raise CalibrationFileError(str(err)) from None
    return CalibrationDocument(
        model=model,
        distortion=dname,
        sensor_size=None if sensor is None else (int(sensor[0]), int(sensor[1])),
        camera=camera,
        board_poses=Pose(jnp.asarray(poses.rotvec), jnp.asarray(poses.translation)),
        plane=plane,
        stage=stage,
        eccentricity_mm=ecc,
        table_pose=table_pose(doc),
        coverage=coverage,
        diagnostics=_diagnostics(doc),
        raw=doc,
    )


def read_calibration_document(path: str | os.PathLike) -> CalibrationDocument:
    """Read and validate a calibration file (errors name the file and the problem).

    What reconstruction and export need (camera, plane, stage, sensor, coverage) without
    the calibration package; `scheimflux.read_calibration` gives the full `Calibration`.

    **Raises:** `FileNotFoundError` if missing; `CalibrationFileError` (a `ValueError`)
    for invalid JSON, another format, missing or unknown keys, wrong shapes, types or
    units, values out of range, an `R_m_c` that is not a rotation. Warns
    `UnconvergedCalibrationWarning` when the file records an unconverged solve.
    """
    doc = load_json(path, "calibration")
    try:
        document = parse_calibration_document(doc)
    except CalibrationFileError as err:
        raise CalibrationFileError(f"{os.fspath(path)}: {err}") from None
    _warn_if_unconverged(path, document)
    return document


def _warn_if_unconverged(path: str | os.PathLike, document: CalibrationDocument) -> None:
    """Warn `UnconvergedCalibrationWarning` when the file records an unconverged solve."""
    if document.converged:
        return
    failed = [
        name
        for name, s in (document.diagnostics.get("solves") or {}).items()
        if isinstance(s, dict) and not s.get("converged", True)
    ]
    warnings.warn(
        f"{os.fspath(path)}: this calibration did NOT converge"
        + (f" (solves: {', '.join(failed)})" if failed else "")
        + "; its numbers may be wrong",
        UnconvergedCalibrationWarning,
        stacklevel=4,
    )


def write_calibration_document(
    path: str | os.PathLike, doc: dict, *, overwrite: bool = False
) -> None:
    """Write a calibration document atomically (never clobbers unless `overwrite`); it is
    validated by parsing it first, so nothing unreadable is written."""
    parse_calibration_document(doc)
    write_json(path, doc, overwrite=overwrite)
