"""The fused reconstruction kernel: stripe pixels → 3-D points as structure-of-arrays code.

For a central camera whose pixel → ray map is a projective matrix (the paper's thick
lens without distortion, the pinhole; a distorted thick lens after its pixels are
undistorted), eq. (3) needs no ray object at all. With `h = H [u, v, 1]` (`H = B A`, the
4×3 pixel → homogeneous conjugate point matrix of eq. 11) the ray runs from the origin
through `P = h[:3] / h[3]`, and its intersection with `n · X = 1` is

    X = h[:3] / (n · h[:3])

(the `h[3]` and the norm of the direction cancel). So each pixel costs a dozen
multiply-adds and one division, computed on the `u` and `v` planes of the input
(every operation a whole-array element-wise op or a broadcast, which XLA fuses into one
loop per output: the status, then the points written straight into the `(N, 3)` array;
no per-pixel 3×3 products, no gathers, no while loop: the undistortion's fixed point is
a fixed count of unrolled steps, `camera/_thick_lens.py`). The status codes
are those of the reference (`intersect_ray_plane` on `backproject_one_with_mask`):

- `INVALID_PIXEL`: non-finite pixel, failed undistortion, `h[3] = 0` or non-finite `h`;
- `DEGENERATE_PLANE`: as `_plane_ok`;
- `PARALLEL`: `|n · d| < PARALLEL_COS |n|` for the unit direction `d`, tested squared,
  `(n · h)² < PARALLEL_COS² |n|² |h|²` (no square root; equal to the reference except
  for rounding within an ulp of the threshold);
- `BEHIND_CAMERA`: `t = h[3] |P| / (n · h) ≤ 0`, i.e. `h[3] (n · h) ≤ 0`;
- `OUTSIDE_SENSOR`: as the reference;
- `INVALID_CAMERA`: `camera.parameters_ok()` is False (every pixel), as the reference.

The points loop replaces the pixels of non-OK points by 0 before the arithmetic (double
`where`), so gradients of a masked loss stay finite, as in the reference; the status
loop reads the raw pixels (an integer status has no gradient). With distortion the
undistortion starts from finite stand-ins (the principal pixel).
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..camera._base import AbstractCamera
from ..camera._pinhole import Pinhole
from ..camera._thick_lens import ThickLensScheimpflug
from ..geometry._plane import LaserPlane
from ..geometry._stage import RotaryStage

# The reference's thresholds (kept in one place: `_reconstruct` imports them from here).
PARALLEL_COS = 1e-3
DEGENERATE_PLANE_MM = 1e-3

_OK, _INVALID, _PARALLEL, _BEHIND, _DEGENERATE, _OUTSIDE, _CAMERA = 0, 1, 2, 3, 4, 5, 6


def plane_ok(plane: LaserPlane) -> Bool[Array, ""]:
    """Whether the plane is finite and at least `DEGENERATE_PLANE_MM` from the origin."""
    n = plane.n
    nn = jnp.sum(n * n)
    return jnp.all(jnp.isfinite(n)) & (nn > 0) & (nn < 1.0 / DEGENERATE_PLANE_MM**2)


def has_fast_path(camera: AbstractCamera) -> bool:
    """Whether `camera` has the fused kernel (else the reference vmap path is used)."""
    return isinstance(camera, (ThickLensScheimpflug, Pinhole))


def _pixel_matrix(camera: AbstractCamera) -> Float[Array, "4 3"]:
    """`H` with the pixel's ray through `H[:3] p̃ / (H[3] p̃)` from the origin."""
    if isinstance(camera, ThickLensScheimpflug):
        return camera.pixel_to_object_matrix()
    # Pinhole: direction K⁻¹ p̃ (z = 1 > 0); K upper triangular, inverted in closed form.
    a, b, g, x0, y0 = camera.alpha, camera.beta, camera.gamma, camera.x0, camera.y0
    z, o = jnp.zeros_like(a), jnp.ones_like(a)
    return jnp.stack(
        [
            jnp.stack([1 / a, -g / (a * b), (g * y0 - b * x0) / (a * b)]),
            jnp.stack([z, 1 / b, -y0 / b]),
            jnp.stack([z, z, o]),
            jnp.stack([z, z, o]),
        ]
    )


def _undistorted_pixels(camera: ThickLensScheimpflug, u, v):
    """Pixels moved to where an undistorted lens would image them, and a success flag.

    The camera's own (convergence-checked) fixed point, vmapped over the pixel planes;
    `u`, `v` must be finite (stand-ins already placed)."""

    def one(uu, vv):
        uv = jnp.stack([uu, vv])
        xi, ok = camera._undistort(camera._untilted(camera.sensor_point(uv)))
        p = camera._sensor_pixel(xi)
        return p[0], p[1], ok

    shape = u.shape
    uu, vv, ok = jax.vmap(one)(u.reshape(-1), v.reshape(-1))
    return uu.reshape(shape), vv.reshape(shape), ok.reshape(shape)


def _rays(camera: AbstractCamera, plane: LaserPlane, u, v):
    """`H`, the pixel planes `su`, `sv` (the raw pixels; with distortion the undistorted
    ones, computed from finite stand-ins), the plane normal used, whether each pixel is
    finite, whether its ray is usable so far, and whether the plane is usable."""
    fin = jnp.isfinite(u) & jnp.isfinite(v)
    H = _pixel_matrix(camera)
    # Without distortion the raw pixels: a non-finite one is INVALID_PIXEL through `fin`
    # whatever its ray computes to, and the status (integer) carries no gradient; the
    # points loop selects its own inputs on the status (`_point_inputs`). Not selecting
    # stand-ins here saves two selects and the principal point's load per pixel.
    su, sv, ok = u, v, fin
    if isinstance(camera, ThickLensScheimpflug) and camera.is_distorted:
        # The undistortion needs finite input: the stand-in is the principal pixel (as
        # the reference), where h[3] ≠ 0.
        su = jnp.where(fin, u, camera.x0.astype(u.dtype))
        sv = jnp.where(fin, v, camera.y0.astype(v.dtype))
        su, sv, ok_u = _undistorted_pixels(camera, su, sv)
        ok = ok & ok_u
    p_ok = plane_ok(plane)
    n = jnp.where(p_ok, plane.n, jnp.zeros_like(plane.n).at[2].set(1.0))
    return H, su, sv, n, fin, ok, p_ok, camera.parameters_ok()


def _status(H, su, sv, n, fin, ok, p_ok, c_ok, u, v, sensor):
    """int8 `Status` codes of the pixels (`_rays`' output and the raw pixels `u`, `v`)."""
    h = [H[i, 0] * su + H[i, 1] * sv + H[i, 2] for i in range(4)]
    hh = h[0] * h[0] + h[1] * h[1] + h[2] * h[2]
    ok = ok & (h[3] != 0) & jnp.isfinite(hh) & jnp.isfinite(h[3]) & (hh > 0)
    q = n[0] * h[0] + n[1] * h[1] + n[2] * h[2]
    parallel = q * q < (PARALLEL_COS**2 * jnp.sum(n * n)) * hh
    behind = h[3] * q <= 0
    code = jnp.where(
        ~ok,
        jnp.int8(_INVALID),
        jnp.where(
            ~p_ok,
            jnp.int8(_DEGENERATE),
            jnp.where(parallel, jnp.int8(_PARALLEL), jnp.where(behind, jnp.int8(_BEHIND), 0)),
        ),
    ).astype(jnp.int8)
    if sensor is not None:
        inside = (u >= -0.5) & (u <= sensor[0] - 0.5) & (v >= -0.5) & (v <= sensor[1] - 0.5)
        code = jnp.where(fin & ~inside & (code != _INVALID), jnp.int8(_OUTSIDE), code)
    return jnp.where(c_ok, code, jnp.int8(_CAMERA))


def _affine3(M, su, sv):
    """`M [u, v, 1]` for each pixel as a `(*batch, 3)` array, written as broadcasts of the
    pixel planes against `M`'s columns: XLA lowers it to one vectorised loop over the
    output, where `jnp.stack` of three planes becomes a per-element select between them
    (measured 2-4x slower per point)."""
    return su[..., None] * M[:, 0] + sv[..., None] * M[:, 1] + M[:, 2]


def _ok_per_coordinate(code, H3):
    """`code == OK` for each of a point's three coordinates, `(*batch, 3)`, written so
    that the compiled points loop is vectorised.

    XLA:CPU emits the `(*batch, 3)` output as a loop over the pixels around a loop over
    the three coordinates. A mask that depends on the pixel only is invariant in the
    inner loop, and LLVM unswitches that loop on it: the body becomes a branch on each
    pixel's status, which the loop vectoriser does not take, so the points loop ran as
    scalar code (no vector type in its LLVM IR; the status loop, without an inner loop,
    was vectorised). Here the mask is `code + z_j == 0` with `z = isnan(H3[:, 0])` as int8,
    a per-coordinate value computed at run time, so the condition differs between the
    inner iterations and nothing is unswitched. `z` is 0 unless `H` holds a NaN, and then
    every `h` is NaN and every status `INVALID_CAMERA`; the codes are ≥ 0, so the mask is
    exactly `code == OK` in every case (bit-identical points)."""
    z = jnp.isnan(H3[:, 0]).astype(code.dtype)
    return (code[..., None] + z) == _OK


def _divide_valid(P, m, H3, su, sv, code):
    """`P / q` with `q = m · [u, v, 1]` where `code` is OK, NaN elsewhere (`q` replaced
    by 1 first: finite gradients of a masked loss). `H3` gives the mask its
    per-coordinate form (`_ok_per_coordinate`).

    `q` is evaluated for each of the three output columns (`_affine3` of a 3×3 matrix
    whose rows are all `m`) rather than once per pixel and broadcast: XLA rewrites
    `P / broadcast(q)` into `P * broadcast(1 / q)` and keeps the (expensive) reciprocal
    out of the output loop, a second pass through memory; three multiply-adds per output
    element cost less than that pass."""
    good = _ok_per_coordinate(code, H3)
    q = _affine3(jnp.stack([m, m, m]), su, sv)
    r = jnp.where(good, q, jnp.ones_like(q))
    return jnp.where(good, P / r, jnp.asarray(jnp.nan, P.dtype))


def _camera_points(H, su, sv, n, code):
    """Eq. (3) as `(*batch, 3)`: `X = h[:3] / (n · h[:3])`, NaN where `code` is not OK."""
    H3 = H[:3]
    m = n @ H3  # n · h[:3] = m · [u, v, 1]
    return _divide_valid(_affine3(H3, su, sv), m, H3, su, sv, code)


def _measurement_points(stage: RotaryStage, H, su, sv, n, code, cos, sin):
    """Eq. (13) `X_m = R_i (R_m_c X_c + t_m_c)` as `(*batch, 3)`, NaN where not OK.

    With `X_c = H[:3] p̃ / q` and `G = R_m_c H[:3]`, `X_m = (R_i G) p̃ / q + R_i t_m_c`:
    one affine map of the pixel per frame, divided once. `R_i` turns about z by `i Δω`;
    `cos`, `sin` are its cosine and sine on the frame index's own (unbroadcast) shape
    (`frame_cos_sin`), and `R_i G` is written as `c G_α + s G_β + G_γ` (the rows of `G`
    that the cosine, the sine and neither multiply), all broadcasts against the output
    so that XLA keeps one loop over it."""
    G = stage.R_m_c @ H[:3]
    t = stage.t_m_c
    z = jnp.zeros_like(G[0])
    c, s = cos[..., None, None], sin[..., None, None]
    W = c * jnp.stack([G[0], G[1], z]) + s * jnp.stack([-G[1], G[0], z])
    W = W + jnp.stack([z, z, G[2]])  # (*frames, 3, 3): R_i G
    zt = jnp.zeros_like(t[0])
    T = c[..., 0] * jnp.stack([t[0], t[1], zt]) + s[..., 0] * jnp.stack([-t[1], t[0], zt])
    T = T + jnp.stack([zt, zt, t[2]])  # (*frames, 3): R_i t_m_c
    P = su[..., None] * W[..., 0] + sv[..., None] * W[..., 1] + W[..., 2]
    return _divide_valid(P, n @ H[:3], H[:3], su, sv, code) + T


def camera_kernel(camera: AbstractCamera, plane: LaserPlane, u, v, sensor=None):
    """Eq. (3) on pixel planes `u`, `v` (same shape, any batch), structure of arrays.

    **Arguments:**
    - `camera`: a camera with `has_fast_path(camera)`.
    - `plane`: the laser plane (camera frame).
    - `u`, `v`: pixel coordinates, same shape and float dtype.
    - `sensor`: None or `(w, h)` as an array: pixels outside get `OUTSIDE_SENSOR`.

    **Returns:** `(points, status)`: `(*shape, 3)` points (mm, NaN where invalid) and
    int8 `Status` codes of the shape of `u`.
    """
    rays = _rays(camera, plane, u, v)
    code = _status(*rays, u, v, sensor)
    H, pu, pv, n = _point_inputs(camera, rays, u, v, code)
    return _camera_points(H, pu, pv, n, code), code


def _point_inputs(camera: AbstractCamera, rays, u, v, code):
    """`H`, the pixel planes the points loop reads, and the plane normal.

    Without distortion these are the raw pixels where the status is OK and 0 elsewhere,
    selected on the status that the points loop reads anyway, rather than `_rays`'
    stand-ins (where the status is OK the two are equal, elsewhere the point is NaN
    whatever its input): the points loop then need not recompute the finiteness test
    (measured: 9–13 % of the kernel's CPU time). The 0 keeps gradients finite: a parameter's
    derivative sums cotangent × pixel, and a zero cotangent times a NaN pixel would be
    NaN. With distortion the undistorted planes (computed once, in memory) are read."""
    H, su, sv, n = rays[:4]
    if isinstance(camera, ThickLensScheimpflug) and camera.is_distorted:
        return H, su, sv, n
    good = code == _OK
    return H, jnp.where(good, u, jnp.zeros_like(u)), jnp.where(good, v, jnp.zeros_like(v)), n


def cast_floats(tree, dtype):
    """Every floating leaf of `tree` in `dtype` (traced: free inside `jax.jit`)."""
    return jax.tree.map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, tree)


# `jax.jit` rather than `eqx.filter_jit`: every leaf of the cameras, planes and stages is
# an array, and the C++ dispatch of `jax.jit` costs microseconds per call, not the
# pytree filtering of `filter_jit` (which dominated below 1e5 points). The parameters are
# cast to the pixels' dtype inside the trace.
#
# One pass per output (issue 14). XLA:CPU fuses element-wise code into one loop per
# output but does not merge loops whose outputs differ in shape ((N, 3) points, (N,)
# status). The kernel as first written made three passes (q = n · h written out, the
# status reading it, the points reading both, ~50 bytes per float32 point) and built the
# points with `jnp.stack` (a per-element select, 2-4x slower than a broadcast). Now: the
# status loop reads the pixels and writes 1 byte; the points loop reads the pixels and
# the status and writes 3 floats (~30 bytes per float32 point), the ray map being a
# dozen multiply-adds, cheaper to compute in both loops than to store. With distortion
# the undistorted pixel planes are computed once, before both loops.
# `tests/test_reconstruct_fast.py` checks the loop count on the compiled program.


@jax.jit
def fast_stripe_to_camera(camera, plane, uv, sensor=None):
    """`(points (*batch, 3), status (*batch,))` from pixels `(*batch, 2)`."""
    camera, plane = cast_floats((camera, plane), uv.dtype)
    return camera_kernel(camera, plane, uv[..., 0], uv[..., 1], sensor)


@partial(jax.jit, static_argnames="dtype")
def frame_cos_sin(stage: RotaryStage, frame_index, dtype):
    """The cosine and sine of each frame's turn `frame_index · Δω`, in `dtype`, on
    `frame_index`'s own shape.

    A program of its own: in the same program as the points XLA fuses the cosine and
    sine into the points loop (they feed the per-frame matrix that the loop
    broadcasts), where they are evaluated for every output element, not once per frame:
    measured 46-49 M points per CPU-s against 180 with the turns given as inputs, at
    1000 × 1000 float32 pixels (same results, bit for bit)."""
    ang = jnp.asarray(frame_index, dtype) * stage.delta_omega.astype(dtype)
    return jnp.cos(ang), jnp.sin(ang)


@jax.jit
def fast_stripe_to_measurement_cs(camera, plane, stage, uv, cos, sin, sensor=None):
    """As `fast_stripe_to_camera`, then eq. (13) with the frames' turns given by their
    cosine and sine (`frame_cos_sin`; they broadcast to the batch)."""
    camera, plane, stage = cast_floats((camera, plane, stage), uv.dtype)
    u, v = uv[..., 0], uv[..., 1]
    rays = _rays(camera, plane, u, v)
    code = _status(*rays, u, v, sensor)
    H, pu, pv, n = _point_inputs(camera, rays, u, v, code)
    return _measurement_points(stage, H, pu, pv, n, code, cos, sin), code


def fast_stripe_to_measurement(camera, plane, stage, uv, frame_index, sensor=None):
    """As `fast_stripe_to_camera`, then eq. (13); `frame_index` broadcasts to the batch.
    Two programs: the frames' turns (`frame_cos_sin`), then the kernel."""
    cos, sin = frame_cos_sin(stage, frame_index, uv.dtype)
    return fast_stripe_to_measurement_cs(camera, plane, stage, uv, cos, sin, sensor)


# Output buffers reused (`stripe_to_camera(..., out=previous)`). XLA's CPU client takes a
# fresh allocation for every result; above glibc's mmap threshold (at most 32 MiB: a
# float32 (N, 3) result from N ≈ 2.8e6) that is fresh pages each call, and the first
# write of each 4 KiB page is a page fault: at 1e7 float32 points ~29 000 faults per
# call, measured to cost as much as the kernel's own arithmetic. Donating a previous
# result's `(points, status)` lets XLA write the new result into those (already mapped)
# buffers: same shapes and dtypes, so the outputs alias the donated inputs. They are
# unused by the computation, so `keep_unused=True` keeps them as parameters (else jit
# prunes them and the donation is silently dropped).


@partial(jax.jit, donate_argnums=(3,), keep_unused=True)
def fast_stripe_to_camera_into(camera, plane, uv, out, sensor=None):
    """`fast_stripe_to_camera`, its result written into the donated `out = (points,
    status)` (a previous result of the same shape and dtype; invalid afterwards)."""
    del out
    return fast_stripe_to_camera(camera, plane, uv, sensor)


@partial(jax.jit, donate_argnums=(6,), keep_unused=True)
def _measurement_cs_into(camera, plane, stage, uv, cos, sin, out, sensor=None):
    del out
    return fast_stripe_to_measurement_cs(camera, plane, stage, uv, cos, sin, sensor)


def fast_stripe_to_measurement_into(camera, plane, stage, uv, frame_index, out, sensor=None):
    """`fast_stripe_to_measurement` written into the donated `out = (points, status)`."""
    cos, sin = frame_cos_sin(stage, frame_index, uv.dtype)
    return _measurement_cs_into(camera, plane, stage, uv, cos, sin, out, sensor)
