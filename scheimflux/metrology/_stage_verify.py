"""Verification on an artefact that was not used to calibrate: measured − nominal ± U.

A calibration's own residuals cannot show that its table axis is wrong (the gauge's
radius is an input of the stage calibration, so re-measuring it cannot fail). An
independent artefact can: a second ring of known radius, two spheres of known centre
distance on the table (a length spanning a large table angle: what an axis error
spoils), or a stepped gauge of known heights. [`verify_artefact`][] reconstructs its
stripe pixels with the calibration, fits the artefact with `scheimflux.metrology`
(value and GUM uncertainty U, k = 2, including the calibration's covariance), and
compares with the nominal value: pass when |measured − nominal| ≤ the tolerance
(default: U, i.e. the difference is explained by the stated uncertainty).
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ._shapes import AbstractShape, Cylinder, Steps, _check_spread, _np_points

__all__ = ["ARTEFACTS", "SpherePair", "Verification", "parse_artefact", "verify_artefact"]

ARTEFACTS = ("cylinder", "sphere-pair", "steps")


def parse_artefact(text: str) -> tuple[str, tuple[float, ...]]:
    """`"cylinder:R"`, `"sphere-pair:D"`, `"steps:H1,H2,…"` → `(kind, nominal values mm)`."""
    kind, sep, rest = str(text).partition(":")
    kind = kind.strip().lower()
    if kind not in ARTEFACTS:
        raise ValueError(
            f"unknown artefact {kind!r}: give cylinder:R, sphere-pair:D or steps:H1,H2,..."
        )
    if not sep or not rest.strip():
        raise ValueError(f"artefact {kind!r} needs its nominal value(s) in mm, e.g. "
                         + {"cylinder": "cylinder:17.0", "sphere-pair": "sphere-pair:17.02",
                            "steps": "steps:1.0,1.5,2.0"}[kind])  # fmt: skip
    try:
        vals = tuple(float(v) for v in rest.split(","))
    except ValueError:
        raise ValueError(f"artefact {kind!r}: nominal values must be numbers, got {rest!r}")
    if not all(math.isfinite(v) and v > 0 for v in vals):
        raise ValueError(f"artefact {kind!r}: nominal values must be positive, got {rest!r}")
    if kind != "steps" and len(vals) != 1:
        raise ValueError(f"artefact {kind!r} takes one nominal value, got {len(vals)}")
    return kind, vals


class SpherePair(AbstractShape):
    """Two spheres (label 0 and 1); values: the centre distance, then the two radii."""

    kind: ClassVar[str] = "sphere-pair"

    @property
    def names(self):
        return ("centre_distance", "radius_0", "radius_1")

    def n_params(self):
        return 8

    def check(self, X, labels):
        X = _np_points(X, "sphere pair", 10)
        lab = np.asarray(labels)
        for k in (0, 1):
            Xk = X[lab == k]
            if len(Xk) < 5:
                raise ValueError(f"sphere pair: sphere {k} has {len(Xk)} points, 5 needed")
            _check_spread(Xk, f"sphere pair (sphere {k})", need_3d=True)

    def start(self, X, labels):
        X = jax.lax.stop_gradient(X)

        def one(k):
            w = (labels == k).astype(X.dtype)
            m = (w @ X) / jnp.sum(w)
            d = X - m
            A = jnp.concatenate([2.0 * d, jnp.ones_like(d[:, :1])], axis=1) * w[:, None]
            sol = jnp.linalg.solve(A.T @ A, A.T @ (jnp.sum(d * d, axis=1) * w))
            c = m + sol[:3]
            return c, jnp.sqrt(jnp.maximum(sol[3] + sol[:3] @ sol[:3], 0.0))

        (c0, r0), (c1, r1) = one(0), one(1)
        return jnp.zeros(8, X.dtype), (c0, r0, c1, r1)

    def _spheres(self, y, frame):
        c0, r0, c1, r1 = frame
        return c0 + y[:3], r0 + y[3], c1 + y[4:7], r1 + y[7]

    def residual(self, y, frame, x, label):
        c0, r0, c1, r1 = self._spheres(y, frame)
        c = jnp.where(label == 1, c1, c0)
        r = jnp.where(label == 1, r1, r0)
        d = x - c
        return jnp.reshape(jnp.sqrt(jnp.maximum(d @ d, 1e-300)) - r, (1,))

    def values(self, y, frame, X, labels):
        c0, r0, c1, r1 = self._spheres(y, frame)
        return jnp.stack([jnp.linalg.norm(c1 - c0), r0, r1])

    def describe(self, y, frame):
        c0, _, c1, _ = self._spheres(y, frame)
        return {"centre_0": c0, "centre_1": c1}


def split_two_clusters(X: np.ndarray) -> np.ndarray:
    """Labels 0/1 of two well-separated clusters (2-means from the farthest pair).

    Raises `ValueError` when the points do not form two clusters (the gap between them
    under 3× the larger cluster's extent).
    """
    X = np.asarray(X, dtype=np.float64)
    a = X[np.argmax(np.linalg.norm(X - X.mean(axis=0), axis=1))]
    b = X[np.argmax(np.linalg.norm(X - a, axis=1))]
    for _ in range(20):
        lab = (np.linalg.norm(X - b, axis=1) < np.linalg.norm(X - a, axis=1)).astype(np.int32)
        if lab.min() == lab.max():
            break
        a, b = X[lab == 0].mean(axis=0), X[lab == 1].mean(axis=0)
    if lab.min() == lab.max():
        raise ValueError("sphere pair: the points form one cluster, not two spheres")
    ext = max(float(np.linalg.norm(X[lab == k] - c, axis=1).max()) for k, c in ((0, a), (1, b)))
    if np.linalg.norm(b - a) < 3.0 * ext:
        raise ValueError("sphere pair: the two spheres' points are not clearly separated")
    return lab


@dataclasses.dataclass(frozen=True)
class Verification:
    """Measured − nominal of an artefact, with U and a pass/fail per value.

    **Fields:** `kind`, `names` (values compared), `nominal_mm`, `measured_mm`, `U_mm`
    (k = 2), `error_mm` (measured − nominal), `tolerance_mm` (per value), `passed` (per
    value), `measurement` (the full `metrology.Measurement`), `notes`.
    """

    kind: str
    names: tuple[str, ...]
    nominal_mm: np.ndarray
    measured_mm: np.ndarray
    U_mm: np.ndarray
    error_mm: np.ndarray
    tolerance_mm: np.ndarray
    passed: np.ndarray
    measurement: object
    notes: tuple[str, ...] = ()

    @property
    def all_passed(self) -> bool:
        return bool(np.all(self.passed))

    def summary(self) -> str:
        lines = [f"verify {self.kind}: {self.measurement.n_points} points"]
        for k, name in enumerate(self.names):
            lines.append(
                f"  {name:<16} measured {self.measured_mm[k]:.6f} mm, nominal "
                f"{self.nominal_mm[k]:.6f} mm: error {self.error_mm[k] * 1e3:+.3f} µm "
                f"± {self.U_mm[k] * 1e3:.3f} µm (U, k = 2), tolerance "
                f"{self.tolerance_mm[k] * 1e3:.3f} µm: {'PASS' if self.passed[k] else 'FAIL'}"
            )
        lines.extend(f"  note: {n}" for n in self.notes)
        lines.append("PASS" if self.all_passed else "FAIL")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "format": "scheimflux.verification/1",
            "kind": self.kind,
            "unit": "mm",
            "passed": self.all_passed,
            "values": {
                name: {
                    "nominal": float(self.nominal_mm[k]),
                    "measured": float(self.measured_mm[k]),
                    "error": float(self.error_mm[k]),
                    "U": float(self.U_mm[k]),
                    "tolerance": float(self.tolerance_mm[k]),
                    "passed": bool(self.passed[k]),
                }
                for k, name in enumerate(self.names)
            },
            "notes": list(self.notes),
            "measurement": self.measurement.to_dict(),
        }


def verify_artefact(
    cal,
    frames,
    kind: str,
    nominal,
    *,
    tolerance_mm: float | None = None,
    sigma_px: float | None = None,
    delta_omega: float | None = None,
    source: str = "the calibration",
) -> Verification:
    """Measure an artefact from its stripe pixels and compare with its nominal value.

    **Arguments:**
    - `cal`: a `Calibration` with its covariance (in memory, or
      `read_calibration(path, observations=OBS)`).
    - `frames`: per frame the `(K_i, 2)` stripe pixels; frame i is table step i.
    - `kind`: `"cylinder"` (radius, measurement frame), `"sphere-pair"` (centre distance,
      measurement frame) or `"steps"` (heights of faces 1 … K above face 0, the faces
      numbered along the profile from its end at smaller pixel u, one profile in the
      camera frame; the faces are taken
      perpendicular to the laser plane, so the distance between the profile's lines is
      the height).
    - `nominal`: the nominal value(s) (mm): `(R,)`, `(D,)`, `(H1, …, HK)`.
    - `tolerance_mm`: the accepted |measured − nominal|; None: U of each value.
    - `sigma_px`: the stripe centres' noise (px), for the stripe-noise term.
    - `delta_omega`: the scan's table step (rad) when it differs from the calibration's.

    **Returns:** a [`Verification`][]. **Raises:** `ValueError` (one line) for an unknown
    artefact, a missing or wrong number of nominal values, too few points, a calibration
    without the stage a rotary artefact needs.
    """
    from ._labels import label_steps
    from ._own_gauge import (
        few_gauge_frames_message,
        frames_on_calibration_gauge,
        is_own_gauge_scan,
        own_gauge_message,
    )
    from ._stripes import measure_stripes

    if kind not in ARTEFACTS:
        raise ValueError(f"unknown artefact {kind!r} (one of {', '.join(ARTEFACTS)})")
    nominal = np.atleast_1d(np.asarray(nominal, dtype=np.float64))
    if nominal.size == 0:
        raise ValueError(f"artefact {kind!r} needs its nominal value(s)")
    if kind != "steps" and nominal.size != 1:
        raise ValueError(f"artefact {kind!r} takes one nominal value, got {nominal.size}")
    if tolerance_mm is not None and not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"the tolerance must be positive, got {tolerance_mm}")
    frames = [np.asarray(f, dtype=np.float64).reshape(-1, 2) for f in frames]
    if not frames or sum(len(f) for f in frames) == 0:
        raise ValueError("the scan holds no stripe pixels")
    uv = np.concatenate(frames)
    fi = np.concatenate([np.full(len(f), i, np.float64) for i, f in enumerate(frames)])
    own = frames_on_calibration_gauge(cal, uv, fi)
    used = sum(len(f) > 0 for f in frames)
    if is_own_gauge_scan(own, used):
        raise ValueError(own_gauge_message(cal, own, used) + ": verify with an artefact "
                         "not used to calibrate")  # fmt: skip
    notes = []
    if own:  # a few frames on the gauge's stripes: the scan as a whole is another one
        notes.append(few_gauge_frames_message(own, used))
    rotary = kind in ("cylinder", "sphere-pair")
    if rotary:
        stage = cal.params.stage
        if stage is None:
            raise ValueError(f"{source} has no rotary stage: a {kind} is measured in the "
                             "measurement frame")  # fmt: skip
        if delta_omega is not None:
            if not (math.isfinite(delta_omega) and delta_omega != 0.0):
                raise ValueError(f"the scan's delta_omega must be a non-zero angle, got "
                                 f"{delta_omega}")  # fmt: skip
            # the stage turns frame i by i · Δω_cal: give it the scan's angle
            fi = fi * (float(delta_omega) / float(stage.delta_omega))
            notes.append(f"scan step {math.degrees(delta_omega):.4g}° (calibration "
                         f"{math.degrees(float(stage.delta_omega)):.4g}°)")  # fmt: skip
        if sum(len(f) > 0 for f in frames) < 2:
            raise ValueError(f"a {kind} needs stripe pixels in at least two frames")
    labels = None
    if kind == "cylinder":
        shape, names, sel = Cylinder(), ("radius",), [0]
    elif kind == "sphere-pair":
        shape, names, sel = SpherePair(), ("centre_distance",), [0]
        labels = _sphere_labels(cal, uv, fi)
    else:
        if len(frames) != 1 and sum(len(f) > 0 for f in frames) != 1:
            raise ValueError("steps are measured on one laser profile: give one frame")
        shape = Steps(n_faces=int(nominal.size) + 1, model="lines")
        names, sel = tuple(f"step_{k}" for k in range(1, nominal.size + 1)), list(
            range(nominal.size)
        )
        X = _camera_points(cal, uv)
        ok = np.isfinite(X).all(axis=1)
        if ok.sum() < 2 * (nominal.size + 1):
            raise ValueError(f"steps: {int(ok.sum())} points for {nominal.size + 1} faces")
        labels = np.full(len(uv), -1, np.int32)
        lab = label_steps(X[ok], nominal.size + 1)
        u_mean = [uv[ok][lab == k, 0].mean() for k in (0, nominal.size)]
        if u_mean[0] > u_mean[1]:  # number the faces from the smaller pixel u
            lab = nominal.size - lab
        labels[ok] = lab
        uv, fi, labels = uv[ok], fi[ok], labels[ok]
        notes.append("step heights assume faces perpendicular to the laser plane")
    m = measure_stripes(
        cal, uv, shape, frame="measurement" if rotary else "camera",
        frame_index=fi if rotary else None, labels=labels, sigma_px=sigma_px, source=source,
    )  # fmt: skip
    measured = np.asarray(m.values)[sel]
    U = np.asarray(m.U)[sel]
    if kind == "steps":
        measured = np.abs(measured)
    err = measured - nominal
    tol = U if tolerance_mm is None else np.full_like(U, float(tolerance_mm))
    if not np.all(np.isfinite(U)):
        raise ValueError(f"{kind}: the uncertainty is not finite: no verdict")
    notes.extend(m.notes)
    return Verification(kind, names, nominal, measured, U, err, tol, np.abs(err) <= tol, m,
                        tuple(notes))  # fmt: skip


def _camera_points(cal, uv):
    from ..reconstruct import stripe_to_camera

    rec = stripe_to_camera(cal.camera, cal.params.plane, uv)
    X = np.array(rec.points, dtype=np.float64)  # a copy: a JAX array's view is read-only
    X[np.asarray(rec.status) != 0] = np.nan
    return X


def _sphere_labels(cal, uv, fi):
    from ..reconstruct import stripe_to_measurement

    rec = stripe_to_measurement(cal.camera, cal.params.plane, cal.params.stage, uv, fi)
    X = np.asarray(rec.points, dtype=np.float64)
    ok = np.asarray(rec.status) == 0
    if ok.sum() < 10:
        raise ValueError(f"sphere pair: {int(ok.sum())} valid points, at least 10 needed")
    lab = np.zeros(len(uv), np.int32)
    lab[ok] = split_two_clusters(X[ok])
    return lab


#: Fewest stripe points a fit of each artefact is attempted with (per sphere, per face).
MIN_POINTS = {"cylinder": 6, "sphere-pair": 10, "steps": 3}


def check_scan(frames, kind: str, nominal, *, source: str = "the scan") -> None:
    """Refuse a scan that cannot give the artefact's value (before anything is computed).

    Rotary artefacts need stripe pixels in two frames or more, a stepped gauge exactly one
    profile; each needs enough points (`MIN_POINTS` per sphere or face).
    """
    counts = [len(f) for f in frames]
    n, used = sum(counts), sum(c > 0 for c in counts)
    if n == 0:
        raise ValueError(f"{source} holds no stripe pixels")
    parts = 2 if kind == "sphere-pair" else (len(nominal) + 1 if kind == "steps" else 1)
    need = MIN_POINTS[kind] * parts
    if n < need:
        raise ValueError(f"{source}: too few stripe points for a {kind} ({n}, at least {need})")
    if kind == "steps" and used != 1:
        raise ValueError(f"{source}: steps are measured on one laser profile, the scan has "
                         f"{used} non-empty frames")  # fmt: skip
    if kind != "steps" and used < 2:
        raise ValueError(f"{source}: a {kind} is measured on a rotary scan: stripe pixels in "
                         f"{used} frame, at least 2 needed")  # fmt: skip


def verify_files(
    calibration: str,
    scan: str,
    artefact: str,
    *,
    observations: str | None = None,
    tolerance_um: float | None = None,
    sigma_px: float | None = None,
    delta_omega_deg: float | None = None,
) -> Verification:
    """[`verify_artefact`][] from files: CAL.json, the artefact's STRIPES.json and the
    observations CAL was calibrated from (its covariance needs them).

    **Raises:** `ValueError` / `FileNotFoundError` with a one-line reason naming the file
    or option.
    """
    import os

    from ..calibration import read_calibration
    from ..io import read_observations
    from ..io._stripes import read_stripes

    kind, nominal = parse_artefact(artefact)  # bad artefact text first: nothing read yet
    if tolerance_um is not None and not (math.isfinite(tolerance_um) and tolerance_um > 0):
        raise ValueError(f"--tolerance-um must be positive, got {tolerance_um}")
    if delta_omega_deg is not None and not (
        math.isfinite(delta_omega_deg) and delta_omega_deg != 0.0
    ):
        raise ValueError(f"--delta-omega-deg must be a non-zero angle, got {delta_omega_deg}")
    for path in (calibration, scan, observations):
        if path is not None and not os.path.exists(path):
            raise FileNotFoundError(f"{path}: no such file")
    if observations is None:
        raise ValueError(
            f"{calibration}: a calibration file holds no parameter covariance; give the "
            "observations it was calibrated from (--observations OBS.json) for U"
        )
    frames = read_stripes(scan)
    check_scan(frames, kind, nominal, source=scan)  # before the (slow) calibration load
    obs = read_observations(observations)
    cal = read_calibration(calibration, observations=obs)
    if cal.params.plane is None:
        raise ValueError(f"{calibration} is a camera-only calibration (no laser plane)")
    try:
        return verify_artefact(
            cal, frames, kind, nominal,
            tolerance_mm=None if tolerance_um is None else 1e-3 * float(tolerance_um),
            sigma_px=sigma_px,
            delta_omega=None if delta_omega_deg is None else math.radians(delta_omega_deg),
            source=calibration,
        )  # fmt: skip
    except ValueError as err:
        raise ValueError(f"{scan}: {err}") from None
