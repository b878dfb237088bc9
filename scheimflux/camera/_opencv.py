"""OpenCV's camera model: pinhole, 12-coefficient distortion and tilted sensor (τx, τy)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import MAX_LENGTH_MM, check_physical, check_tilt
from ._base import AbstractCamera, Ray
from ._distortion import (
    AbstractDistortion,
    NoDistortion,
    OpenCVDistortion,
    RadialTangential,
)

_DIST_LENGTHS = (4, 5, 8, 12, 14)


def opencv_tilt_matrices(
    tau_x: ArrayLike, tau_y: ArrayLike
) -> tuple[Float[Array, "3 3"], Float[Array, "3 3"]]:
    """OpenCV's tilted-sensor matrix and its inverse, as `computeTiltProjectionMatrix`.

    From OpenCV's `calib3d/src/distortion_model.hpp`:
    `matRotX = [[1, 0, 0], [0, cτx, sτx], [0, −sτx, cτx]]`,
    `matRotY = [[cτy, 0, −sτy], [0, 1, 0], [sτy, 0, cτy]]`, `R = matRotY · matRotX`,
    `matProjZ = [[R22, 0, −R02], [0, R22, −R12], [0, 0, 1]]`,
    `matTilt = matProjZ · R` and `invMatTilt = Rᵀ · [[1/R22, 0, R02/R22],
    [0, 1/R22, R12/R22], [0, 0, 1]]`.

    **Returns:** `(matTilt, invMatTilt)`, applied to `[x_d, y_d, 1]` of the distorted
    normalised point (then divided by the third component) before `fx, cx`.
    """
    tau_x = jnp.asarray(tau_x, dtype=float)
    tau_y = jnp.asarray(tau_y, dtype=float)
    cx, sx = jnp.cos(tau_x), jnp.sin(tau_x)
    cy, sy = jnp.cos(tau_y), jnp.sin(tau_y)
    o, z = jnp.ones_like(cx), jnp.zeros_like(cx)
    rot_x = jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, cx, sx]), jnp.stack([z, -sx, cx])])
    rot_y = jnp.stack([jnp.stack([cy, z, -sy]), jnp.stack([z, o, z]), jnp.stack([sy, z, cy])])
    R = rot_y @ rot_x
    proj_z = jnp.stack(
        [
            jnp.stack([R[2, 2], z, -R[0, 2]]),
            jnp.stack([z, R[2, 2], -R[1, 2]]),
            jnp.stack([z, z, o]),
        ]
    )
    inv = 1 / R[2, 2]
    inv_proj_z = jnp.stack(
        [
            jnp.stack([inv, z, inv * R[0, 2]]),
            jnp.stack([z, inv, inv * R[1, 2]]),
            jnp.stack([z, z, o]),
        ]
    )
    return proj_z @ R, R.T @ inv_proj_z


def _dehomogenise(v):
    """`v[:2] / v[2]`, with OpenCV's `v[2] ? 1/v[2] : 1` (safe for gradients too)."""
    w = jnp.where(v[2] != 0, v[2], jnp.ones_like(v[2]))
    return v[:2] / w


def opencv_dist_coeffs(dist_coeffs: ArrayLike) -> Float[Array, "14"]:
    """OpenCV's distortion vector of any length (0, 4, 5, 8, 12, 14) padded to 14.

    Order: `[k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, τx, τy]`. Shapes `(N,)`,
    `(N, 1)` and `(1, N)` are accepted, as OpenCV does. Traceable (shape checks only).
    """
    d = jnp.asarray(dist_coeffs, dtype=float)
    if d.ndim == 2 and 1 in d.shape:
        d = d.reshape(-1)
    if d.ndim != 1 or (d.size not in _DIST_LENGTHS and d.size != 0):
        raise ValueError(
            "dist_coeffs must hold 4, 5, 8, 12 or 14 numbers (OpenCV's lengths), "
            f"got shape {jnp.shape(dist_coeffs)}"
        )
    return jnp.concatenate([d, jnp.zeros(14 - d.size, d.dtype)])


class OpenCVCamera(AbstractCamera):
    """OpenCV's camera: `cv2.projectPoints` with `rvec = tvec = 0`, all 14 coefficients.

    A camera-frame point `X` maps to `x = X/Z, y = Y/Z`, then through the distortion
    (`OpenCVDistortion`: k1…k6, p1, p2, s1…s4) to `(x_d, y_d)`, then through OpenCV's
    tilted-sensor matrix (`opencv_tilt_matrices(τx, τy)`), and finally to pixels
    `u = fx x″ + cx`, `v = fy y″ + cy`. Pixel (0, 0) is the centre of the top-left pixel,
    as in OpenCV.

    `backproject` inverts this: undo `K`, undo the tilt, undistort (Newton, with a
    convergence check). Pixels whose undistortion fails give a NaN ray direction.

    **Fields:** `fx, fy, cx, cy` (px), `distortion` (any `AbstractDistortion`;
    `to_opencv` needs `OpenCVDistortion`, `RadialTangential` or `NoDistortion`),
    `tau_x, tau_y` (rad).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    distortion: AbstractDistortion
    tau_x: Float[Array, ""]
    tau_y: Float[Array, ""]

    def __init__(self, fx, fy, cx, cy, distortion=None, tau_x=0.0, tau_y=0.0):
        self.fx, self.fy, self.cx, self.cy = (jnp.asarray(v, dtype=float) for v in (fx, fy, cx, cy))
        self.distortion = OpenCVDistortion() if distortion is None else distortion
        self.tau_x = jnp.asarray(tau_x, dtype=float)
        self.tau_y = jnp.asarray(tau_y, dtype=float)

    def __check_init__(self):
        for name in ("fx", "fy", "cx", "cy", "tau_x", "tau_y"):
            if jnp.shape(getattr(self, name)) != ():
                raise ValueError(f"OpenCVCamera.{name} must be a scalar")
        for name in ("fx", "fy"):
            check_physical("OpenCVCamera", name, getattr(self, name), nonzero=True, unit="px",
                           why=" (a focal length in px; negative for an inverted image)")
        for name in ("cx", "cy"):
            check_physical("OpenCVCamera", name, getattr(self, name), max_abs=MAX_LENGTH_MM,
                           unit="px")  # fmt: skip
        check_tilt("OpenCVCamera", "tau_x", self.tau_x)
        check_tilt("OpenCVCamera", "tau_y", self.tau_y)
        if not isinstance(self.distortion, AbstractDistortion):
            raise TypeError(
                "OpenCVCamera.distortion must be an AbstractDistortion, "
                f"got {type(self.distortion).__name__}"
            )

    # --- OpenCV interchange ----------------------------------------------------------
    def parameters_ok(self):
        return super().parameters_ok() & (self.fx != 0) & (self.fy != 0)

    @classmethod
    def from_opencv(cls, camera_matrix: ArrayLike, dist_coeffs: ArrayLike) -> OpenCVCamera:
        """From OpenCV's camera matrix (3×3) and distortion vector (4, 5, 8, 12 or 14).

        The camera matrix must be `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`: OpenCV's
        `projectPoints` ignores a skew entry, so a non-zero one is refused (checked
        when the values are concrete; `from_opencv` can also be traced and
        differentiated).
        """
        K = jnp.asarray(camera_matrix, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"camera_matrix must be 3×3, got shape {K.shape}")
        if not isinstance(K, jax.core.Tracer):  # traced (differentiated): trust the layout
            Kn = np.asarray(K)
            if Kn[0, 1] != 0 or Kn[1, 0] != 0 or np.any(Kn[2] != [0, 0, 1]):
                raise ValueError(
                    "camera_matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)"
                )
        d = opencv_dist_coeffs(dist_coeffs)
        return cls(
            K[0, 0],
            K[1, 1],
            K[0, 2],
            K[1, 2],
            OpenCVDistortion.from_coefficients(d[:12]),
            d[12],
            d[13],
        )

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """`(camera_matrix (3, 3), dist_coeffs (14,))` as float64 NumPy arrays for cv2."""
        dist = self.distortion
        if isinstance(dist, OpenCVDistortion):
            coeffs = np.asarray(dist.coefficients)
        elif isinstance(dist, RadialTangential):
            coeffs = np.zeros(12)
            coeffs[:5] = [float(getattr(dist, n)) for n in ("k1", "k2", "p1", "p2", "k3")]
        elif isinstance(dist, NoDistortion):
            coeffs = np.zeros(12)
        else:
            raise TypeError(f"OpenCV has no equivalent of {type(dist).__name__}")
        K = np.array(
            [
                [float(self.fx), 0.0, float(self.cx)],
                [0.0, float(self.fy), float(self.cy)],
                [0.0, 0.0, 1.0],
            ]
        )
        return K, np.concatenate([coeffs, [float(self.tau_x), float(self.tau_y)]])

    # --- projection ------------------------------------------------------------------
    @property
    def tilt_matrices(self) -> tuple[Float[Array, "3 3"], Float[Array, "3 3"]]:
        """OpenCV's `(matTilt, invMatTilt)` of this camera's `τx, τy`."""
        return opencv_tilt_matrices(self.tau_x, self.tau_y)

    def project_one(self, X):
        z = X[2]
        xy = X[:2] / jnp.where(z != 0, z, jnp.ones_like(z))  # OpenCV: Z ? 1/Z : 1
        xy_d = self.distortion.distort(xy)
        mat_tilt, _ = self.tilt_matrices
        v = mat_tilt @ jnp.append(xy_d, jnp.ones((), xy_d.dtype))
        xy_t = _dehomogenise(v)
        uv = jnp.stack([self.fx * xy_t[0] + self.cx, self.fy * xy_t[1] + self.cy])
        valid = (z > 0) & (v[2] > 0) & jnp.all(jnp.isfinite(uv))
        return uv, valid

    def backproject_one(self, uv):
        ray, ok = self.backproject_one_with_mask(uv)
        return Ray(jnp.where(ok, ray.origin, jnp.nan), jnp.where(ok, ray.direction, jnp.nan))

    def backproject_one_with_mask(self, uv):
        # Double `where` (see AbstractCamera.backproject_one_with_mask): stand-ins for a
        # non-finite pixel and a failed undistortion keep every primal value finite.
        ok = jnp.all(jnp.isfinite(uv))
        uv = jnp.where(ok, uv, jnp.stack([self.cx, self.cy]).astype(uv.dtype))
        xy_t = jnp.stack([(uv[0] - self.cx) / self.fx, (uv[1] - self.cy) / self.fy])
        _, inv_tilt = self.tilt_matrices
        xy_d = _dehomogenise(inv_tilt @ jnp.append(xy_t, jnp.ones((), xy_t.dtype)))
        xy, ok_u = self.distortion.undistort(xy_d)  # NaN where not converged
        ok = ok & ok_u & jnp.all(jnp.isfinite(xy_d))
        xy = jnp.where(ok, xy, jnp.zeros_like(xy))
        d = jnp.append(xy, jnp.ones((), xy.dtype))
        return Ray(jnp.zeros_like(d), d / jnp.linalg.norm(d)), ok
