"""The calibration file's schema: keys, units, allowed ranges, and their validation.

Used by [`parse_calibration`][] (`_calibration.py`); every error is a
`CalibrationFileError` whose message names the key.
"""

from __future__ import annotations

import difflib
import math

import numpy as np

from .._checks import MAX_LENGTH_MM, MAX_TILT_DEG
from ..camera._distortion import Division, NoDistortion, OpenCVDistortion, RadialTangential
from ..camera._noncentral import ThickLensNonCentral
from ..camera._opencv import OpenCVCamera
from ..camera._pinhole import Pinhole
from ..camera._thick_lens import ThickLensScheimpflug
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose

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
    # the thick lens, the entrance pupil's shift along the axis, c1 ρ² + c2 ρ⁴ (mm), and
    # the ray origin's lateral offset ax, ay and its pivot shift b1 ρ² + b2 ρ⁴ (mm;
    # optional on reading, 0 when absent)
    "thick-lens-noncentral": (
        ("f", "mm"),
        ("e", "mm"),
        ("z0", "mm"),
        ("phi", "deg"),
        ("theta", "deg"),
        ("x0", "px"),
        ("y0", "px"),
        ("dx", "mm"),
        ("dy", "mm"),
        ("c1", "mm"),
        ("c2", "mm"),
        ("ax", "mm"),
        ("ay", "mm"),
        ("b1", "mm"),
        ("b2", "mm"),
    ),
    "pinhole": (("alpha", "px"), ("beta", "px"), ("gamma", "px"), ("x0", "px"), ("y0", "px")),
    "opencv": (
        ("fx", "px"),
        ("fy", "px"),
        ("cx", "px"),
        ("cy", "px"),
        ("tau_x", "deg"),
        ("tau_y", "deg"),
    ),
}
_CAMERA_CLASSES = {
    "thick-lens": ThickLensScheimpflug,
    "thick-lens-noncentral": ThickLensNonCentral,
    "pinhole": Pinhole,
    "opencv": OpenCVCamera,
}
DISTORTION_PARAMETERS = {
    "none": (),
    "radial-tangential": ("k1", "k2", "k3", "p1", "p2"),
    "division": ("kappa",),
    "opencv": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
}
_DISTORTION_CLASSES = {
    "none": NoDistortion,
    "radial-tangential": RadialTangential,
    "division": Division,
    "opencv": OpenCVDistortion,
}
# the distortion models each camera model may hold
_MODEL_DISTORTIONS = {
    "thick-lens": ("none", "radial-tangential", "division"),
    "thick-lens-noncentral": ("none", "radial-tangential", "division"),
    "pinhole": ("none",),
    "opencv": ("opencv",),
}
# Parameters that must be positive (name: why), and sensor tilts that must lie within
# ±MAX_TILT_DEG (the steepest sensor tilt of a real Scheimpflug rig: `_checks.py`); every
# length (mm) and pixel coordinate within ±MAX_LENGTH_MM (beyond any rig).
_POSITIVE = {
    "f": "the focal length",
    "z0": "the sensor lies behind the lens",
    "dx": "pixel pitch",
    "dy": "pixel pitch",
    "alpha": "a focal length in px",
    "beta": "a focal length in px",
    "fx": "a focal length in px",
    "fy": "a focal length in px",
}
_ANGLES = ("phi", "theta", "tau_x", "tau_y")
# |RᵀR − I| and |det R − 1| allowed for a rotation read from a file.
ROTATION_TOLERANCE = 1e-9
# A laser plane this close to the projection centre (mm) cannot triangulate: every pixel's
# ray meets it next to the centre, so all points collapse onto one spot.
MIN_PLANE_DISTANCE_MM = 0.1

_TOP_KEYS = (
    "format",
    "model",
    "sensor",
    "camera",
    "laser_plane",
    "stage",
    "board_poses",
    "table_target_pose",
    "coverage",
    "diagnostics",
    "software",
)
_SENSOR_KEYS = ("width", "height")
_PARAMETER_KEYS = ("value", "unit")
_PLANE_KEYS = ("n_per_mm", "unit_normal", "distance_mm")
_STAGE_KEYS = ("R_m_c", "t_m_c_mm", "delta_omega_deg", "gauge_eccentricity_mm")
_POSES_KEYS = ("rotvec", "translation_mm")
_SOFTWARE_KEYS = ("name", "version")


class CalibrationFileError(ValueError):
    """A malformed calibration file; the message names the problem."""


class UnconvergedCalibrationWarning(UserWarning):
    """A calibration file records a solve that did not converge."""


def _floats(a) -> list:
    a = np.asarray(a, dtype=np.float64)
    return [float(x) for x in a] if a.ndim == 1 else [_floats(r) for r in a]


def _object(d, where: str) -> dict:
    if not isinstance(d, dict):
        raise CalibrationFileError(f"{where or 'the document'} must be a JSON object")
    return d


def _check_keys(d: dict, allowed, where: str) -> None:
    """Refuse keys not in `allowed`, suggesting the closest valid one."""
    for key in d:
        if key in allowed:
            continue
        at = f"{where}.{key}" if where else str(key)
        close = difflib.get_close_matches(str(key), list(allowed), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise CalibrationFileError(f"unknown key {at}{hint}; allowed here: {', '.join(allowed)}")


def _require(d, key: str, where: str):
    _object(d, where)
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


def _lengths(v: np.ndarray, where: str) -> np.ndarray:
    """`v` (mm), refused beyond `MAX_LENGTH_MM` in any component (no rig is that large)."""
    if not np.all(np.abs(v) <= MAX_LENGTH_MM):
        raise CalibrationFileError(
            f"{where} = {_floats(v)} mm is beyond any real rig (each |component| <= "
            f"{MAX_LENGTH_MM:g} mm)"
        )
    return v


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
    _check_keys(entry, _PARAMETER_KEYS, at)
    value = _number(_require(entry, "value", at), f"{at}.value")
    got = _require(entry, "unit", at)
    if got != unit:
        raise CalibrationFileError(f"{at}.unit must be {unit!r}, got {got!r}")
    if name in _POSITIVE and value <= 0:
        raise CalibrationFileError(
            f"{at}.value must be positive ({_POSITIVE[name]}), got {value!r} {unit}"
        )
    if unit == "deg" and name in _ANGLES and not abs(value) <= MAX_TILT_DEG:
        raise CalibrationFileError(
            f"{at}.value = {value!r}° is beyond any Scheimpflug camera's sensor tilt "
            f"(|tilt| <= {MAX_TILT_DEG:g}°)"
        )
    if unit in ("mm", "px") and not abs(value) <= MAX_LENGTH_MM:
        raise CalibrationFileError(
            f"{at}.value = {value!r} {unit} is beyond any real rig (|value| <= "
            f"{MAX_LENGTH_MM:g} {unit})"
        )
    return math.radians(value) if unit == "deg" else value


#: Camera parameters a file may leave out (added after files were written without them):
#: the non-central lens's lateral offset, 0 when absent.
_OPTIONAL_CAMERA = frozenset({"ax", "ay", "b1", "b2"})


def _camera(doc: dict, model: str):
    cd = _object(_require(doc, "camera", ""), "camera")
    names = tuple(n for n, _ in CAMERA_PARAMETERS[model])
    _check_keys(cd, names + ("distortion",), "camera")
    values = {n: _parameter(cd, n, u, "camera") for n, u in CAMERA_PARAMETERS[model]
              if n in cd or n not in _OPTIONAL_CAMERA}  # fmt: skip
    dd = _object(_require(cd, "distortion", "camera"), "camera.distortion")
    dname = _require(dd, "model", "camera.distortion")
    allowed = _MODEL_DISTORTIONS[model]
    if dname not in allowed:
        raise CalibrationFileError(
            f"camera.distortion.model of the {model} model must be one of {list(allowed)}, "
            f"got {dname!r}"
        )
    _check_keys(dd, ("model",) + DISTORTION_PARAMETERS[dname], "camera.distortion")
    coeffs = [_parameter(dd, p, "1", "camera.distortion") for p in DISTORTION_PARAMETERS[dname]]
    try:  # the constructors' physical checks, as a file error naming the camera
        if model == "pinhole":
            return Pinhole(**values), dname
        dist = _DISTORTION_CLASSES[dname](*coeffs)
        if model == "thick-lens-noncentral":
            values["pupil"] = (values.pop("c1"), values.pop("c2"))
            values["lateral"] = (values.pop("ax", 0.0), values.pop("ay", 0.0))
            values["pivot"] = (values.pop("b1", 0.0), values.pop("b2", 0.0))
        return _CAMERA_CLASSES[model](**values, distortion=dist), dname
    except (TypeError, ValueError) as err:
        raise CalibrationFileError(f"camera: {err}") from None


def _plane(doc: dict) -> LaserPlane | None:
    pd = doc.get("laser_plane")
    if pd is None:
        return None  # a camera-only calibration
    pd = _object(pd, "laser_plane")
    _check_keys(pd, _PLANE_KEYS, "laser_plane")
    n = _vector(_require(pd, "n_per_mm", "laser_plane"), 3, "laser_plane.n_per_mm")
    norm = float(np.linalg.norm(n))
    if norm == 0:
        raise CalibrationFileError("laser_plane.n_per_mm must not be zero")
    if not 1.0 / norm <= MAX_LENGTH_MM:
        raise CalibrationFileError(
            f"laser_plane.n_per_mm puts the plane {1.0 / norm:.3g} mm from the projection "
            f"centre, beyond any real rig (at most {MAX_LENGTH_MM:g} mm)"
        )
    if not 1.0 / norm >= MIN_PLANE_DISTANCE_MM:
        raise CalibrationFileError(
            f"laser_plane.n_per_mm is degenerate: the plane passes {1e3 / norm:.3g} µm from "
            f"the projection centre (at least {MIN_PLANE_DISTANCE_MM} mm needed to "
            "triangulate)"
        )
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
    _check_keys(sd, _STAGE_KEYS, "stage")
    R = _matrix3(_require(sd, "R_m_c", "stage"), "stage.R_m_c")
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    det = float(np.linalg.det(R))
    if err > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise CalibrationFileError(
            f"stage.R_m_c is not a rotation matrix (max |R^T R - I| = {err:.3g}, det = {det:.9g})"
        )
    t = _lengths(_vector(_require(sd, "t_m_c_mm", "stage"), 3, "stage.t_m_c_mm"),
                 "stage.t_m_c_mm")  # fmt: skip
    dw_deg = _number(_require(sd, "delta_omega_deg", "stage"), "stage.delta_omega_deg")
    if not 0 < abs(dw_deg) < 360:
        raise CalibrationFileError(
            f"stage.delta_omega_deg must be non-zero and within ±360°, got {dw_deg!r}"
        )
    ecc = None
    if sd.get("gauge_eccentricity_mm") is not None:
        ecc = _lengths(_vector(sd["gauge_eccentricity_mm"], 2, "stage.gauge_eccentricity_mm"),
                       "stage.gauge_eccentricity_mm")  # fmt: skip
    return RotaryStage(pose=Pose.from_matrix(R, t), delta_omega=math.radians(dw_deg)), ecc


def _sensor(doc: dict) -> tuple[int, int] | None:
    sd = doc.get("sensor")
    if sd is None:
        return None
    sd = _object(sd, "sensor")
    _check_keys(sd, _SENSOR_KEYS, "sensor")
    out = []
    for key in _SENSOR_KEYS:
        v = _require(sd, key, "sensor")
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            raise CalibrationFileError(f"sensor.{key} must be a positive integer, got {v!r}")
        out.append(int(v))
    return out[0], out[1]


def _rows(v, where: str) -> np.ndarray:
    if not isinstance(v, list):
        raise CalibrationFileError(f"{where} must be a list of [x, y, z]")
    return np.stack([_vector(r, 3, f"{where}[{i}]") for i, r in enumerate(v)] or [np.zeros(3)])[
        : len(v)
    ]


def _poses(doc: dict) -> Pose:
    pd = doc.get("board_poses")
    if pd is None:
        return Pose(np.zeros((0, 3)), np.zeros((0, 3)))
    pd = _object(pd, "board_poses")
    _check_keys(pd, _POSES_KEYS, "board_poses")
    rv = _rows(_require(pd, "rotvec", "board_poses"), "board_poses.rotvec")
    t = _lengths(
        _rows(_require(pd, "translation_mm", "board_poses"), "board_poses.translation_mm"),
        "board_poses.translation_mm",
    )
    if len(rv) != len(t):
        raise CalibrationFileError(
            f"board_poses.rotvec has {len(rv)} rows but board_poses.translation_mm {len(t)}"
        )
    return Pose(rv, t)


def table_pose(doc: dict) -> Pose | None:
    """The `table_target_pose` (a target fixed to the rotary table), None if absent."""
    pd = doc.get("table_target_pose")
    if pd is None:
        return None
    pd = _object(pd, "table_target_pose")
    _check_keys(pd, _POSES_KEYS, "table_target_pose")
    rv = _vector(_require(pd, "rotvec", "table_target_pose"), 3, "table_target_pose.rotvec")
    t = _lengths(
        _vector(
            _require(pd, "translation_mm", "table_target_pose"), 3,
            "table_target_pose.translation_mm",
        ),
        "table_target_pose.translation_mm",
    )  # fmt: skip
    return Pose(rv, t)


def _diagnostics(doc: dict) -> dict:
    diagnostics = doc.get("diagnostics", {})
    if diagnostics is None:
        return {}
    if not isinstance(diagnostics, dict):
        raise CalibrationFileError("diagnostics must be a JSON object")
    _check_recorded_sigma(diagnostics)
    return diagnostics


def _check_recorded_sigma(diagnostics: dict) -> None:
    """The file's values against its own recorded diagnostics, where it records enough:
    a parameter listed in `diagnostics.frozen` was held fixed, so it cannot have a σ in
    `diagnostics.uncertainty.std`, and every recorded σ is a finite number >= 0 (or
    null, written for an undetermined one).

    (The value a frozen parameter was held at is not recorded in the file — only in the
    observations it was computed from — so a frozen value edited afterwards is caught
    only by the physical bounds, not by comparison.)"""
    frozen = diagnostics.get("frozen")
    if frozen is not None and (
        not isinstance(frozen, list) or not all(isinstance(p, str) for p in frozen)
    ):
        raise CalibrationFileError(
            f"diagnostics.frozen must be a list of parameter names, got {frozen!r}"
        )
    unc = diagnostics.get("uncertainty")
    std = unc.get("std") if isinstance(unc, dict) else None
    if std is None:
        return
    if not isinstance(std, dict):
        raise CalibrationFileError("diagnostics.uncertainty.std must be a JSON object")
    for name, sigma in std.items():
        if sigma is None:  # written for a σ that was not finite (undetermined)
            continue
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not (
            math.isfinite(sigma) and sigma >= 0
        ):
            raise CalibrationFileError(
                f"diagnostics.uncertainty.std.{name} must be a finite number >= 0 (a "
                f"standard deviation), got {sigma!r}"
            )
    for p in frozen or ():
        clash = [k for k in std if k == p or k.startswith((p + ".", p + "["))]
        if clash:
            raise CalibrationFileError(
                f"the file contradicts its own diagnostics: {p} is listed in "
                f"diagnostics.frozen (held fixed) but diagnostics.uncertainty.std gives "
                f"it a standard deviation ({clash[0]}); the file was edited or "
                "assembled from two calibrations"
            )
