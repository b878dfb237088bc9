"""Rotary-stage calibration from a gauge scan (paper §2.4 step 4): the closed-form start
([`_stage_axis`][]) refined by Levenberg–Marquardt on the gauge residuals."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._export import exported_jit
from ...geometry._plane import LaserPlane
from ...geometry._stage import RotaryStage
from ...geometry._transforms import Pose
from ...io._observations import Observations
from ._blocks import _laser_points_safe
from ._model import CalibrationData, SystemParams, gauge_point_residuals, make_data
from ._plane import _laser_residuals_jit, _pad_pow2
from ._solve import ONE_SHOT, Fit, NotConvergedError, free_spec, least_squares
from ._stage_axis import (
    _fit_cylinder_axis,
    _section_fits,
    _Sections,
    _stage_from_sections,
    _straight_line_ms,
)


@dataclasses.dataclass(frozen=True)
class StageInit:
    """Closed-form start of the stage calibration (see [`initial_stage`][]).

    **Fields:**
    - `stage`: the table axis as a gauge-fixed `RotaryStage` (`t_m_c = (d, 0, 0)`).
    - `eccentricity_mm`: the gauge axis's offset from the table axis (measurement frame).
    - `rms_mm`: RMS in-plane distance of the gauge points from the fitted sections.
    - `sense_from_data`: whether the table's turning sense (the sign of `z_m`) came from
      the eccentric motion of the gauge; False: the convention (`z_m` towards image up).
    """

    stage: RotaryStage
    eccentricity_mm: np.ndarray
    rms_mm: float
    sense_from_data: bool


@dataclasses.dataclass(frozen=True)
class StageCalibration:
    """Rotary-stage calibration from a gauge scan (paper §2.4 step 4).

    **Fields:**
    - `stage`: `R_m_c`, `t_m_c` (gauge-fixed: `t_m_c = (d, 0, 0)`) and Δω.
    - `eccentricity_mm`: the gauge axis's offset from the table axis, measurement frame.
    - `fit`: the Levenberg–Marquardt solve.
    - `radius_rms_mm`: RMS in-plane distance of the gauge points from the gauge's section
      by the laser plane (the residual of `gauge_residuals`, in mm).
    - `initial`: the closed-form start ([`StageInit`][]).
    """

    stage: RotaryStage
    eccentricity_mm: np.ndarray
    fit: Fit
    radius_rms_mm: float
    initial: StageInit | None = None


# Backprojection onto the laser plane, compiled once per (padded) number of pixels.
_laser_points_jit = exported_jit(_laser_points_safe, compiler_options=ONE_SHOT)


def _gauge_points(camera, plane: LaserPlane, frames) -> tuple[np.ndarray, np.ndarray]:
    """All frames' stripe pixels → laser-plane points `(N, 3)` and frame indices `(N,)`,
    in ONE compiled call (pixels concatenated and padded to a power of two)."""
    uv, idx = [], []
    for i, f in enumerate(frames):
        f = np.asarray(f, dtype=np.float64).reshape(-1, 2)
        f = f[np.all(np.isfinite(f), axis=1)]
        uv.append(f)
        idx.append(np.full(len(f), i))
    uv, idx = np.concatenate(uv), np.concatenate(idx)
    n = len(uv)
    if n == 0:
        raise ValueError("the stage scan holds no stripe pixels")
    X = np.asarray(_laser_points_jit(camera, plane, jnp.asarray(_pad_pow2(uv))))[:n]
    ok = np.all(np.isfinite(X), axis=1)
    return X[ok], idx[ok]


def _usable_gauge_points(X, frame, radius, min_points=5):
    """The points of frames with `min_points` or more; `ValueError` if too few remain."""
    if not (radius > 0 and np.isfinite(radius)):
        raise ValueError(f"the gauge radius must be positive, got {radius}")
    n_per = np.bincount(frame)
    keep = n_per[frame] >= min_points
    if np.count_nonzero(keep) < 2 * min_points:
        raise ValueError(
            f"the stage scan holds too few stripe points ({len(X)}; need frames with "
            f"{min_points} or more, {2 * min_points} in all) to fit the gauge"
        )
    return X[keep], frame[keep]


def initial_stage(camera, plane: LaserPlane, obs: Observations) -> StageInit:
    """Closed-form start for the stage calibration: table axis and gauge eccentricity.

    The stripe pixels of all frames are back-projected onto the laser plane (one compiled
    call). The table axis direction is searched over a hemisphere about the laser normal
    (coarse grid, then Levenberg–Marquardt on the direction): along the right direction
    every frame's points project onto a circle of the gauge radius, with the lit side
    facing the camera ([`_section_fits`][]). The per-frame circle centres then give the
    axis position, the eccentricity (the gauge circles the table axis as it turns) and
    the turning sense.

    **Returns:** a [`StageInit`][]. Raises `ValueError` for a scan that cannot determine
    the axis (too few points, a straight stripe, no fitting cylinder facing the camera).
    """
    if obs.stage is None:
        raise ValueError('the observations hold no rotary-stage scan ("stage")')
    radius = float(obs.stage.gauge_radius_mm)
    X, frame = _gauge_points(camera, plane, obs.stage.frames)
    X, frame = _usable_gauge_points(X, frame, radius)
    sec = _Sections.of(X, frame, np.asarray(plane.n, dtype=np.float64), radius)
    min_elevation = math.radians(2.0)
    d, score = _fit_cylinder_axis(sec, min_elevation=min_elevation)
    # The axis comes from the stripe's curvature: it must stand out of the noise, i.e. a
    # straight line per frame must fit far worse than the sections.
    line_ms = _straight_line_ms(sec)
    typical = float(np.median(np.abs(_section_fits(sec, d[None])[1][0])))
    if typical > 1e-3 * radius:
        # Not a straight stripe (it fits the cylinder of its axis, to the noise): most
        # points lie far from every cylinder of this radius, so the points' scale or the
        # radius is wrong (a square size 10x off gave "the stripe is straight" at 2.7 mm
        # RMS from the cylinder and 5.6 mm from a line). The median: a few stray points
        # are no reason.
        raise ValueError(
            f"no cylinder of the gauge radius ({radius:g} mm) fits the gauge scan: its "
            f"stripe points lie a median {typical:.3g} mm from the best one "
            f"({typical / radius:.1%} of the radius; RMS {math.sqrt(max(score, 0.0)):.3g} "
            f"mm, {math.sqrt(max(line_ms, 0.0)):.3g} mm from a straight line per frame). "
            "Check the gauge radius (detect --gauge-radius-mm) and the board's square "
            "size (detect --square-mm): it sets the scale of every point"
        )
    if d @ sec.normal < math.sin(min_elevation) or line_ms < 100.0 * score:
        raise ValueError(
            "the gauge scan does not determine the table axis: the stripe is straight "
            f"(RMS {1e3 * math.sqrt(max(line_ms, 0.0)):.3g} µm from a straight line per "
            f"frame, {1e3 * math.sqrt(max(score, 0.0)):.3g} µm from the fitted cylinder; "
            "the best axis "
            f"lies {math.degrees(math.asin(min(1.0, abs(d @ sec.normal)))):.3g}° out of "
            "the laser plane). Tilt the table axis out of the laser plane."
        )
    stage, ecc, rms, from_data = _stage_from_sections(
        sec, d, math.radians(obs.stage.delta_omega_deg)
    )
    return StageInit(stage, ecc, rms, from_data)


def calibrate_stage(
    camera,
    plane: LaserPlane,
    obs: Observations,
    *,
    sigma_stripe_mm: float = 1e-3,
    freeze: Sequence[str] = (),
    max_steps: int = 200,
    throw: bool = True,
) -> StageCalibration:
    """Paper §2.4 step 4: R_m_c, t_m_c (and the gauge eccentricity) from a gauge scan.

    Starts from [`initial_stage`][] and refines the table axis and the eccentricity by
    Levenberg–Marquardt on `gauge_residuals` (camera, laser plane and Δω held fixed,
    and the stage or eccentricity paths in `freeze`, e.g. `"stage.T_m_c.rotvec"`).

    **Arguments:**
    - `camera`: the calibrated camera.
    - `plane`: the calibrated laser plane.
    - `obs`: observations with a rotary-stage scan (`obs.stage`: Δω, the gauge radius
      and the stripe pixels of every frame); its board views are not used.
    - `sigma_stripe_mm`: the gauge points' noise within the laser plane (mm): the
      residuals' weight.
    - `freeze`: further stage or eccentricity paths held fixed (e.g.
      `"stage.T_m_c.rotvec"`, `"eccentricity"`).
    - `max_steps`: Levenberg–Marquardt steps.
    - `throw`: raise `NotConvergedError` if the solve does not converge.

    **Returns:** a [`StageCalibration`][] (stage, eccentricity, the solve, the gauge
    RMS in mm and the closed-form start). `ValueError` for observations without a
    stage scan or a scan that cannot determine the axis (see [`initial_stage`][]).
    """
    if obs.stage is None:
        raise ValueError('the observations hold no rotary-stage scan ("stage")')
    init = initial_stage(camera, plane, obs)
    if not obs.views:  # the stage block needs no boards; make_data wants one view
        from ...io._observations import View

        blank = View(np.full((len(obs.board_points_mm), 2), np.nan), np.zeros((0, 2)))
        obs = dataclasses.replace(obs, views=[blank])
    data = make_data(obs, sigma_stripe_mm=sigma_stripe_mm)
    poses = Pose(jnp.zeros((1, 3)), jnp.zeros((1, 3)))
    # Camera and plane are held: the gauge pixels' laser-plane points are computed once
    # and the solve minimises `gauge_residuals` on them (`gauge_point_residuals`), so
    # its compiled program holds no camera model.
    points = _GaugePoints(_plane_points(camera, plane, data.gauge), plane.n, data)
    fit = least_squares(
        _stage_residuals,
        _StageUnknowns(init.stage, jnp.asarray(init.eccentricity_mm)),
        points,
        freeze=("stage.delta_omega", *freeze),
        blocks=None,
        max_steps=max_steps,
        throw=False,
    )
    # reported over the whole parameter pytree, as the solve of `gauge_residuals` with
    # camera, poses and plane frozen (same free parameters, labels, residuals)
    full = SystemParams(camera, poses, plane, fit.params.stage, fit.params.eccentricity)
    spec = free_spec(full, ("camera", "board_poses", "plane", "stage.delta_omega", *freeze))
    fit = dataclasses.replace(fit, params=full, free_mask=spec)
    if throw and not fit.converged:
        raise NotConvergedError(f"Levenberg–Marquardt did not converge: {fit.message}", fit)
    r = np.asarray(fit.residuals) * float(data.sigma_stripe_mm)
    rms = float(np.sqrt(np.sum(r**2) / max(float(np.sum(np.asarray(data.gauge_w))), 1.0)))
    return StageCalibration(
        fit.params.stage,
        np.asarray(fit.params.eccentricity),
        fit,
        rms,
        init,
    )


class _StageUnknowns(eqx.Module):
    """What the stage solve moves: the table axis and the gauge's eccentricity."""

    stage: RotaryStage
    eccentricity: Float[Array, "2"]


class _GaugePoints(eqx.Module):
    """The stage solve's data: the gauge pixels' laser-plane points `(F, L, 3)`, the
    plane's normal and the padded observations (weights, frame indices, σ)."""

    points: Float[Array, "F L 3"]
    plane_n: Float[Array, "3"]
    data: CalibrationData


def _stage_residuals(p: _StageUnknowns, d: _GaugePoints):
    return gauge_point_residuals(
        p.stage, p.eccentricity, d.plane_n, d.points, d.data.gauge_w, d.data
    )


def _plane_points(camera, plane: LaserPlane, uv) -> jnp.ndarray:
    """Laser-plane points of the padded pixels `(F, L, 2)` (one compiled call)."""
    F, L, _ = uv.shape
    flat = np.asarray(uv).reshape(-1, 2)
    X = _laser_points_jit(camera, plane, jnp.asarray(_pad_pow2(flat)))
    return X[: F * L].reshape(F, L, 3)


def _gauge_rms(params, data) -> float:
    r = np.asarray(_laser_residuals_jit(params, data)[1]) * float(data.sigma_stripe_mm)
    n = float(np.sum(np.asarray(data.gauge_w)))
    return float(np.sqrt(np.sum(r**2) / max(n, 1.0)))
