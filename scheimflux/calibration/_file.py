"""A `Calibration` to its file and back (`scheimflux.calibration/1`; the format and its
validation: `scheimflux.io._calibration`).

Writing adds what the file needs to rebuild the calibration: the noise weights, the
rejection pass's choice and the solve statistics. Reading gives the same `Calibration`
type as `calibrate` returns. The file holds the solution (camera, laser plane, stage,
board poses), the frozen set, the noise weights and the solve statistics. Given the
observations it was computed from, that is all the in-memory `Calibration` needs: the
residual arrays (`data`) are rebuilt with the same weights, and each solve (`fits`) is
restored at the stored optimum with its free parameters. `diagnostics`,
`fit_diagnostics`, `point_uncertainty`, `length_uncertainty`, `residual_function` and
`refine` then work on a calibration read back exactly as on the one that was written.

What the file does not keep: the intermediate optimum of the camera-only solve of a
joint calibration (its restored `fits["camera"]` sits at the final camera and poses), and
the optimiser's internal state (`initial_cost` is NaN).
"""

from __future__ import annotations

import math
import os

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..io._calibration import (
    CalibrationDocument,
    CalibrationFileError,
    camera_model,
    camera_to_dict,
    jsonable,
    parse_calibration_document,
    plane_to_dict,
    pose_to_dict,
    poses_to_dict,
    read_calibration_document,
    software_version,
    stage_to_dict,
    write_calibration_document,
)
from ..io._calibration_schema import FORMAT
from ..io._observations import read_observations
from .core._model import (
    CalibrationData,
    SystemParams,
    camera_plane_residuals,
    camera_residuals,
    gauge_residuals,
    joint_residuals,
    make_data,
)
from .core._rejection import apply_left_out
from .core._result import Calibration, MissingObservations
from .core._screen import screen_field, screen_observations
from .core._solve import Fit, free_spec, split
from .core._table_block import table_target_rms_px

__all__ = ["calibration_to_dict", "parse_calibration", "read_calibration", "write_calibration"]

# Frozen in the stage solve of `calibrate_stage` (only the stage and eccentricity move).
_STAGE_FREEZE = ("camera", "board_poses", "plane", "stage.delta_omega")


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
    from .core._camera import pixel_footprint_mm

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
    document: CalibrationDocument, *, observations=None, source: str = "the calibration"
) -> Calibration:
    """Rebuild a [`Calibration`][] from a parsed file (see module docstring).

    **Arguments:** the parsed file; `observations`: the `Observations` the calibration
    was computed from (or None: `data` is then a `MissingObservations`).
    """
    params = SystemParams(
        document.camera,
        document.board_poses,
        document.plane,
        document.stage,
        None if document.eccentricity_mm is None else jnp.asarray(document.eccentricity_mm),
        document.table_pose,
    )
    model, sensor_size = document.model, document.sensor_size
    diagnostics = document.diagnostics
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
    return Calibration(
        params=params,
        model=model,
        distortion=document.distortion,
        init=str(diag.get("init") or "unknown"),
        joint="joint" in fits,
        fits=fits,
        freeze=frozen,
        reprojection_rms_px=_opt_float(diag.get("reprojection_rms_px")),
        plane_rms_mm=None if params.plane is None else _opt_float(diag.get("laser_plane_rms_mm")),
        gauge_rms_mm=None if params.stage is None else _opt_float(diag.get("gauge_rms_mm")),
        data=data,
        sensor_size=sensor_size,
        coverage=document.coverage,
        diagnostics=diag,
        raw=document.raw,
    )


# ----------------------------------------------------------------------------- writing


def _remaining_step(fit) -> dict:
    """`{"remaining_step_sigma": x}` for a solve that stopped at its step limit (how far
    from the optimum, in σ: `_solve.remaining_step_sigma`); `{}` otherwise."""
    x = (fit.stats or {}).get("remaining_step_sigma")
    return {} if x is None or not math.isfinite(x) else {"remaining_step_sigma": float(x)}


def _weights(cal) -> dict:
    """The noise weights of the residuals (to rebuild them from the observations)."""
    data = cal.data
    if not isinstance(data, CalibrationData):
        return {}
    out = {
        "sigma_corner_px": float(data.sigma_corner_px),
        "sigma_stripe_mm": float(data.sigma_stripe_mm),
        "robust": data.robust,
    }
    scale = np.asarray(data.stripe_scale)
    if np.any(scale != 1.0):  # views weighted by their own measured stripe σ
        out["stripe_sigma_scale"] = [float(x) for x in scale]
    gain = np.asarray(data.stripe_gain)
    if np.any(gain != 1.0):  # each view's σ off its board, in footprints (the gates')
        out["stripe_gain"] = [float(x) for x in gain]
    radius = None if cal.quality is None else cal.quality.rejected.get("field_radius_px")
    if radius is not None:  # calibrated inside this radius; re-applied on reading
        out["field_radius_px"] = float(radius)
    left_out = cal.left_out
    if left_out is not None:  # the rejection pass's choice, re-applied on reading
        out["left_out"] = {k: np.asarray(v, dtype=int).tolist() for k, v in left_out.items()}
    return out


def calibration_to_dict(cal, *, diagnostics: dict | None = None) -> dict:
    """A `Calibration` (from `calibrate`, or read back) as a JSON-ready dict.

    `diagnostics` adds entries to the file's diagnostics (they override the computed
    ones of the same name). A calibration read from a file keeps its file's diagnostics.
    """
    params = cal.params
    model = camera_model(params.camera)
    if model != cal.model:
        raise ValueError(f"calibration says model {cal.model!r} but holds a {model} camera")
    doc = {"format": FORMAT, "model": cal.model}
    size = cal.sensor_size
    if size is not None and all(int(v) > 0 for v in size):
        doc["sensor"] = {"width": int(size[0]), "height": int(size[1])}
    doc["camera"] = camera_to_dict(params.camera)
    if params.plane is not None:
        doc["laser_plane"] = plane_to_dict(params.plane)
    if params.stage is not None:
        if params.plane is None:
            raise ValueError("the calibration has a stage but no laser plane")
        doc["stage"] = stage_to_dict(params.stage, params.eccentricity)
    if params.board_poses is not None and np.shape(params.board_poses.rotvec)[0] > 0:
        doc["board_poses"] = poses_to_dict(params.board_poses)
    if params.table_pose is not None:
        doc["table_target_pose"] = pose_to_dict(params.table_pose)
    if cal.coverage is not None:
        doc["coverage"] = cal.coverage.to_dict()
    fits = dict(cal.fits)
    diag = dict(cal.diagnostics)  # a calibration read from a file keeps its file's
    diag.update(
        {
            "reprojection_rms_px": cal.reprojection_rms_px,
            "laser_plane_rms_mm": cal.plane_rms_mm,
            "gauge_rms_mm": cal.gauge_rms_mm,
            "init": cal.init,
            "joint": cal.joint,
            "solves": {
                name: {
                    "steps": int(fit.steps),
                    "converged": bool(fit.converged),
                    "time_s": float(fit.time_s),
                    "cost": float(fit.cost),
                    **({"message": str(fit.message)} if fit.message else {}),
                    **_remaining_step(fit),
                }
                for name, fit in fits.items()
            },
            "converged": all(bool(fit.converged) for fit in fits.values()),
            "frozen": list(cal.freeze),
            **_weights(cal),
            **_table_target(cal),
        }
    )
    diag.update(diagnostics or {})
    doc["diagnostics"] = jsonable(diag)
    doc["software"] = {"name": "scheimflux", "version": software_version()}
    return doc


def _table_target(cal) -> dict:
    """`{"table_target": {"steps", "rms_px"}}` of a stage calibrated with a target on the
    table (its data at hand), else `{}`."""
    data = cal.data  # not CalibrationData: read without observations
    table = data.table if isinstance(data, CalibrationData) else None
    if table is None or cal.params.table_pose is None:
        return {}

    steps = np.asarray(table.steps)[np.asarray(table.w).sum(axis=1) > 0]
    rms = table_target_rms_px(cal.params, cal.data)
    return {"table_target": {"steps": [int(i) for i in steps], "rms_px": rms}}


def write_calibration(
    path: str | os.PathLike, cal, *, diagnostics: dict | None = None, overwrite: bool = False
) -> None:
    """Write a calibration file atomically (never clobbers unless `overwrite`).

    The document is validated by reading it back before anything is written.
    """
    doc = calibration_to_dict(cal, diagnostics=diagnostics)
    parse_calibration(doc)  # refuse to write what could not be read back
    write_calibration_document(path, doc, overwrite=overwrite)


# ----------------------------------------------------------------------------- reading


def parse_calibration(doc, *, observations=None, source: str = "the calibration") -> Calibration:
    """Validate a decoded calibration document and rebuild its `Calibration`; raises
    `CalibrationFileError`. See [`read_calibration`][] for `observations`."""
    return restore_calibration(
        parse_calibration_document(doc), observations=observations, source=source
    )


def read_calibration(path: str | os.PathLike, *, observations=None) -> Calibration:
    """Read and validate a calibration file; errors name the file and the problem.

    **Arguments:**
    - `path`: a `scheimflux.calibration/1` file.
    - `observations`: the `Observations` (or the path of the observations file) the
      calibration was computed from. With them the result supports everything the
      in-memory calibration does — `scheimflux.diagnostics`, `point_uncertainty`,
      `residual_function` and `refine` — on the same residuals (rebuilt with the file's
      noise weights at the stored optimum). Without them `cal.data` raises a clear error
      when used.

    **Returns:** a `Calibration`, the same type `calibrate` returns, with the file's
    `diagnostics` and the whole decoded document (`raw`); `sensor_size` is None for a
    file that does not record it.

    **Raises:** `FileNotFoundError` if missing; `ValueError` (`CalibrationFileError`)
    for invalid JSON, another format, missing or unknown keys, wrong shapes or types,
    units other than the file's, values out of range, an `R_m_c` that is not a rotation,
    or an unknown model/distortion; `ValueError` for observations that do not match.
    Warns `UnconvergedCalibrationWarning` when the file records an unconverged solve.
    """
    document = read_calibration_document(path)
    if isinstance(observations, (str, os.PathLike)):
        observations = read_observations(observations)
    try:
        cal = restore_calibration(document, observations=observations, source=os.fspath(path))
    except CalibrationFileError as err:
        raise CalibrationFileError(f"{os.fspath(path)}: {err}") from None
    return cal
