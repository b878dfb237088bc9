"""A calibration read from its file, as a full `Calibration`.

The file holds the solution (camera, laser plane, stage, board poses), the frozen set,
the noise weights and the solve statistics. Given the observations it was computed from,
that is all the in-memory `Calibration` needs: the residual arrays (`data`) are rebuilt
with the same weights, and each solve (`fits`) is restored at the stored optimum with its
free parameters. `diagnostics`, `fit_diagnostics`, `point_uncertainty`,
`length_uncertainty`, `residual_function` and `refine` then work on a calibration read
back exactly as on the one that was written.

What the file does not keep: the intermediate optimum of the camera-only solve of a
joint calibration (its restored `fits["camera"]` sits at the final camera and poses), and
the optimiser's internal state (`initial_cost` is NaN).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..geometry._transforms import Pose
from ..io._calibration import CalibrationFileError
from ._gates import screen_field, screen_observations
from ._model import (
    CalibrationData,
    SystemParams,
    camera_plane_residuals,
    camera_residuals,
    gauge_residuals,
    joint_residuals,
    make_data,
)
from ._rejection import apply_left_out
from ._result import Calibration
from ._solve import Fit, free_spec, split

__all__ = ["LoadedCalibration", "MissingObservations", "restore_calibration"]

# Frozen in the stage solve of `calibrate_stage` (only the stage and eccentricity move).
_STAGE_FREEZE = ("camera", "board_poses", "plane", "stage.delta_omega")


class MissingObservations:
    """Stands in for `Calibration.data` when a file was read without its observations.

    Any use says what to do instead of failing somewhere deep in a solver.
    """

    def __init__(self, source: str):
        self.source = source

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        raise ValueError(
            f"{self.source} was read without its observations: residuals, diagnostics and "
            "refinement need them (read_calibration(path, observations=OBS))"
        )

    def __repr__(self) -> str:
        # shown by type checkers that stop it before use: say what to do there too
        return (
            f"MissingObservations({self.source!r}: read without its observations; use "
            "read_calibration(path, observations=OBS))"
        )


@dataclasses.dataclass(frozen=True)
class LoadedCalibration(Calibration):
    """A `Calibration` read from a `scheimflux.calibration/1` file.

    Everything of `Calibration`, plus:

    **Fields:**
    - `eccentricity_mm`: the gauge axis's offset from the table axis `(2,)`, or None.
    - `diagnostics`: the file's diagnostics (a dict: σ, warnings, gates, … as written).
    - `raw`: the whole decoded document.
    - `sensor_size`: `(width, height)` px, or None for a file that does not record it.
    - `data`: the residual arrays when read with `observations=`; otherwise a
      [`MissingObservations`][] that raises a clear error when used.
    """

    data: CalibrationData | MissingObservations | None = None
    sensor_size: tuple[int, int] | None = None
    eccentricity_mm: np.ndarray | None = None
    diagnostics: dict = dataclasses.field(default_factory=dict)
    raw: dict = dataclasses.field(default_factory=dict)

    @property
    def converged(self) -> bool:
        """Whether every solve converged, as the file records it."""
        return bool(self.diagnostics.get("converged", True))


def _opt_float(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan


def _restored_fit(fn, params, spec, data, solve: dict) -> Fit:
    x0, _, _ = split(params, spec)
    r = eqx.filter_jit(fn)(params, data) if isinstance(data, CalibrationData) else jnp.zeros(0)
    cost = _opt_float(solve.get("cost"))
    if not math.isfinite(cost) and r.size:
        cost = float(0.5 * jnp.sum(r**2))
    return Fit(
        params=params,
        converged=bool(solve.get("converged", True)),
        message=str(solve.get("message", "")),
        steps=int(solve.get("steps", 0)),
        residuals=r,
        initial_cost=math.nan,
        cost=cost,
        time_s=_opt_float(solve.get("time_s")),
        free_mask=spec,
        scale=jnp.ones_like(x0),
    )


def _check_observations(obs, n_poses: int, sensor_size, source: str) -> None:
    if n_poses == 0:
        raise ValueError(
            f"{source} holds no board poses (written by an older scheimflux): it cannot be "
            "matched to observations; re-run calibrate"
        )
    if len(obs.views) != n_poses:
        raise ValueError(
            f"{source} holds {n_poses} board poses but the observations have "
            f"{len(obs.views)} views: give the observations it was calibrated from"
        )
    if sensor_size is not None and tuple(sensor_size) != (int(obs.width), int(obs.height)):
        raise ValueError(
            f"{source} is for a {sensor_size[0]}×{sensor_size[1]} sensor but the observations "
            f"are {obs.width}×{obs.height}"
        )


def _sigma_stripe_mm(diag: dict, params, obs) -> float:
    """σ of the stripe points (mm) as the solve used it (older files: recomputed)."""
    s = diag.get("sigma_stripe_mm")
    if isinstance(s, (int, float)) and s > 0:
        return float(s)
    from ._camera import pixel_footprint_mm

    px = diag.get("sigma_stripe_px", 0.05)
    return float(px) * pixel_footprint_mm(params.camera, params.board_poses, obs)


def _per_view(diag: dict, key: str, n_views: int) -> np.ndarray | None:
    """A per-view factor list of the diagnostics as the solve used it
    (`stripe_sigma_scale`: each view's stripe σ in units of `sigma_stripe_mm`;
    `stripe_gain`: its σ off its board in pixel footprints); None: 1 for every view
    (absent: not used, or an older file)."""
    s = diag.get(key)
    if s is None:
        return None
    ok = isinstance(s, list) and len(s) == n_views
    ok = ok and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and 0 < x < math.inf for x in s
    )
    if not ok:
        raise CalibrationFileError(
            f"diagnostics.{key} must hold one positive number per view ({n_views}), got {s!r}"
        )
    return np.asarray(s, dtype=np.float64)


def _field_radius(diag: dict) -> float | None:
    """The field radius the calibration was made inside (`calibrate(max_radius_px=)`);
    None: the whole sensor."""
    r = diag.get("field_radius_px")
    if r is None:
        return None
    if not isinstance(r, (int, float)) or isinstance(r, bool) or not 0 < r < math.inf:
        raise CalibrationFileError(
            f"diagnostics.field_radius_px must be a positive number of pixels, got {r!r}"
        )
    return float(r)


def restore_calibration(
    *,
    params: SystemParams,
    model: str,
    distortion: str,
    diagnostics: dict,
    sensor_size,
    eccentricity_mm,
    raw: dict,
    observations=None,
    source: str = "the calibration",
) -> LoadedCalibration:
    """Rebuild a [`LoadedCalibration`][] from a parsed file (see module docstring).

    **Arguments:** the parsed pieces; `observations`: the `Observations` the calibration
    was computed from (or None: `data` is then a [`MissingObservations`][]).
    """
    diag = diagnostics
    frozen = tuple(str(p) for p in diag.get("frozen", ()) or ())
    solves = diag.get("solves", {}) or {}
    if not isinstance(solves, dict):
        solves = {}
    n_poses = int(np.shape(params.board_poses.rotvec)[0])
    if observations is not None:
        _check_observations(observations, n_poses, sensor_size, source)
        robust = diag.get("robust")
        robust = float(robust) if isinstance(robust, (int, float)) else None
        # as `calibrate` did: off-sensor pixels screened out, then the residual arrays
        # with the file's weights and the rejection pass's left-out observations
        observations, _ = screen_observations(observations)
        radius = _field_radius(diag)
        if radius is not None:  # calibrated inside a radius of the sensor's centre
            observations, _ = screen_field(observations, radius)
        data = make_data(
            observations,
            sigma_corner_px=float(diag.get("sigma_corner_px", 0.03)),
            sigma_stripe_mm=_sigma_stripe_mm(diag, params, observations),
            stripe_scale=_per_view(diag, "stripe_sigma_scale", len(observations.views)),
            stripe_gain=_per_view(diag, "stripe_gain", len(observations.views)),
            robust=robust,
        )
        if isinstance(diag.get("left_out"), dict):
            try:
                data = apply_left_out(data, diag["left_out"])
            except (ValueError, TypeError) as err:
                raise CalibrationFileError(f"diagnostics.left_out: {err}") from None
    else:
        data = MissingObservations(source)
    fits = {}
    cam_params = SystemParams(params.camera, params.board_poses)
    try:
        free_spec(params, frozen)
    except ValueError as err:
        raise CalibrationFileError(f"diagnostics.frozen: {err} (a {model} calibration)") from None
    for name in solves:
        if name == "camera":
            fn, p, spec = camera_residuals, cam_params, free_spec(cam_params, frozen)
        elif name == "stage" and params.stage is not None:
            fn, p, spec = gauge_residuals, params, free_spec(params, _STAGE_FREEZE)
        elif name == "joint" and params.plane is not None:
            extra = ("stage.delta_omega",) if params.stage is not None else ()
            if params.table_pose is not None and diag.get("gauge_rms_mm") is None:
                extra += ("eccentricity",)  # a table target alone: no gauge scan
            fn = joint_residuals if params.stage is not None else camera_plane_residuals
            p, spec = params, free_spec(params, frozen + extra)
        else:
            continue
        fits[name] = _restored_fit(fn, p, spec, data, solves[name])
    return LoadedCalibration(
        params=params,
        model=model,
        distortion=distortion,
        init=str(diag.get("init") or "unknown"),
        joint="joint" in fits,
        fits=fits,
        freeze=frozen,
        reprojection_rms_px=_opt_float(diag.get("reprojection_rms_px")),
        plane_rms_mm=None if params.plane is None else _opt_float(diag.get("laser_plane_rms_mm")),
        gauge_rms_mm=None if params.stage is None else _opt_float(diag.get("gauge_rms_mm")),
        data=data,
        sensor_size=None if sensor_size is None else (int(sensor_size[0]), int(sensor_size[1])),
        eccentricity_mm=eccentricity_mm,
        diagnostics=diag,
        raw=raw,
    )


def empty_poses() -> Pose:
    """No board poses (a file that does not store them)."""
    return Pose(jnp.zeros((0, 3)), jnp.zeros((0, 3)))
