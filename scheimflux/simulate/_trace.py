"""Differentiable sequential ray tracing through spherical and plane surfaces.

Lens coordinates: millimetres, object on the left, light travelling towards +z, the first
vertex at z = 0. Every function here is written for *one* ray and batched with `jax.vmap`;
none branches in Python on array values, so all of them can be jitted and differentiated.

Rays that miss a surface, are totally internally reflected, fall outside a clear aperture or
would have to travel backwards are not turned into NaNs: they carry `valid = False` and
finite (meaningless) coordinates, so that masks, means and gradients stay finite.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

_TINY = 1e-300


class Surfaces(eqx.Module):
    """A sequence of rotationally symmetric surfaces on the z axis (lens coordinates).

    **Fields:**

    - `z`: vertex positions (mm), shape `(n,)`.
    - `curvature`: 1 / radius (1/mm); 0 for a plane, shape `(n,)`.
    - `n_before`, `n_after`: refractive index of the medium before / after each surface.
    - `semi_diameter`: clear semi-aperture of each surface (mm); `inf` means unlimited.
    - `stop`: index of the aperture stop surface (static).
    """

    z: Float[Array, " n"]
    curvature: Float[Array, " n"]
    n_before: Float[Array, " n"]
    n_after: Float[Array, " n"]
    semi_diameter: Float[Array, " n"]
    stop: int = eqx.field(static=True)

    def __getitem__(self, item: slice) -> Surfaces:
        """A contiguous, statically sliced subsequence (the stop index is re-based)."""
        start = item.start or 0
        return Surfaces(
            self.z[item],
            self.curvature[item],
            self.n_before[item],
            self.n_after[item],
            self.semi_diameter[item],
            self.stop - start,
        )


class Trace(eqx.Module):
    """The result of tracing one ray through a sequence of surfaces.

    **Fields:**

    - `points`: intersection point with each surface, shape `(n, 3)`.
    - `directions`: unit direction after each surface, shape `(n, 3)`.
    - `valid`: whether the ray is still valid after each surface, shape `(n,)`
      (cumulative: once invalid, always invalid).
    """

    points: Float[Array, "n 3"]
    directions: Float[Array, "n 3"]
    valid: Bool[Array, " n"]

    @property
    def point(self) -> Float[Array, "3"]:
        """Point on the last surface."""
        return self.points[-1]

    @property
    def direction(self) -> Float[Array, "3"]:
        """Direction after the last surface."""
        return self.directions[-1]

    @property
    def ok(self) -> Bool[Array, ""]:
        """Whether the ray passed all surfaces."""
        return self.valid[-1]


def _safe_norm(v: Float[Array, "3"]) -> Float[Array, ""]:
    sq = jnp.sum(v * v)
    pos = sq > _TINY
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def normalize(v: Float[ArrayLike, "3"]) -> Float[Array, "3"]:
    """`v / |v|`, with a finite value and gradient at `v = 0`."""
    v = jnp.asarray(v)
    norm = _safe_norm(v)
    return v / jnp.where(norm > 0, norm, 1.0)


def refract(
    direction: Float[ArrayLike, "3"],
    normal: Float[ArrayLike, "3"],
    n1: Float[ArrayLike, ""],
    n2: Float[ArrayLike, ""],
) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
    """Vector form of Snell's law.

    **Arguments:**

    - `direction`: unit direction of the incident ray.
    - `normal`: unit surface normal (either orientation).
    - `n1`, `n2`: refractive indices before and after the surface.

    **Returns:**

    `(refracted_direction, ok)`; `ok` is False on total internal reflection (the direction
    is then the incident one, to keep values finite).
    """
    d = jnp.asarray(direction)
    nrm = jnp.asarray(normal)
    mu = jnp.asarray(n1) / jnp.asarray(n2)
    cos_i = jnp.dot(d, nrm)
    k = 1.0 - mu**2 * (1.0 - cos_i**2)
    ok = k >= 0.0
    sqrt_k = jnp.sqrt(jnp.where(ok, k, 1.0))
    # sign(cos_i) keeps the refracted ray on the far side whichever way the normal points.
    sign = jnp.where(cos_i >= 0.0, 1.0, -1.0)
    out = mu * d + (sign * sqrt_k - mu * cos_i) * nrm
    return jnp.where(ok, out, d), ok


def intersect_surface(
    origin: Float[ArrayLike, "3"],
    direction: Float[ArrayLike, "3"],
    z_vertex: Float[ArrayLike, ""],
    curvature: Float[ArrayLike, ""],
) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, ""], Bool[Array, ""]]:
    """Intersect a ray with a sphere (or plane, `curvature = 0`) with vertex on the z axis.

    Uses the cancellation-free form t = F / (G + sqrt(G² − c F)) of the near root, which is
    exact for planes too. The surface is c (x² + y² + z'²) − 2 z' = 0, z' = z − z_vertex.

    **Returns:**

    `(point, unit_normal, t, ok)`: the normal is (−c x, −c y, 1 − c z′), oriented towards +z
    near the vertex; `ok` is False when the ray misses the sphere.
    """
    p = jnp.asarray(origin)
    d = jnp.asarray(direction)
    c = jnp.asarray(curvature)
    rel = p - jnp.stack([0.0, 0.0, jnp.asarray(z_vertex)])
    f = c * jnp.dot(rel, rel) - 2.0 * rel[2]
    g = d[2] - c * jnp.dot(rel, d)
    disc = g * g - c * f * jnp.dot(d, d)
    hit = disc >= 0.0
    denom = g + jnp.sqrt(jnp.where(hit, disc, 0.0))
    hit = hit & (jnp.abs(denom) > 1e-300)
    t = f / jnp.where(hit, denom, 1.0)
    q = rel + t * d
    nrm = jnp.stack([-c * q[0], -c * q[1], 1.0 - c * q[2]])
    return q + (p - rel), normalize(nrm), t, hit


def intersect_plane(
    origin: Float[ArrayLike, "3"],
    direction: Float[ArrayLike, "3"],
    point: Float[ArrayLike, "3"],
    normal: Float[ArrayLike, "3"],
) -> tuple[Float[Array, "3"], Float[Array, ""], Bool[Array, ""]]:
    """Intersect a ray with the plane through `point` with normal `normal`.

    **Returns:** `(point, t, ok)`; `ok` is False for rays parallel to the plane.
    """
    p = jnp.asarray(origin)
    d = jnp.asarray(direction)
    nrm = jnp.asarray(normal)
    denom = jnp.dot(d, nrm)
    ok = jnp.abs(denom) > 1e-300
    t = jnp.dot(jnp.asarray(point) - p, nrm) / jnp.where(ok, denom, 1.0)
    return p + t * d, t, ok


@eqx.filter_jit
def trace(
    surfaces: Surfaces,
    origin: Float[ArrayLike, "3"],
    direction: Float[ArrayLike, "3"],
    *,
    clip: bool = True,
    unroll: bool = False,
) -> Trace:
    """Trace one ray sequentially through `surfaces`.

    **Arguments:**

    - `surfaces`: the surfaces, in order.
    - `origin`: a point on the incoming ray (lens coordinates, mm), before the first surface.
    - `direction`: its direction (need not be unit length).
    - `clip`: whether the clear semi-diameters vignette the ray.
    - `unroll`: unroll the loop over surfaces (`lax.scan(unroll=True)`): larger programs,
      but much faster XLA compilation when the trace is nested in loops and autodiff.

    **Returns:** a [`Trace`][] with the intersection points, directions and validity after
    every surface.
    """
    p0 = jnp.asarray(origin)
    d0 = normalize(direction)

    def step(carry, s):
        p, d, ok = carry
        z, c, n1, n2, sd = s
        q, nrm, t, hit = intersect_surface(p, d, z, c)
        d2, no_tir = refract(d, nrm, n1, n2)
        ok = ok & hit & no_tir & (t >= -1e-9)
        if clip:
            ok = ok & (q[0] ** 2 + q[1] ** 2 <= sd**2)
        return (q, d2, ok), (q, d2, ok)

    xs = (
        surfaces.z,
        surfaces.curvature,
        surfaces.n_before,
        surfaces.n_after,
        surfaces.semi_diameter,
    )
    _, (points, directions, valid) = jax.lax.scan(
        step, (p0, d0, jnp.asarray(True)), xs, unroll=unroll
    )
    return Trace(points, directions, valid)


@eqx.filter_jit
def aim_ray(
    surfaces: Surfaces,
    origin: Float[ArrayLike, "3"],
    stop_xy: Float[ArrayLike, "2"],
    z_aim: Float[ArrayLike, ""],
    aim_scale: Float[ArrayLike, ""],
    *,
    iterations: int = 8,
) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
    """Direction of the ray from `origin` that crosses the stop plane at `stop_xy`.

    The direction is parametrised by the point (a, b, z_aim) it aims at (use the paraxial
    entrance pupil: `z_aim` its position, `aim_scale` its magnification, so that the
    paraxial guess (a, b) = aim_scale · stop_xy is already close). A fixed number of Newton
    iterations (2 × 2 Jacobian by forward-mode autodiff) is followed by one more Newton
    step whose Jacobian is held constant: its value is the converged solution and its
    derivative is exactly the implicit-function-theorem derivative, so gradients with
    respect to the surfaces and to `origin` are those of the exact root, not of the
    unrolled iteration.

    **Returns:** `(direction, ok)`: unit direction and whether the final ray reaches the
    stop (no TIR or miss on the way; clear apertures are not applied while aiming).
    """
    p = jnp.asarray(origin)
    target = jnp.asarray(stop_xy)
    front = surfaces[: surfaces.stop + 1]

    def direction_of(ab, p):
        return normalize(jnp.concatenate([ab, jnp.reshape(z_aim, (1,))]) - p)

    def residual(ab, p, front):
        tr = trace(front, p, direction_of(ab, p), clip=False)
        return tr.point[:2] - target, tr.ok

    def newton(ab, p, front):
        """Inverse Jacobian and residual at `ab`."""
        jac, (r, _) = jax.jacfwd(lambda x: _dup(residual(x, p, front)), has_aux=True)(ab)
        det = jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]
        det = jnp.where(jnp.abs(det) > 1e-300, det, 1.0)
        inv = jnp.stack([jnp.stack([jac[1, 1], -jac[0, 1]]), jnp.stack([-jac[1, 0], jac[0, 0]])])
        return inv / det, r

    p_sg, front_sg = jax.lax.stop_gradient((p, front))

    def body(_, carry):
        ab, _ = carry
        inv, r = newton(ab, p_sg, front_sg)
        return ab - inv @ r, inv

    ab0 = jax.lax.stop_gradient(jnp.asarray(aim_scale) * target)
    ab_sg, inv = jax.lax.fori_loop(0, iterations, body, (ab0, jnp.eye(2)))
    # Implicit-function step: Jacobian (from the last, converged iteration) held fixed.
    ab_sg, inv = jax.lax.stop_gradient((ab_sg, inv))
    r, ok = residual(ab_sg, p, front)
    ab = ab_sg - inv @ r
    return direction_of(ab, p), ok


def _dup(out):
    r, ok = out
    return r, (r, ok)


def sensor_normal(phi: Float[ArrayLike, ""], theta: Float[ArrayLike, ""]) -> Float[Array, "3"]:
    """Third column of R_y(θ) R_x(φ): the normal of a sensor tilted by (φ, θ)."""
    phi = jnp.asarray(phi)
    theta = jnp.asarray(theta)
    return jnp.stack([jnp.cos(phi) * jnp.sin(theta), -jnp.sin(phi), jnp.cos(phi) * jnp.cos(theta)])


def sensor_rotation(phi: Float[ArrayLike, ""], theta: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """R_s = R_y(θ) R_x(φ) (DESIGN.md, eqs. 5–8)."""
    phi = jnp.asarray(phi)
    theta = jnp.asarray(theta)
    cp, sp, ct, st = jnp.cos(phi), jnp.sin(phi), jnp.cos(theta), jnp.sin(theta)
    one, zero = jnp.ones_like(cp), jnp.zeros_like(cp)
    r_x = jnp.stack(
        [jnp.stack([one, zero, zero]), jnp.stack([zero, cp, -sp]), jnp.stack([zero, sp, cp])]
    )
    r_y = jnp.stack(
        [jnp.stack([ct, zero, st]), jnp.stack([zero, one, zero]), jnp.stack([-st, zero, ct])]
    )
    return r_y @ r_x
