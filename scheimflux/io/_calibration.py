"""The calibration file, `"format": "scheimflux.calibration/1"` (JSON).

```
{"format": "scheimflux.calibration/1",
 "model": "thick-lens",                                   # or "pinhole"
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
 "diagnostics": {"reprojection_rms_px": ..., "laser_plane_rms_mm": ..., "gauge_rms_mm": ...,
                 "solves": {"camera": {"steps": 12, "converged": true, "time_s": 3.1}, ...},
                 "frozen": ["camera.dx", ...], "converged": true, ...},
 "software": {"name": "scheimflux", "version": "0.1.0"}}
```

The pinhole model (paper eq. 14) has `alpha`, `beta`, `gamma`, `x0`, `y0` (px) and
`"distortion": {"model": "none"}`. Distortion models: `"none"`, `"radial-tangential"`
(k1, k2, k3, p1, p2) and `"division"` (kappa), all dimensionless (unit `"1"`), acting in
the untilted image plane.

Angles are written in degrees and read back in radians; the degree values are chosen
so that the conversion back reproduces the radians bit for bit. The laser plane is
`n · X = 1` in the camera frame; `unit_normal` and `distance_mm` are written for people
and, when present, must agree with `n_per_mm`. `R_m_c`, `t_m_c_mm` map camera to
measurement coordinates (`X_m = R_m_c X_c + t_m_c`, frame 0 of a scan).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import math
import os
from typing import Any

import numpy as np

from ..camera._distortion import Division, NoDistortion, RadialTangential
from ..camera._pinhole import Pinhole
from ..camera._thick_lens import ThickLensScheimpflug
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ._files import load_json, write_json

FORMAT = "scheimflux.calibration/1"

# (name, unit) in file order; angles are stored in degrees.
CAMERA_PARAMETERS = {
    "thick-lens": (
        ("f", "mm"),
        ("e", "mm"),
        ("z0", "mm"),
        ("phi", "deg"),
        ("theta", "deg"),
        ("x0", "px"),
        ("y0", "px"),
        ("dx", "mm"),
        ("dy", "mm"),
    ),
    "pinhole": (("alpha", "px"), ("beta", "px"), ("gamma", "px"), ("x0", "px"), ("y0", "px")),
}
DISTORTION_PARAMETERS = {
    "none": (),
    "radial-tangential": ("k1", "k2", "k3", "p1", "p2"),
    "division": ("kappa",),
}
_DISTORTION_CLASSES = {
    "none": NoDistortion,
    "radial-tangential": RadialTangential,
    "division": Division,
}
# |RᵀR − I| and |det R − 1| allowed for a rotation read from a file.
ROTATION_TOLERANCE = 1e-9


class CalibrationFileError(ValueError):
    """A malformed calibration file; the message names the problem."""


@dataclasses.dataclass(frozen=True)
class LoadedCalibration:
    """A calibration read from a file.

    **Fields:**
    - `camera`: `ThickLensScheimpflug` or `Pinhole`.
    - `plane`: the `LaserPlane` (camera frame).
    - `stage`: the `RotaryStage`, or None when no stage was calibrated.
    - `eccentricity_mm`: the gauge axis's offset from the table axis `(2,)`, or None.
    - `model`: `"thick-lens"` or `"pinhole"`; `distortion`: the distortion model's name.
    - `diagnostics`: the file's diagnostics (a dict, possibly empty).
    - `raw`: the whole decoded document.
    """

    camera: ThickLensScheimpflug | Pinhole
    plane: LaserPlane
    stage: RotaryStage | None
    eccentricity_mm: np.ndarray | None
    model: str
    distortion: str
    diagnostics: dict
    raw: dict


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


def camera_to_dict(camera) -> dict:
    """`(model, camera dict)` pieces of the file for a thick-lens or pinhole camera."""
    if isinstance(camera, ThickLensScheimpflug):
        model = "thick-lens"
    elif isinstance(camera, Pinhole):
        model = "pinhole"
    else:
        raise ValueError(
            f"cannot store a {type(camera).__name__} camera: the calibration file holds "
            "thick-lens and pinhole cameras"
        )
    doc = {name: _value(getattr(camera, name), unit) for name, unit in CAMERA_PARAMETERS[model]}
    if model == "thick-lens":
        dname = distortion_name(camera.distortion)
        dist = {"model": dname}
        for p in DISTORTION_PARAMETERS[dname]:
            dist[p] = _value(getattr(camera.distortion, p), "1")
    else:
        dist = {"model": "none"}
    doc["distortion"] = dist
    return doc


def _floats(a) -> list:
    a = np.asarray(a, dtype=np.float64)
    return [float(x) for x in a] if a.ndim == 1 else [_floats(r) for r in a]


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


def _jsonable(v: Any) -> Any:
    """Diagnostics values as plain JSON types (NumPy/JAX scalars and arrays included)."""
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
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
    return [_jsonable(x) for x in a]


def _version() -> str:
    try:
        return importlib.metadata.version("scheimflux")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - source checkout
        return "unknown"


def calibration_to_dict(cal, *, diagnostics: dict | None = None) -> dict:
    """A `Calibration` (from `scheimflux.calibrate.calibrate`) as a JSON-ready dict.

    `diagnostics` adds entries to the file's diagnostics (they override the computed
    ones of the same name).
    """
    params = cal.params
    if params.plane is None:
        raise ValueError("the calibration has no laser plane: nothing to measure with")
    doc = {
        "format": FORMAT,
        "model": cal.model,
        "camera": camera_to_dict(params.camera),
        "laser_plane": plane_to_dict(params.plane),
    }
    model = "thick-lens" if isinstance(params.camera, ThickLensScheimpflug) else "pinhole"
    if model != cal.model:
        raise ValueError(f"calibration says model {cal.model!r} but holds a {model} camera")
    if params.stage is not None:
        doc["stage"] = stage_to_dict(params.stage, params.eccentricity)
    fits = dict(getattr(cal, "fits", {}) or {})
    diag = {
        "reprojection_rms_px": cal.reprojection_rms_px,
        "laser_plane_rms_mm": cal.plane_rms_mm,
        "gauge_rms_mm": cal.gauge_rms_mm,
        "init": getattr(cal, "init", None),
        "joint": getattr(cal, "joint", None),
        "solves": {
            name: {
                "steps": int(fit.steps),
                "converged": bool(fit.converged),
                "time_s": float(fit.time_s),
                "cost": float(fit.cost),
                **({"message": str(fit.message)} if fit.message else {}),
            }
            for name, fit in fits.items()
        },
        "converged": all(bool(fit.converged) for fit in fits.values()),
        "frozen": list(getattr(cal, "freeze", ()) or ()),
    }
    diag.update(diagnostics or {})
    doc["diagnostics"] = _jsonable(diag)
    doc["software"] = {"name": "scheimflux", "version": _version()}
    return doc


def write_calibration(
    path: str | os.PathLike, cal, *, diagnostics: dict | None = None, overwrite: bool = False
) -> None:
    """Write a calibration file atomically (never clobbers unless `overwrite`).

    The document is validated by reading it back before anything is written.
    """
    doc = calibration_to_dict(cal, diagnostics=diagnostics)
    parse_calibration(doc)  # refuse to write what we could not read
    write_json(path, doc, overwrite=overwrite)


# ----------------------------------------------------------------------------- reading


def _require(d, key: str, where: str):
    if not isinstance(d, dict):
        raise CalibrationFileError(f"{where or 'the document'} must be a JSON object")
    if key not in d:
        raise CalibrationFileError(f"missing key {where + '.' if where else ''}{key}")
    return d[key]


def _number(v, where: str) -> float:
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise CalibrationFileError(f"{where} must be a finite number, got {v!r}")
    return float(v)


def _vector(v, n: int, where: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n:
        raise CalibrationFileError(f"{where} must be a list of {n} numbers, got {v!r}")
    return np.array([_number(x, f"{where}[{i}]") for i, x in enumerate(v)], dtype=np.float64)


def _matrix3(v, where: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != 3:
        raise CalibrationFileError(f"{where} must be a 3x3 list of lists")
    return np.stack([_vector(r, 3, f"{where}[{i}]") for i, r in enumerate(v)])


def _parameter(d, name: str, unit: str, where: str) -> float:
    entry = _require(d, name, where)
    at = f"{where}.{name}"
    if not isinstance(entry, dict):
        raise CalibrationFileError(
            f'{at} must be {{"value": number, "unit": "{unit}"}}, got {entry!r}'
        )
    value = _number(_require(entry, "value", at), f"{at}.value")
    got = _require(entry, "unit", at)
    if got != unit:
        raise CalibrationFileError(f"{at}.unit must be {unit!r}, got {got!r}")
    return math.radians(value) if unit == "deg" else value


def _camera(doc: dict, model: str):
    cd = _require(doc, "camera", "")
    if not isinstance(cd, dict):
        raise CalibrationFileError("camera must be a JSON object")
    values = {n: _parameter(cd, n, u, "camera") for n, u in CAMERA_PARAMETERS[model]}
    dd = _require(cd, "distortion", "camera")
    dname = _require(dd, "model", "camera.distortion")
    if dname not in DISTORTION_PARAMETERS:
        raise CalibrationFileError(
            f"camera.distortion.model must be one of {list(DISTORTION_PARAMETERS)}, got {dname!r}"
        )
    if model == "pinhole":
        if dname != "none":
            raise CalibrationFileError(
                f"the pinhole model has no distortion; camera.distortion.model is {dname!r}"
            )
        camera = Pinhole(**values)
    else:
        dist = _DISTORTION_CLASSES[dname](
            *(_parameter(dd, p, "1", "camera.distortion") for p in DISTORTION_PARAMETERS[dname])
        )
        for name in ("dx", "dy"):
            if values[name] <= 0:
                raise CalibrationFileError(f"camera.{name} (pixel pitch) must be positive")
        camera = ThickLensScheimpflug(**values, distortion=dist)
    return camera, dname


def _plane(doc: dict) -> LaserPlane:
    pd = _require(doc, "laser_plane", "")
    n = _vector(_require(pd, "n_per_mm", "laser_plane"), 3, "laser_plane.n_per_mm")
    norm = float(np.linalg.norm(n))
    if norm == 0:
        raise CalibrationFileError("laser_plane.n_per_mm must not be zero")
    if "unit_normal" in pd:
        u = _vector(pd["unit_normal"], 3, "laser_plane.unit_normal")
        if np.max(np.abs(u - n / norm)) > 1e-9:
            raise CalibrationFileError(
                "laser_plane.unit_normal disagrees with n_per_mm (n_per_mm / |n_per_mm| = "
                f"{_floats(n / norm)})"
            )
    if "distance_mm" in pd:
        d = _number(pd["distance_mm"], "laser_plane.distance_mm")
        if abs(d * norm - 1.0) > 1e-9:
            raise CalibrationFileError(
                f"laser_plane.distance_mm = {d} disagrees with n_per_mm (1 / |n_per_mm| = "
                f"{1.0 / norm})"
            )
    return LaserPlane(n)


def _stage(doc: dict) -> tuple[RotaryStage | None, np.ndarray | None]:
    sd = doc.get("stage")
    if sd is None:
        return None, None
    if not isinstance(sd, dict):
        raise CalibrationFileError("stage must be a JSON object (or absent)")
    R = _matrix3(_require(sd, "R_m_c", "stage"), "stage.R_m_c")
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    det = float(np.linalg.det(R))
    if err > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise CalibrationFileError(
            f"stage.R_m_c is not a rotation matrix (max |R^T R - I| = {err:.3g}, det = {det:.9g})"
        )
    t = _vector(_require(sd, "t_m_c_mm", "stage"), 3, "stage.t_m_c_mm")
    dw = math.radians(_number(_require(sd, "delta_omega_deg", "stage"), "stage.delta_omega_deg"))
    ecc = None
    if sd.get("gauge_eccentricity_mm") is not None:
        ecc = _vector(sd["gauge_eccentricity_mm"], 2, "stage.gauge_eccentricity_mm")
    return RotaryStage(pose=Pose.from_matrix(R, t), delta_omega=dw), ecc


def parse_calibration(doc) -> LoadedCalibration:
    """Validate a decoded calibration document; raises `CalibrationFileError`."""
    if not isinstance(doc, dict):
        raise CalibrationFileError("a calibration file must hold a JSON object")
    fmt = doc.get("format")
    if fmt != FORMAT:
        raise CalibrationFileError(f"format must be {FORMAT!r}, got {fmt!r}")
    model = _require(doc, "model", "")
    if model not in CAMERA_PARAMETERS:
        raise CalibrationFileError(f"model must be one of {list(CAMERA_PARAMETERS)}, got {model!r}")
    camera, dname = _camera(doc, model)
    plane = _plane(doc)
    stage, ecc = _stage(doc)
    diagnostics = doc.get("diagnostics", {})
    if diagnostics is None:
        diagnostics = {}
    if not isinstance(diagnostics, dict):
        raise CalibrationFileError("diagnostics must be a JSON object")
    return LoadedCalibration(camera, plane, stage, ecc, model, dname, diagnostics, doc)


def read_calibration(path: str | os.PathLike) -> LoadedCalibration:
    """Read and validate a calibration file; errors name the file and the problem.

    **Raises:** `FileNotFoundError` if missing; `ValueError` (`CalibrationFileError`)
    for invalid JSON, another format, missing keys, wrong shapes or types, units other
    than the file's, an `R_m_c` that is not a rotation, or an unknown model/distortion.
    """
    doc = load_json(path, "calibration")
    try:
        return parse_calibration(doc)
    except CalibrationFileError as err:
        raise CalibrationFileError(f"{os.fspath(path)}: {err}") from None
