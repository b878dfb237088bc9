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
the quadrature weights of the stop's area times the share of each node's cell that the
clear apertures pass (0 for a ray lost to TIR or a missed surface).

Quadrature ([`pupil_grid`][]): Gauss–Legendre in s = ρ² on [0, 1] (ρ the normalised stop
radius: area is uniform in s) times equally spaced azimuths. For a spot free of
vignetting the centroid is a smooth function over the stop and converges fast with the
number of rings. Where a clear aperture cuts the bundle the integrand has an edge: a
node that passes or fails as a whole makes the quadrature first order in the node
spacing, so each node's polar cell is split along the edge, linearised at the node
(`_coverage`), and the error falls with the square of the spacing.

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

from ._lens import paraxial
from ._rig import Rig, _lens_from_camera
from ._trace import aim_ray, sensor_rotation, trace

__all__ = ["PupilImage", "PupilSampling", "pupil_grid", "pupil_image", "pupil_points"]

_CHUNK = 128  # fixed batch of object points: one compilation serves every scene


class PupilSampling(eqx.Module):
    """Quadrature nodes on the unit disk (the normalised aperture stop) and their weights.

    **Fields:** `points` `(k, 2)`; `weights` `(k,)`, non-negative, summing to 1 (nodes of
    weight 0 are padding and carry no light); `cells` `(k, 3)`: each node's share of the
    disk as a polar cell, `(ρ_in, ρ_out, Δa)` (inner and outer radius, angular width in
    radians; zeros for padding), used to split a cell that a clear aperture's edge cuts.
    """

    points: Float[Array, "k 2"]
    weights: Float[Array, " k"]
    cells: Float[Array, "k 3"]

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
        cells = jnp.concatenate([self.cells, jnp.zeros((size - k, 3))])
        return PupilSampling(pts, jnp.concatenate([self.weights, jnp.zeros(size - k)]), cells)


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
    # Each ring's cell is the annulus between the partial sums of the weights (Gauss
    # nodes interlace with them), so the cells tile the disk with the nodes' areas.
    edges = np.sqrt(np.clip(np.concatenate([[0.0], np.cumsum(w)]), 0.0, 1.0))
    edges[-1] = 1.0
    pts, wts, cells = [], [], []
    for i in range(rings):
        rho = math.sqrt(s[i])
        a = (np.arange(spokes) + 0.5 * (i % 2)) * (2.0 * math.pi / spokes)
        pts.append(np.stack([rho * np.cos(a), rho * np.sin(a)], axis=-1))
        wts.append(np.full(spokes, w[i] / spokes))
        cells.append(np.tile([edges[i], edges[i + 1], 2.0 * math.pi / spokes], (spokes, 1)))
    return PupilSampling(*(jnp.asarray(np.concatenate(v)) for v in (pts, wts, cells)))


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


def _edge_ray(rig: Rig, x_c: Float[Array, "3"], stop_xy: Float[Array, "2"]):
    """The ray from `x_c` through `stop_xy`, traced without clipping: (p, d, ok, ρ²), the
    exit point and direction (lens coordinates), whether it passed every surface (no TIR
    or miss; clear apertures not applied) and its squared height at each surface."""
    par = paraxial(rig.lens)
    surf = rig.lens.surfaces()
    x_l = _lens_from_camera(x_c, par.z_principal_image)
    d, ok = aim_ray(surf, x_l, stop_xy, par.z_entrance_pupil, par.entrance_pupil_magnification)
    tr = trace(surf, x_l, d, clip=False)
    rho2 = tr.points[:, 0] ** 2 + tr.points[:, 1] ** 2
    return tr.point, tr.direction, ok & tr.ok, rho2


def _straight_edge_share(x, a, b):
    """Share of a rectangle on the near side of a straight edge at signed distance `x`
    from its centre, the rectangle's sides projecting onto the edge's normal as widths
    `a >= b >= 0`: the distribution function of the sum of two uniform variables on
    [−a/2, a/2] and [−b/2, b/2] (quadratic, linear, quadratic pieces)."""
    h = 0.5 * (a + b)
    k = 0.5 * (a - b)
    ab2 = 2.0 * jnp.maximum(a * b, 1e-300)
    lower = (x + h) ** 2 / ab2
    upper = 1.0 - (h - x) ** 2 / ab2
    middle = (x + 0.5 * a) / jnp.maximum(a, 1e-300)
    share = jnp.where(x <= -k, lower, jnp.where(x < k, middle, upper))
    return jnp.where(x <= -h, 0.0, jnp.where(x >= h, 1.0, share))


def _coverage(rig: Rig, x_c, node, cell, sd):
    """Exit ray of the node `node` (normalised stop coordinates) and the share of its
    polar cell `cell = (ρ_in, ρ_out, Δa)` that the clear apertures let through.

    A pass/fail test of the node alone makes the quadrature first order in the node
    spacing where a clear aperture cuts the bundle. Instead each surface's edge (not the
    stop's: the cells tile the stop's disk exactly) is linearised at the node in the
    normalised stop coordinates: a straight line at signed distance
    δ = (r² − ρ²) / |∇ρ²| along the unit normal g = ∇ρ² / |∇ρ²| (ρ² the ray's squared
    height on the surface, r its clear semi-diameter; ∇ by forward-mode autodiff through
    the aimed trace). The cell, taken as the rectangle of its radial and arc extents about
    the node, passes the share of its area on the clear side of that line
    ([`_straight_edge_share`][]: exact for a straight edge, 1 where the edge misses the
    cell, 0 where the cell lies beyond it); the surfaces' smallest share counts.
    """
    stop = rig.lens.stop

    def rho2(n):
        return _edge_ray(rig, x_c, n * sd)[3]

    p, d, ok, r2 = _edge_ray(rig, x_c, node * sd)
    grad = jax.jacfwd(rho2)(node)  # (surfaces, 2)
    gnorm = jnp.sqrt(jnp.maximum(jnp.sum(grad**2, axis=-1), 1e-300))  # no NaN derivative
    has = gnorm > 1e-150
    g = grad / jnp.where(has, gnorm, 1.0)[:, None]
    sds = rig.lens.semi_diameters
    finite = jnp.isfinite(sds) & (jnp.arange(sds.shape[0]) != stop)
    delta = (jnp.where(finite, sds, 0.0) ** 2 - r2) / jnp.where(has, gnorm, 1.0)
    # The cell about the node in its local radial / tangential axes.
    rho = jnp.sqrt(jnp.sum(node * node))
    radial = node / jnp.where(rho > 0.0, rho, 1.0)
    tangential = jnp.stack([-radial[1], radial[0]])
    gr, ga = g @ radial, g @ tangential
    # The rectangle projects onto g as the sum of two uniform spreads of widths a ≥ b
    # (its radial and tangential sides times |g|'s components) about its centre c.
    wr, wa = jnp.abs(gr) * (cell[1] - cell[0]), jnp.abs(ga) * rho * cell[2]
    c = gr * (0.5 * (cell[0] + cell[1]) - rho)
    share = _straight_edge_share(delta - c, jnp.maximum(wr, wa), jnp.minimum(wr, wa))
    share = jnp.where(has, share, (delta >= 0.0).astype(share.dtype))
    return p, d, ok, jnp.min(jnp.where(finite, share, 1.0))


def _image_one(rig: Rig, x_c: Float[Array, "3"], sampling: PupilSampling):
    """Pupil image of one camera-frame point: (uv, cov, fraction, valid)."""
    sd = rig.lens.semi_diameters[rig.lens.stop]
    p, d, ok, share = jax.vmap(_coverage, in_axes=(None, None, 0, 0, None))(
        rig, x_c, sampling.points, sampling.cells, sd
    )
    q, hit = jax.vmap(rig._hit_sensor, in_axes=(0, 0, None, None, None))(
        p, d, rig.z0, rig.phi, rig.theta
    )
    local = (q - jnp.stack([0.0, 0.0, -rig.z0])) @ sensor_rotation(rig.phi, rig.theta)[:, :2]
    px = local / jnp.stack([rig.dx, rig.dy])  # sensor-plane pixel offsets from (x0, y0)
    w = jnp.where(ok & hit, sampling.weights * share, 0.0)
    px = jnp.where((w > 0.0)[:, None], px, 0.0)  # a ray that carries no light: no NaN
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
