"""Cross-validation: two calibrations from disjoint halves of the views, compared on
the reconstructed stripe points and the laser planes."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..geometry._fitting import aligned_distances
from ..io._observations import Observations
from ..reconstruct._reconstruct import stripe_to_camera
from ._calibrate import calibrate
from .core._result import Calibration


@dataclasses.dataclass(frozen=True)
class CrossValidation:
    """Two calibrations from disjoint halves of the views, compared where it matters.

    **Fields:**
    - `rms_um`, `max_um`: RMS and largest distance between the two reconstructions of
      the same stripe pixels (camera frame, µm).
    - `aligned_rms_um`, `aligned_max_um`: the same after the best rigid alignment of the
      two point sets (Kabsch): what remains is a difference of shape — the part that
      changes measured lengths — while the raw difference also holds the weakly
      determined placement of the camera frame itself (e.g. its depth: e and z0 trade
      off along the axis when the perspective is weak).
    - `n_points`: how many pixels both reconstruct.
    - `plane_angle_urad`: angle between the two laser planes (µrad).
    - `plane_distance_um`: distance of the first plane's point at the FOV centre (where
      the centre pixel's ray meets it) from the second plane (µm).
    - `views`: the view indices of each half; `calibrations`: the two `Calibration`s.
    """

    rms_um: float
    max_um: float
    aligned_rms_um: float
    aligned_max_um: float
    n_points: int
    plane_angle_urad: float
    plane_distance_um: float
    views: tuple[list[int], list[int]]
    calibrations: tuple[Calibration, Calibration]

    def summary(self) -> str:
        return (
            f"cross-validation (views {self.views[0]} vs {self.views[1]}): "
            f"{self.n_points} stripe points differ by {self.rms_um:.4g} µm RMS, "
            f"{self.max_um:.4g} µm max ({self.aligned_rms_um:.4g} / {self.aligned_max_um:.4g} µm "
            "after rigid alignment); laser planes differ by "
            f"{self.plane_angle_urad:.4g} µrad and {self.plane_distance_um:.4g} µm "
            "at the FOV centre"
        )


def _stripe_pixels(obs: Observations) -> np.ndarray:
    uv = [np.asarray(v.stripe_px, dtype=np.float64).reshape(-1, 2) for v in obs.views]
    uv = np.concatenate(uv) if uv else np.zeros((0, 2))
    return uv[np.all(np.isfinite(uv), axis=1)]


def cross_validate(obs: Observations, **calibrate_kwargs) -> CrossValidation:
    """Calibrate on the even and on the odd views separately and compare.

    Both halves are calibrated with `calibrate(half, **calibrate_kwargs)`. The rotary
    stage scan is left out of both (it is one scan that cannot be split into
    independent halves, and sharing it would correlate the two calibrations); the
    comparison is made in the camera frame, which needs no stage. Every board stripe
    pixel of the full set is reconstructed with both calibrations: on noise-free data
    from the model itself the two agree to rounding; the spread on real (noisy) data
    measures how well the calibration generalises to views it was not fitted to.

    **Arguments:**
    - `obs`: the observations, at least 6 views (3 per half) with the laser line on the
      boards.
    - `**calibrate_kwargs`: passed to [`calibrate`][] for both halves (`model`,
      `distortion`, `joint`, `throw`, ...).

    **Returns:** a [`CrossValidation`][] (point and plane differences, the halves and
    both calibrations).
    """
    n = len(obs.views)
    halves = (list(range(0, n, 2)), list(range(1, n, 2)))
    if min(len(h) for h in halves) < 3:
        raise ValueError(f"cross-validation needs at least 6 views (3 per half), got {n}")
    cals = tuple(
        calibrate(
            dataclasses.replace(obs, views=[obs.views[i] for i in h], stage=None),
            **calibrate_kwargs,
        )
        for h in halves
    )
    uv = _stripe_pixels(obs)
    Xa = np.asarray(stripe_to_camera(cals[0].camera, cals[0].plane, uv).points)
    Xb = np.asarray(stripe_to_camera(cals[1].camera, cals[1].plane, uv).points)
    ok = np.all(np.isfinite(Xa) & np.isfinite(Xb), axis=1)
    d = np.linalg.norm(Xa[ok] - Xb[ok], axis=1) * 1e3
    da = aligned_distances(Xa[ok], Xb[ok]) * 1e3
    na = np.asarray(cals[0].plane.normal)
    nb = np.asarray(cals[1].plane.normal)
    angle = math.atan2(float(np.linalg.norm(np.cross(na, nb))), float(abs(na @ nb)))
    centre = np.array([[(obs.width - 1) / 2, (obs.height - 1) / 2]])
    Xc = np.asarray(stripe_to_camera(cals[0].camera, cals[0].plane, centre).points)
    dist = float(np.abs(np.asarray(cals[1].plane.signed_distance(jnp.asarray(Xc))))[0])
    return CrossValidation(
        rms_um=float(np.sqrt(np.mean(d**2))) if d.size else math.nan,
        max_um=float(d.max()) if d.size else math.nan,
        aligned_rms_um=float(np.sqrt(np.mean(da**2))) if da.size else math.nan,
        aligned_max_um=float(da.max()) if da.size else math.nan,
        n_points=int(ok.sum()),
        plane_angle_urad=angle * 1e6,
        plane_distance_um=dist * 1e3,
        views=halves,
        calibrations=cals,
    )
