"""Stripe pixels → 3-D points: ray–plane intersection (paper eq. 3) and the stage (eq. 13)."""

from __future__ import annotations

import enum

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int8

from .._checks import as_points
from ..camera._base import AbstractCamera, Ray
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage
from ._kernel import (
    DEGENERATE_PLANE_MM as DEGENERATE_PLANE_MM,
    PARALLEL_COS as PARALLEL_COS,
    fast_stripe_to_camera,
    fast_stripe_to_camera_into,
    fast_stripe_to_measurement,
    fast_stripe_to_measurement_into,
    has_fast_path,
    plane_ok as _plane_ok,
)


class Status(enum.IntEnum):
    """Why a reconstructed point is invalid (0 = valid)."""

    OK = 0
    INVALID_PIXEL = 1  # non-finite pixel coordinates (e.g. a gap in the stripe)
    PARALLEL = 2  # the pixel's ray is parallel to the laser plane
    BEHIND_CAMERA = 3  # the intersection lies behind the ray's origin
    DEGENERATE_PLANE = 4  # the laser plane is not finite or passes through the camera centre
    OUTSIDE_SENSOR = 5  # the pixel lies outside the sensor given as `sensor_size`
    INVALID_CAMERA = 6  # the camera's parameters describe no camera (f <= 0 or NaN, ...)


class Reconstruction(eqx.Module):
    """Reconstructed points with a validity mask.

    **Fields:**
    - `points`: shape `(*batch, 3)`, mm; NaN where `valid` is False.
    - `status`: shape `(*batch,)`, int8 codes of `Status` (0 = valid).
    - `in_coverage`: shape `(*batch,)`, True where the pixel lies in the sensor region
      covered by calibration data (`calibrate.Coverage`); None when no coverage was
      given. A valid point outside it is kept: the model extrapolates there (errors
      several times larger, docs/coverage.md).
    """

    points: Float[Array, "*batch 3"]
    status: Int8[Array, "*batch"]
    in_coverage: Bool[Array, "*batch"] | None = None

    @property
    def valid(self) -> Bool[Array, "*batch"]:
        return self.status == Status.OK


# PARALLEL_COS (a ray counts as parallel to the plane when the cosine of the angle between
# the ray and the plane normal is below it: about 0.06 degrees from grazing) and
# DEGENERATE_PLANE_MM (a plane closer than this to the camera centre carries no depth: 1 µm
# is below the object-side footprint of one pixel of any rig this package models, 3.45–5.5
# µm pixels at |β| ≤ 2 giving ≥ 1.7 µm) live in `_kernel.py`, shared with the fast path.


def intersect_ray_plane(
    ray: Ray, plane: LaserPlane, ray_ok: Bool[ArrayLike, ""] = True
) -> tuple[Float[Array, "3"], Int8[Array, ""]]:
    """Intersection of one ray with the plane `n · X = 1`, and its `Status` code.

    **Arguments:**
    - `ray`: one ray (its origin and unit direction, shape `(3,)` each).
    - `plane`: the laser plane.
    - `ray_ok`: False marks a ray known to be invalid (from
      `AbstractCamera.backproject_one_with_mask`).

    **Returns:** `(X (3,), status)`; `X` is NaN unless the status is `Status.OK`. Every
    intermediate value stays finite whatever the inputs (stand-ins replace invalid
    rays and planes before the arithmetic), so gradients of a loss that masks invalid
    points are finite.
    """
    finite = (
        jnp.asarray(ray_ok)
        & jnp.all(jnp.isfinite(ray.direction))
        & jnp.all(jnp.isfinite(ray.origin))
    )
    origin = jnp.where(finite, ray.origin, jnp.zeros_like(ray.origin))
    direction = jnp.where(finite, ray.direction, jnp.zeros_like(ray.direction).at[2].set(1.0))
    plane_ok = _plane_ok(plane)
    n = jnp.where(plane_ok, plane.n, jnp.zeros_like(plane.n).at[2].set(1.0))
    denom = jnp.dot(n, direction)
    numer = 1.0 - jnp.dot(n, origin)
    cos = jnp.abs(denom) / (jnp.linalg.norm(n) * jnp.linalg.norm(direction))
    parallel = cos < PARALLEL_COS
    safe = jnp.where(parallel, jnp.ones_like(denom), denom)
    t = numer / safe
    X = origin + t * direction
    code = {s: jnp.int8(s) for s in Status}
    status = jnp.where(
        ~finite,
        code[Status.INVALID_PIXEL],
        jnp.where(
            ~plane_ok,
            code[Status.DEGENERATE_PLANE],
            jnp.where(
                parallel,
                code[Status.PARALLEL],
                jnp.where(t <= 0, code[Status.BEHIND_CAMERA], code[Status.OK]),
            ),
        ),
    )
    return jnp.where(status == code[Status.OK], X, jnp.nan), status


def _cast_floats(tree, dtype):
    return jax.tree.map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, tree)


def _pixel_to_camera(camera: AbstractCamera, plane: LaserPlane, uv, sensor):
    ok_px = jnp.all(jnp.isfinite(uv))
    ray, ok = camera.backproject_one_with_mask(uv)
    X, status = intersect_ray_plane(ray, plane, ok)
    status = jnp.where(ok_px, status, jnp.int8(Status.INVALID_PIXEL))
    if sensor is not None:
        # Pixel (0, 0) is the centre of the top-left pixel: the sensor spans
        # [-0.5, w - 0.5] x [-0.5, h - 0.5].
        inside = jnp.all((uv >= -0.5) & (uv <= sensor - 0.5))
        status = jnp.where(
            ok_px & ~inside & (status != Status.INVALID_PIXEL),
            jnp.int8(Status.OUTSIDE_SENSOR),
            status,
        )
    status = jnp.where(camera.parameters_ok(), status, jnp.int8(Status.INVALID_CAMERA))
    X = jnp.where(status == Status.OK, X, jnp.nan)
    return X, status


@eqx.filter_jit
def reference_stripe_to_camera(camera, plane, uv, sensor=None):
    """The reference path: `intersect_ray_plane` on each pixel's ray, under `jax.vmap`
    (any camera). The fused kernel of `_kernel.py` must agree with it."""
    flat = uv.reshape(-1, 2)
    X, status = jax.vmap(_pixel_to_camera, in_axes=(None, None, 0, None))(
        camera, plane, flat, sensor
    )
    return Reconstruction(X.reshape(uv.shape[:-1] + (3,)), status.reshape(uv.shape[:-1]))


def _check_plane(plane, camera) -> None:  # unannotated: checked here, by hand
    if not isinstance(camera, AbstractCamera):
        raise TypeError(
            f"camera must be a camera model (an AbstractCamera), got {type(camera).__name__}"
        )
    if not isinstance(plane, LaserPlane):
        raise TypeError(f"plane must be a LaserPlane, got {type(plane).__name__}")


def _check_stage(stage) -> None:
    if not isinstance(stage, RotaryStage):
        raise TypeError(f"stage must be a RotaryStage, got {type(stage).__name__}")


def _check_frame_index(fi) -> None:
    """A concrete `frame_index` must hold finite numbers (NaN turns every point by NaN:
    NaN points that the status would call valid)."""
    if isinstance(fi, jax.core.Tracer):
        return
    if jnp.issubdtype(fi.dtype, jnp.floating) and not bool(np.all(np.isfinite(np.asarray(fi)))):
        raise ValueError("frame_index must be finite frame numbers, got NaN or infinity")


def _sensor(sensor_size, dtype):
    """`(w, h)` in pixels as an array, checked; None stays None."""
    if sensor_size is None:
        return None
    try:
        w, h = (float(v) for v in sensor_size)
    except (TypeError, ValueError):
        raise ValueError(
            f"sensor_size must be (width, height) in pixels, got {sensor_size!r}"
        ) from None
    if not (np.isfinite(w) and np.isfinite(h) and w >= 1 and h >= 1):
        raise ValueError(f"sensor_size must be two positive pixel counts, got {sensor_size!r}")
    return jnp.asarray([w, h], dtype=dtype)


def stripe_to_camera(
    camera: AbstractCamera,
    plane: LaserPlane,
    uv: ArrayLike,
    *,
    sensor_size: tuple[int, int] | None = None,
    coverage=None,
    out: Reconstruction | None = None,
) -> Reconstruction:
    """Reconstruct laser-stripe pixels as 3-D points in the camera frame (paper eq. 3).

    Each pixel's ray (`camera.backproject`) is intersected with the laser plane
    `n · X = 1`. For `ThickLensScheimpflug` this is the paper's rational map
    `X = K_f p̃ / (n · K_f p̃)`; it works for any `AbstractCamera`.

    **Arguments:**
    - `camera`: any camera model.
    - `plane`: the laser plane in the camera frame.
    - `uv`: stripe pixels, shape `(*batch, 2)`, float32 or float64 (float16 is refused:
      its spacing is 1 px above u = 1024); NaN marks a missing pixel. Computation runs
      in the dtype of `uv`.
    - `sensor_size`: optional `(width, height)` of the sensor in pixels; pixels outside
      `[-0.5, width - 0.5] × [-0.5, height - 0.5]` get `Status.OUTSIDE_SENSOR`.
    - `coverage`: optional `calibrate.Coverage` (`cal.coverage`): fills `in_coverage`
      (the points and their status are the same with or without it).
    - `out`: optional previous `Reconstruction` of the same batch shape and dtype whose
      `points` and `status` buffers are reused for the result (donated: they are
      deleted by the call; use the returned object). For repeated calls on large
      batches: a fresh result costs one page fault per 4 KiB of output on first write
      (docs/throughput.md). A buffer still viewed from NumPy is not reused (the view
      keeps its values). Ignored for cameras without the fused kernel.

    **Returns:** a `Reconstruction` with `points` `(*batch, 3)` (mm, NaN where invalid)
    and `status` `(*batch,)` (`Status` codes: invalid pixel, ray parallel to the plane,
    intersection behind the camera, degenerate plane, outside the sensor, invalid
    camera).
    """
    _check_plane(plane, camera)
    uv = as_points(uv, 2, "uv")
    sensor = _sensor(sensor_size, uv.dtype)
    if has_fast_path(camera):
        if out is None:
            rec = Reconstruction(*fast_stripe_to_camera(camera, plane, uv, sensor))
        else:
            buf = _out_buffers(out, uv)
            rec = Reconstruction(*fast_stripe_to_camera_into(camera, plane, uv, buf, sensor))
    else:
        camera, plane = _cast_floats((camera, plane), uv.dtype)
        rec = reference_stripe_to_camera(camera, plane, uv, sensor)
    return _with_coverage(rec, coverage, uv)


def _out_buffers(out, uv) -> tuple:
    """`(points, status)` of `out`, checked against the result `uv` will give."""
    if not isinstance(out, Reconstruction):
        raise TypeError(f"out must be a Reconstruction, got {type(out).__name__}")
    batch = uv.shape[:-1]
    p, s = out.points, out.status
    if not (isinstance(p, jax.Array) and isinstance(s, jax.Array)):
        raise TypeError("out.points and out.status must be JAX arrays (a previous result)")
    if p.shape != batch + (3,) or p.dtype != uv.dtype or s.shape != batch or s.dtype != jnp.int8:
        raise ValueError(
            f"out does not match the result: points {p.shape} {p.dtype}, status {s.shape} "
            f"{s.dtype}; need {batch + (3,)} {uv.dtype} and {batch} int8"
        )
    return p, s


def _with_coverage(rec: Reconstruction, coverage, uv) -> Reconstruction:
    """`rec` with `in_coverage` from a `Coverage` lookup of the pixels (outside the
    fused kernel, which stays as it is)."""
    if coverage is None:
        return rec
    return Reconstruction(rec.points, rec.status, coverage.contains(uv))


@eqx.filter_jit
def reference_stripe_to_measurement(camera, plane, stage, uv, frame_index, sensor=None):
    """The reference path of `stripe_to_measurement` (`frame_index` of the batch shape)."""
    rec = reference_stripe_to_camera(camera, plane, uv, sensor)
    to_m = stage.to_measurement
    for _ in range(uv.ndim - 1):
        to_m = jax.vmap(to_m)
    X_m = to_m(rec.points, frame_index)
    return Reconstruction(X_m, rec.status)


def stripe_to_measurement(
    camera: AbstractCamera,
    plane: LaserPlane,
    stage: RotaryStage,
    uv: ArrayLike,
    frame_index: ArrayLike,
    *,
    sensor_size: tuple[int, int] | None = None,
    coverage=None,
    out: Reconstruction | None = None,
) -> Reconstruction:
    """Reconstruct stripe pixels in the measurement (rotary-table) frame (paper eq. 13).

    `X_m = R_i (R_m_c X_c + t_m_c)` with `R_i` the rotation about `z_m` by
    `frame_index · delta_omega`.

    **Arguments:**
    - `uv`: stripe pixels, shape `(*batch, 2)`, e.g. `(frames, points, 2)`.
    - `frame_index`: the frame number of each pixel: a scalar, or an array with as many
      axes as `uv.shape[:-1]`, each of length 1 or equal to that axis, e.g.
      `np.arange(frames)[:, None]` (shape `(frames, 1)`) for one index per frame of
      `(frames, points, 2)` pixels. An index with fewer axes than the batch is refused
      rather than guessed: `(frames,)` against `(frames, points)` would be read along the
      points by NumPy's rules when `frames == points`.
    - `sensor_size`, `coverage`, `out`: as in `stripe_to_camera`.

    **Returns:** a `Reconstruction` in the measurement frame.
    """
    _check_plane(plane, camera)
    _check_stage(stage)
    uv = as_points(uv, 2, "uv")
    batch = uv.shape[:-1]
    fi = frame_index if isinstance(frame_index, jax.Array) else np.asarray(frame_index)
    if not (jnp.issubdtype(fi.dtype, jnp.integer) or jnp.issubdtype(fi.dtype, jnp.floating)):
        raise ValueError(f"frame_index must be numbers, got dtype {fi.dtype}")
    _check_frame_index(fi)
    ok = fi.ndim == 0 or (
        fi.ndim == len(batch) and all(a in (1, b) for a, b in zip(fi.shape, batch))
    )
    if not ok:
        hint = ""
        if fi.ndim == 1 and len(batch) >= 2 and fi.shape[0] == batch[0]:
            hint = "; for one index per frame pass frame_index[:, None]"
        raise ValueError(
            f"frame_index of shape {tuple(fi.shape)} does not match uv.shape[:-1] = "
            f"{tuple(batch)}: give a scalar or one axis per batch axis, each of length 1 "
            f"or the batch length{hint}"
        )
    sensor = _sensor(sensor_size, uv.dtype)
    if has_fast_path(camera):
        # Unbroadcast: the kernel takes cos/sin once per frame, then broadcasts.
        fi = jnp.asarray(fi)
        if out is None:
            res = fast_stripe_to_measurement(camera, plane, stage, uv, fi, sensor)
        else:
            buf = _out_buffers(out, uv)
            res = fast_stripe_to_measurement_into(camera, plane, stage, uv, fi, buf, sensor)
        rec = Reconstruction(*res)
        return _with_coverage(rec, coverage, uv)
    camera, plane, stage = _cast_floats((camera, plane, stage), uv.dtype)
    fi = jnp.broadcast_to(jnp.asarray(fi), batch)
    rec = reference_stripe_to_measurement(camera, plane, stage, uv, fi, sensor)
    return _with_coverage(rec, coverage, uv)
