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


class Status(enum.IntEnum):
    """Why a reconstructed point is invalid (0 = valid)."""

    OK = 0
    INVALID_PIXEL = 1  # non-finite pixel coordinates (e.g. a gap in the stripe)
    PARALLEL = 2  # the pixel's ray is parallel to the laser plane
    BEHIND_CAMERA = 3  # the intersection lies behind the ray's origin


class Reconstruction(eqx.Module):
    """Reconstructed points with a validity mask.

    **Fields:**
    - `points`: shape `(*batch, 3)`, mm; NaN where `valid` is False.
    - `status`: shape `(*batch,)`, int8 codes of `Status` (0 = valid).
    """

    points: Float[Array, "*batch 3"]
    status: Int8[Array, "*batch"]

    @property
    def valid(self) -> Bool[Array, "*batch"]:
        return self.status == Status.OK


# A ray counts as parallel to the plane when the cosine of the angle between the ray and
# the plane normal is below this (about 0.06 degrees from grazing).
PARALLEL_COS = 1e-3


def intersect_ray_plane(ray: Ray, plane: LaserPlane) -> tuple[Float[Array, "3"], Int8[Array, ""]]:
    """Intersection of one ray with the plane `n · X = 1`, and its `Status` code."""
    n = plane.n
    denom = jnp.dot(n, ray.direction)
    numer = 1.0 - jnp.dot(n, ray.origin)
    cos = jnp.abs(denom) / jnp.linalg.norm(n)
    parallel = cos < PARALLEL_COS
    safe = jnp.where(parallel, jnp.ones_like(denom), denom)
    t = numer / safe
    X = ray.origin + t * ray.direction
    finite = jnp.all(jnp.isfinite(ray.direction)) & jnp.all(jnp.isfinite(ray.origin))
    code = {s: jnp.int8(s) for s in Status}
    status = jnp.where(
        ~finite,
        code[Status.INVALID_PIXEL],
        jnp.where(
            parallel,
            code[Status.PARALLEL],
            jnp.where(t <= 0, code[Status.BEHIND_CAMERA], code[Status.OK]),
        ),
    )
    return jnp.where(status == code[Status.OK], X, jnp.nan), status


def _cast_floats(tree, dtype):
    return jax.tree.map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, tree)


def _pixel_to_camera(camera: AbstractCamera, plane: LaserPlane, uv):
    X, status = intersect_ray_plane(camera.backproject_one(uv), plane)
    bad_pixel = ~jnp.all(jnp.isfinite(uv))
    status = jnp.where(bad_pixel, jnp.int8(Status.INVALID_PIXEL), status)
    return X, status


@eqx.filter_jit
def _stripe_to_camera(camera, plane, uv):
    flat = uv.reshape(-1, 2)
    X, status = jax.vmap(_pixel_to_camera, in_axes=(None, None, 0))(camera, plane, flat)
    return Reconstruction(X.reshape(uv.shape[:-1] + (3,)), status.reshape(uv.shape[:-1]))


def stripe_to_camera(camera: AbstractCamera, plane: LaserPlane, uv: ArrayLike) -> Reconstruction:
    """Reconstruct laser-stripe pixels as 3-D points in the camera frame (paper eq. 3).

    Each pixel's ray (`camera.backproject`) is intersected with the laser plane
    `n · X = 1`. For `ThickLensScheimpflug` this is the paper's rational map
    `X = K_f p̃ / (n · K_f p̃)`; it works for any `AbstractCamera`.

    **Arguments:**
    - `camera`: any camera model.
    - `plane`: the laser plane in the camera frame.
    - `uv`: stripe pixels, shape `(*batch, 2)`, float32 or float64; NaN marks a missing
      pixel. Computation runs in the dtype of `uv`.

    **Returns:** a `Reconstruction` with `points` `(*batch, 3)` (mm, NaN where invalid)
    and `status` `(*batch,)` (`Status` codes: invalid pixel, ray parallel to the plane,
    intersection behind the camera).
    """
    uv = as_points(uv, 2, "uv")
    camera, plane = _cast_floats((camera, plane), uv.dtype)
    return _stripe_to_camera(camera, plane, uv)


@eqx.filter_jit
def _stripe_to_measurement(camera, plane, stage, uv, frame_index):
    rec = _stripe_to_camera(camera, plane, uv)
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
) -> Reconstruction:
    """Reconstruct stripe pixels in the measurement (rotary-table) frame (paper eq. 13).

    `X_m = R_i (R_m_c X_c + t_m_c)` with `R_i` the rotation about `z_m` by
    `frame_index · delta_omega`.

    **Arguments:**
    - `uv`: stripe pixels, shape `(*batch, 2)`, e.g. `(frames, points, 2)`.
    - `frame_index`: the frame number of each pixel: an integer, an array broadcastable
      to `uv.shape[:-1]`, or shape `(frames,)` when `uv` is `(frames, points, 2)`.

    **Returns:** a `Reconstruction` in the measurement frame.
    """
    uv = as_points(uv, 2, "uv")
    batch = uv.shape[:-1]
    fi = np.asarray(frame_index) if not isinstance(frame_index, jax.Array) else frame_index
    if fi.ndim == 1 and len(batch) >= 2 and fi.shape[0] == batch[0] and fi.shape != batch[-1:]:
        fi = fi.reshape(fi.shape + (1,) * (len(batch) - 1))
    try:
        fi = jnp.broadcast_to(jnp.asarray(fi), batch)
    except ValueError:
        raise ValueError(
            f"frame_index of shape {tuple(np.shape(frame_index))} does not match "
            f"uv of shape {tuple(uv.shape)}"
        ) from None
    camera, plane, stage = _cast_floats((camera, plane, stage), uv.dtype)
    return _stripe_to_measurement(camera, plane, stage, uv, fi)
