"""Initial values: from nominal device values (paper step 2) or in closed form."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from numbers import Real

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._export import exported_jit
from ...camera._pinhole import Pinhole
from ...camera._thick_lens import ThickLensScheimpflug
from ...geometry._transforms import Pose, rotation_matrix
from ...io._observations import Nominal
from ._solve import ONE_SHOT, least_squares
from ._zhang import (
    board_homographies,
    centred_intrinsics,
    pose_from_homography,
    zhang_intrinsics,
)


def require_pixel_pitch(obs) -> tuple[float, float]:
    """The observations' pixel pitch `(dx, dy)` in mm; a clear error when it is absent.

    The thick-lens model's image-side lengths (f, e, z0) are in mm: without the sensor's
    pixel pitch they are undetermined, and no default is assumed.
    """
    pitch = getattr(obs, "pixel_pitch_mm", None)
    if pitch is None:
        raise ValueError(
            "the thick-lens model needs the sensor's pixel pitch: give --pixel-pitch-mm "
            "(calibrate or detect; library: with_nominal(obs, pixel_pitch_mm=...)), "
            "or use --model opencv or pinhole"
        )
    dx, dy = (float(p) for p in pitch)
    if not (math.isfinite(dx) and math.isfinite(dy) and dx > 0 and dy > 0):
        raise ValueError(f"the pixel pitch must be positive and finite, got {tuple(pitch)} mm")
    return dx, dy


def _positive(name: str, v) -> float:
    v = float(v)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be positive and finite, got {v}")
    return v


def with_nominal(
    obs,
    *,
    pixel_pitch_mm: Real | Sequence[Real] | None = None,
    focal_length_mm: Real | None = None,
    magnification: Real | None = None,
    tilt_deg: Sequence[Real] | None = None,
):
    """The observations with nominal device values given here overriding the file's.

    **Arguments:**
    - `obs`: `Observations`.
    - `pixel_pitch_mm`: one number (square pixels) or `(dx, dy)`, mm.
    - `focal_length_mm`, `magnification` (|β| > 0), `tilt_deg` `(φ, θ)`: the nominal
      values the thick-lens initialisation reads (`obs.nominal`).

    Values left at None keep the file's. **Returns:** a new `Observations`.
    """
    changes = {}
    if pixel_pitch_mm is not None:
        p = np.atleast_1d(np.asarray(pixel_pitch_mm, dtype=np.float64))
        if p.shape not in ((1,), (2,)):
            raise ValueError(f"pixel_pitch_mm must be one number or (dx, dy), got {pixel_pitch_mm}")
        p = np.broadcast_to(p, (2,))
        changes["pixel_pitch_mm"] = (
            _positive("pixel_pitch_mm", p[0]),
            _positive("pixel_pitch_mm", p[1]),
        )
    nom = obs.nominal if obs.nominal is not None else Nominal()
    new = {}
    if focal_length_mm is not None:
        new["focal_length_mm"] = _positive("focal_length_mm", focal_length_mm)
    if magnification is not None:
        new["magnification"] = _positive("magnification", magnification)
    if tilt_deg is not None:
        t = tuple(float(a) for a in tilt_deg)
        if len(t) != 2 or not all(math.isfinite(a) and abs(a) < 90 for a in t):
            raise ValueError(f"tilt_deg must be (phi, theta) within ±90°, got {tilt_deg}")
        new["tilt_deg"] = t
    if new:
        changes["nominal"] = dataclasses.replace(nom, **new)
    return dataclasses.replace(obs, **changes) if changes else obs


def _stack_poses(Rs, ts) -> Pose:
    return Pose(
        jnp.stack([Pose.from_matrix(R, t).rotvec for R, t in zip(Rs, ts)]),
        jnp.asarray(np.stack(ts)),
    )


@exported_jit(compiler_options=ONE_SHOT)
def _directions(camera, uv):
    """The unit ray directions of pixels `uv` `(N, 2)`, compiled (eagerly, every
    operation of the back-projection would be a program of its own, per shape)."""
    return camera.backproject(uv).direction


def poses_for_central_camera(camera, obs) -> Pose:
    """Board poses by homography for any central camera (rays from the origin).

    Each detected corner's ray direction is normalised to z = 1; the board-to-normalised
    homography then gives the pose as for a calibrated pinhole.
    """
    corners, mask = obs.corners()
    board_xy = obs.board_points_mm[:, :2]
    # every view's corners in one compiled call (undetected ones at the image centre,
    # not used)
    centre = np.array([(obs.width - 1) / 2, (obs.height - 1) / 2])
    uv_all = np.where(mask[..., None], corners, centre).reshape(-1, 2)
    d_all = np.asarray(_directions(camera, jax.device_put(uv_all))).reshape(*mask.shape, 3)
    Rs, ts = [], []
    for i, (d, m) in enumerate(zip(d_all, mask)):
        if m.sum() < 4:
            raise ValueError(f"view {i} has {int(m.sum())} detected corners; at least 4 needed")
        d = d[m]
        if np.any(d[:, 2] <= 0):
            raise ValueError(f"view {i}: corners map behind the initial camera")
        xy = d[:, :2] / d[:, 2:]
        H, _ = cv2.findHomography(board_xy[m], xy, 0)
        if H is None:
            raise ValueError(f"view {i}: degenerate corner layout (no homography)")
        R, t = pose_from_homography(np.eye(3), H / H[2, 2])
        Rs.append(R)
        ts.append(t)
    return _stack_poses(Rs, ts)


def nominal_thick_lens(obs) -> ThickLensScheimpflug:
    """The paper's step 2: f, pixel pitch, sensor centre, adapter tilt, e = 0."""
    nom = obs.nominal
    if nom is None or nom.focal_length_mm is None or nom.magnification is None:
        raise ValueError(
            "nominal initialisation needs nominal.focal_length_mm and nominal.magnification "
            "in the observations file (or use the closed-form initialisation)"
        )
    f, m = nom.focal_length_mm, nom.magnification
    phi, theta = (math.radians(a) for a in (nom.tilt_deg or (0.0, 0.0)))
    dx, dy = require_pixel_pitch(obs)
    return ThickLensScheimpflug(
        f=f,
        e=0.0,
        z0=f * (1.0 + m),
        phi=phi,
        theta=theta,
        x0=(obs.width - 1) / 2,
        y0=(obs.height - 1) / 2,
        dx=dx,
        dy=dy,
    )


def closed_form_pinhole(obs) -> tuple[Pinhole, Pose]:
    """Zhang's closed form: pinhole K with skew and the board poses; where its five
    intrinsics are degenerate, K with the principal point at the centre and no skew
    (`_zhang.centred_intrinsics`)."""
    corners, mask = obs.corners()
    board = obs.board_points_mm
    if np.ptp(board[:, 2]) > 1e-9:
        raise ValueError("the closed-form initialisation needs a planar board (z = 0)")
    Hs = board_homographies(board[:, :2], corners, mask)
    try:
        K = zhang_intrinsics(Hs)
    except ValueError:  # e.g. strong distortion: a centred principal point, no skew
        K = centred_intrinsics(Hs, int(obs.width), int(obs.height))
    Rs, ts = [], []
    for i, H in enumerate(Hs):
        if H is None:
            raise ValueError(f"view {i} has fewer than 4 detected corners")
        R, t = pose_from_homography(K, H)
        Rs.append(R)
        ts.append(t)
    cam = Pinhole(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])
    return cam, _stack_poses(Rs, ts)


class _Conversion(eqx.Module):
    camera: ThickLensScheimpflug
    rotvec: jax.Array  # Q: pinhole frame → thick-lens frame


def _conversion_residuals(p: _Conversion, data):
    pinhole, uv = data
    Q = rotation_matrix(p.rotvec)

    def one(q):
        d_t = p.camera.backproject_one(q).direction
        d_p = Q @ pinhole.backproject_one(q).direction
        return d_t - d_p

    return (jax.vmap(one)(uv) * 1e4).reshape(-1)


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def _normalise_tilt(conv: _Conversion) -> _Conversion:
    """Bring the tilt angles into (-pi/2, pi/2).

    R_y(pi - theta) R_x(pi + phi) = R_z(pi) R_y(theta) R_x(phi), and a half-turn of the
    sensor about the optical axis is a half-turn of the camera frame, so the same camera
    is described with the small angles and the frame rotation Q turned by R_z(pi).
    """
    phi, theta = _wrap(float(conv.camera.phi)), _wrap(float(conv.camera.theta))
    Q = np.asarray(rotation_matrix(conv.rotvec))
    if math.cos(phi) < 0 and math.cos(theta) < 0:
        phi, theta = _wrap(phi - math.pi), _wrap(math.pi - theta)
        Q = np.diag([-1.0, -1.0, 1.0]) @ Q
    cam = eqx.tree_at(
        lambda c: (c.phi, c.theta), conv.camera, (jnp.asarray(phi), jnp.asarray(theta))
    )
    return _Conversion(cam, Pose.from_matrix(Q, np.zeros(3)).rotvec)


def thick_lens_from_pinhole(pinhole: Pinhole, poses: Pose, obs, *, f=None):
    """Convert a pinhole calibration into a thick-lens Scheimpflug camera.

    Both are central cameras: with f and the pixel pitch fixed and the optical axis
    through the sensor centre (the gauge choice when the tilt is unknown), the tilt, z0
    and e follow from matching the pixel rays up to a rotation of the frame.
    Returns the camera and the board poses in its frame.
    """
    dx, dy = require_pixel_pitch(obs)
    z_board = float(np.median(np.asarray(poses.translation)[:, 2]))
    img_dist = float(pinhole.alpha) * dx  # perpendicular distance centre–sensor (mm)
    if f is None:
        f = img_dist * z_board / (img_dist + z_board)  # thin-lens estimate
    u, v = np.meshgrid(np.linspace(0, obs.width - 1, 9), np.linspace(0, obs.height - 1, 7))
    uv = jnp.asarray(np.stack([u.ravel(), v.ravel()], -1))
    best = None
    for q in (0.0, math.pi):
        for theta0 in (0.0, -0.3, 0.3):
            cam0 = ThickLensScheimpflug(
                f=f,
                e=0.0,
                z0=img_dist,
                phi=0.0,
                theta=theta0,
                x0=(obs.width - 1) / 2,
                y0=(obs.height - 1) / 2,
                dx=dx,
                dy=dy,
            )
            p0 = _Conversion(cam0, jnp.array([0.0, 0.0, q]))
            fit = least_squares(
                _conversion_residuals,
                p0,
                (pinhole, uv),
                freeze=("camera.f", "camera.e", "camera.x0", "camera.y0", "camera.dx", "camera.dy"),
                throw=False,
                max_steps=100,
            )
            # Planar boards cannot tell the camera from its mirror image through the lens
            # (the world reflected in z: sensor in front of the lens, e and the tilt
            # negated, the boards behind it): the same rays to rounding (measured: costs
            # equal to 1e-13 relative on a circle-grid capture, and the start with
            # z0 = -226 mm won by rounding). Only the physical one is a start.
            if float(fit.params.camera.z0) > 0 and (best is None or fit.cost < best.cost):
                best = fit
    if best is None:
        raise ValueError(
            "the closed-form start found no camera with the sensor behind the lens; give "
            "the nominal focal length, magnification and tilt (nominal initialisation)"
        )
    conv = _normalise_tilt(best.params)
    Q = rotation_matrix(conv.rotvec)
    Rs = jax.vmap(rotation_matrix)(poses.rotvec)
    new_R = jnp.einsum("ij,vjk->vik", Q, Rs)
    new_t = poses.translation @ Q.T
    new_poses = _stack_poses(list(np.asarray(new_R)), list(np.asarray(new_t)))
    return conv.camera, new_poses
