"""Calibrating OpenCV's camera model: which coefficients are free, and the initial camera.

OpenCV's model (`OpenCVCamera`, equal to `cv2.projectPoints`) is a pinhole `fx, fy, cx,
cy` (no skew) with up to 12 distortion coefficients and a tilted sensor `τx, τy`. Which of
them `cv2.calibrateCamera` estimates is set by flags; scheimflux names the same choices:

| flag | frees | `cv2` flag |
|---|---|---|
| (always) | `fx, fy, cx, cy, k1, k2, p1, p2, k3` | (default) |
| `rational` | `k4, k5, k6` | `CALIB_RATIONAL_MODEL` |
| `thin-prism` | `s1, s2, s3, s4` | `CALIB_THIN_PRISM_MODEL` |
| `tilted` | `τx, τy` | `CALIB_TILTED_MODEL` |
| `zero-tangent` | holds `p1 = p2 = 0` | `CALIB_ZERO_TANGENT_DIST` |
| `fix-k3` | holds `k3 = 0` | `CALIB_FIX_K3` |

Coefficients that are not free stay at zero and are listed in the calibration's frozen
set (`camera.distortion.k4`, `camera.tau_x`, …). Any other parameter can be held with
`freeze` as for the other models.
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2

from ...camera._distortion import OpenCVDistortion
from ...camera._opencv import OpenCVCamera
from ...camera._pinhole import Pinhole

OPENCV_FLAGS = ("rational", "thin-prism", "tilted", "zero-tangent", "fix-k3")

_CV2_FLAGS = {
    "rational": cv2.CALIB_RATIONAL_MODEL,
    "thin-prism": cv2.CALIB_THIN_PRISM_MODEL,
    "tilted": cv2.CALIB_TILTED_MODEL,
    "zero-tangent": cv2.CALIB_ZERO_TANGENT_DIST,
    "fix-k3": cv2.CALIB_FIX_K3,
}
_DIST = "camera.distortion."
_RATIONAL = tuple(_DIST + k for k in ("k4", "k5", "k6"))
_PRISM = tuple(_DIST + s for s in ("s1", "s2", "s3", "s4"))
_TILT = ("camera.tau_x", "camera.tau_y")
_TANGENT = (_DIST + "p1", _DIST + "p2")
_K3 = (_DIST + "k3",)
# every coefficient besides the pinhole: frozen for the ideal first solve
OPENCV_COEFFICIENTS = (
    tuple(_DIST + k for k in ("k1", "k2", "p1", "p2", "k3")) + _RATIONAL + _PRISM + _TILT
)


def parse_opencv_flags(flags: str | Iterable[str] | None) -> tuple[str, ...]:
    """Normalise OpenCV-model flags: `"rational,tilted"`, a list of names, or None.

    **Returns:** the flags in `OPENCV_FLAGS` order, each once. Raises `ValueError` naming
    an unknown flag (with the valid ones).
    """
    if flags is None:
        return ()
    if isinstance(flags, str):
        flags = [f for f in flags.replace(" ", "").split(",") if f]
    names = set()
    for f in flags:
        if f not in OPENCV_FLAGS:
            raise ValueError(f"unknown OpenCV flag {f!r}; valid flags: {', '.join(OPENCV_FLAGS)}")
        names.add(f)
    return tuple(f for f in OPENCV_FLAGS if f in names)


def opencv_frozen(flags: Iterable[str] = ()) -> tuple[str, ...]:
    """Parameter paths the flags hold at zero (the coefficients not in the model)."""
    flags = parse_opencv_flags(tuple(flags))
    frozen = []
    if "rational" not in flags:
        frozen += _RATIONAL
    if "thin-prism" not in flags:
        frozen += _PRISM
    if "tilted" not in flags:
        frozen += _TILT
    if "zero-tangent" in flags:
        frozen += _TANGENT
    if "fix-k3" in flags:
        frozen += _K3
    return tuple(frozen)


def opencv_flags_from_frozen(frozen: Iterable[str]) -> tuple[str, ...]:
    """The flags whose model terms are (at least partly) free, given a frozen set."""
    frozen = set(frozen)
    if "camera.distortion" in frozen or "camera" in frozen:
        return ()
    out = []
    for name, paths in (("rational", _RATIONAL), ("thin-prism", _PRISM), ("tilted", _TILT)):
        if not all(p in frozen for p in paths):
            out.append(name)
    if all(p in frozen for p in _TANGENT):
        out.append("zero-tangent")
    if all(p in frozen for p in _K3):
        out.append("fix-k3")
    return parse_opencv_flags(out)


def cv2_calibration_flags(flags: Iterable[str] = ()) -> int:
    """The `cv2.calibrateCamera` flags of the same model (`cv2.CALIB_*` OR-ed)."""
    out = 0
    for f in parse_opencv_flags(tuple(flags)):
        out |= _CV2_FLAGS[f]
    return out


def opencv_from_pinhole(pinhole: Pinhole) -> OpenCVCamera:
    """An OpenCV camera with the pinhole's focal lengths and principal point, no
    distortion and no tilt (OpenCV has no skew: Zhang's γ is dropped; it is ~0 for an
    untilted sensor and absorbed by `cx`, the tilt and the poses in the solve)."""
    return OpenCVCamera(
        pinhole.alpha, pinhole.beta, pinhole.x0, pinhole.y0, OpenCVDistortion(), 0.0, 0.0
    )
