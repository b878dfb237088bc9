"""Pupil-integrated imaging: the spot centroid of a ray bundle filling the aperture stop.

A sensor does not record where the chief ray lands: it records the light of the whole
bundle that passes the lens. [`pupil_image`][] traces, from each object point, rays aimed
(real-ray aiming, Newton) at the nodes of a deterministic quadrature over the aperture
stop's full area, vignettes them by every surface's clear aperture (and by TIR or a
missed surface), intersects the survivors with the tilted sensor and returns the
intensity-weighted centroid, the second moments of the spot (a Gaussian fit of the
bundle: same centroid and covariance) and the share of the light that got through.

Illumination model: the stop is uniformly illuminated (equal power per unit stop area);
cos⁴ fall-off and pupil distortion of the radiometry are not modelled, so the weights are
the quadrature weights of the stop's area, times 1 for a ray that passes and 0 for one
that is vignetted.

Quadrature ([`pupil_grid`][]): Gauss–Legendre in s = ρ² on [0, 1] (ρ the normalised stop
radius: area is uniform in s) times equally spaced azimuths. For a spot free of
vignetting the centroid is a smooth function over the stop and converges fast with the
number of rings; where a clear aperture cuts the bundle the integrand has an edge and
convergence is only first order in the node spacing.

When every ray of a bundle is vignetted the centroid is undefined: `valid` is False and
the returned centroid is a finite placeholder (never NaN inside traced code).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._rig import Rig
from ._trace import sensor_rotation

__all__ = ["PupilImage", "PupilSampling", "pupil_grid", "pupil_image", "pupil_points"]

_CHUNK = 128  # fixed batch of object points: one compilation serves every scene


class PupilSampling(eqx.Module):
    """Quadrature nodes on the unit disk (the normalised aperture stop) and their weights.

    **Fields:** `points` `(k, 2)`; `weights` `(k,)`, non-negative, summing to 1 (nodes of
    weight 0 are padding and carry no light).
    """

    points: Float[Array, "k 2"]
    weights: Float[Array, " k"]

    @property
    def size(self) -> int:
        return self.points.shape[0]

    def padded(self, size: int) -> PupilSampling:
        """The same quadrature padded with weight-0 nodes to `size` nodes (so that
        samplings of different density share one compilation)."""
        k = self.size
        if size < k:
            raise ValueError(f"cannot pad {k} pupil nodes to {size}")
        pts = jnp.concatenate([self.points, jnp.zeros((size - k, 2))])
        return PupilSampling(pts, jnp.concatenate([self.weights, jnp.zeros(size - k)]))


def pupil_grid(rings: int = 6, spokes: int | None = None) -> PupilSampling:
    """A polar Gauss quadrature over the unit disk.

    **Arguments:**
    - `rings`: Gauss–Legendre nodes in s = ρ² ∈ [0, 1] (area-uniform radial coordinate).
    - `spokes`: equally spaced azimuths per ring (default `2 rings + 1`), offset by half
      a step on alternate rings.

    **Returns:** a [`PupilSampling`][] with `rings × spokes` nodes. It integrates
    polynomials in (x, y) exactly up to degree min(2 rings − 1, spokes − 1) over the disk
    (uniform weight), so the centroid of an unvignetted spot converges quickly.
    """
    rings = int(rings)
    spokes = 2 * rings + 1 if spokes is None else int(spokes)
    if rings < 1 or spokes < 1:
        raise ValueError(f"pupil_grid needs rings >= 1 and spokes >= 1, got {rings}, {spokes}")
    s, w = np.polynomial.legendre.leggauss(rings)
    s, w = 0.5 * (s + 1.0), 0.5 * w  # nodes and weights on [0, 1]
    pts, wts = [], []
    for i in range(rings):
        rho = math.sqrt(s[i])
        a = (np.arange(spokes) + 0.5 * (i % 2)) * (2.0 * math.pi / spokes)
        pts.append(np.stack([rho * np.cos(a), rho * np.sin(a)], axis=-1))
        wts.append(np.full(spokes, w[i] / spokes))
    return PupilSampling(jnp.asarray(np.concatenate(pts)), jnp.asarray(np.concatenate(wts)))


class PupilImage(eqx.Module):
    """The pupil-integrated image of object points.

    **Fields:**
    - `uv`: intensity-weighted spot centroid (pixels), `(*batch, 2)`; a finite placeholder
      (the chief ray's hit, or the principal pixel) where `valid` is False.
    - `cov_px2`: second central moments of the spot (px²), `(*batch, 2, 2)`: the
      covariance of the Gaussian fit of the bundle.
    - `fraction`: share of the stop's light that reached the sensor (0 … 1): 1 − vignetting.
    - `valid`: some light got through and its centroid lies on the sensor.
    """

    uv: Float[Array, "*batch 2"]
    cov_px2: Float[Array, "*batch 2 2"]
    fraction: Float[Array, "*batch"]
    valid: Bool[Array, "*batch"]

    @property
    def sigma_px(self) -> Float[Array, "*batch"]:
        """Isotropic Gaussian fit: σ = sqrt(trace(cov) / 2), px."""
        tr = jnp.trace(self.cov_px2, axis1=-2, axis2=-1)
        return jnp.sqrt(jnp.maximum(0.5 * tr, 0.0))


def _image_one(rig: Rig, x_c: Float[Array, "3"], sampling: PupilSampling):
    """Pupil image of one camera-frame point: (uv, cov, fraction, valid)."""
    sd = rig.lens.semi_diameters[rig.lens.stop]
    stop_xy = sampling.points * sd
    p, d, ok = jax.vmap(rig._exit_ray, in_axes=(None, 0))(x_c, stop_xy)
    q, hit = jax.vmap(rig._hit_sensor, in_axes=(0, 0, None, None, None))(
        p, d, rig.z0, rig.phi, rig.theta
    )
    local = (q - jnp.stack([0.0, 0.0, -rig.z0])) @ sensor_rotation(rig.phi, rig.theta)[:, :2]
    px = local / jnp.stack([rig.dx, rig.dy])  # sensor-plane pixel offsets from (x0, y0)
    w = jnp.where(ok & hit, sampling.weights, 0.0)
    total = jnp.sum(w)
    some = total > 0.0
    safe = jnp.where(some, total, 1.0)
    # Offsets from (x0, y0) in px; moments about the centroid (well conditioned).
    centre = jnp.sum(px * w[:, None], axis=0) / safe
    dev = (px - centre) * jnp.sqrt(w)[:, None]
    cov = dev.T @ dev / safe
    uv = jnp.stack([rig.x0, rig.y0]) + centre
    valid = some & rig.in_bounds(uv)
    return uv, cov, total / jnp.sum(sampling.weights), valid


@eqx.filter_jit
def _image_flat(rig: Rig, x: Float[Array, "m 3"], sampling: PupilSampling):
    return jax.vmap(_image_one, in_axes=(None, 0, None))(rig, x, sampling)


def pupil_image(
    rig: Rig,
    x_c: Float[ArrayLike, "*batch 3"],
    sampling: PupilSampling | None = None,
    *,
    f_number: float | None = None,
) -> PupilImage:
    """Pupil-integrated image of camera-frame points through `rig` (jitted, differentiable).

    **Arguments:**
    - `rig`: the rig (its lens's stop semi-diameter sets the aperture).
    - `x_c`: object points in the camera frame (mm), `(*batch, 3)`.
    - `sampling`: the stop quadrature (default [`pupil_grid`][]`()`: 6 rings × 13 azimuths).
    - `f_number`: open or close the stop to this working f-number first
      ([`Lens.with_f_number`][]).

    **Returns:** a [`PupilImage`][] with batch shape `x_c.shape[:-1]`.
    """
    rig = _with_f_number(rig, f_number)
    sampling = pupil_grid() if sampling is None else sampling
    x_c = jnp.asarray(x_c)
    uv, cov, frac, ok = _image_flat(rig, x_c.reshape(-1, 3), sampling)
    batch = x_c.shape[:-1]
    return PupilImage(
        uv.reshape(*batch, 2), cov.reshape(*batch, 2, 2), frac.reshape(batch), ok.reshape(batch)
    )


def _with_f_number(rig: Rig, f_number: float | None) -> Rig:
    if f_number is None:
        return rig
    return eqx.tree_at(lambda r: r.lens, rig, rig.lens.with_f_number(float(f_number)))


def pupil_points(
    rig: Rig,
    X: np.ndarray,
    sampling: PupilSampling | None = None,
    *,
    f_number: float | None = None,
    min_fraction: float = 0.0,
    on_sensor: bool = True,
    chunk: int = _CHUNK,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Host-side batch of [`pupil_image`][] in fixed-size chunks (one compilation for any N).

    **Arguments:** `X` `(N, 3)` camera-frame points; `min_fraction`: also call a spot
    invalid when less than this share of its light passes (0: any light at all);
    `on_sensor=False`: keep centroids that fall off the sensor (renderers need them);
    `chunk`: points per compiled call.

    **Returns:** `(uv, valid, fraction, sigma_px)`: centroids `(N, 2)` (NaN where not
    valid: no light passed, too little, or off the sensor), validity `(N,)`, transmitted
    share `(N,)` and the isotropic Gaussian-fit σ `(N,)` in px.
    """
    if not 0.0 <= float(min_fraction) < 1.0:
        raise ValueError(f"min_fraction must be in [0, 1), got {min_fraction}")
    rig = _with_f_number(rig, f_number)
    sampling = pupil_grid() if sampling is None else sampling
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    n = len(X)
    uv = np.full((n, 2), np.nan)
    ok = np.zeros(n, dtype=bool)
    frac = np.zeros(n)
    sig = np.full(n, np.nan)
    if n == 0:
        return uv, ok, frac, sig
    chunk = int(chunk)
    pad = (-n) % chunk
    Xp = np.concatenate([X, np.repeat(X[-1:], pad, axis=0)]) if pad else X
    for k in range(0, len(Xp), chunk):
        img = pupil_image(rig, jnp.asarray(Xp[k : k + chunk]), sampling)
        m = min(chunk, n - k)
        uv[k : k + m] = np.asarray(img.uv)[:m]
        ok[k : k + m] = np.asarray(img.valid if on_sensor else img.fraction > 0)[:m]
        frac[k : k + m] = np.asarray(img.fraction)[:m]
        sig[k : k + m] = np.asarray(img.sigma_px)[:m]
    ok &= frac > float(min_fraction)
    uv[~ok] = np.nan
    sig[~ok] = np.nan
    return uv, ok, frac, sig
