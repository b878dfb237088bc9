"""A complete simulated calibration data set: observations plus exact ground truth.

[`simulate_observations`][] poses a checkerboard `n_views` times around the laser plane,
traces its corners and the laser line on it through the real lens, optionally scans a
ring gauge on a rotary table, and returns

- `Observations`: what a user's detection would produce (noisy pixels, the board's 3-D
  points, sensor size and pitch, rounded nominal values) — the input of calibration;
- [`Truth`][]: the board poses, the laser plane, the stage and the gauge, the exact
  (noise-free) pixels and 3-D points, and the rig's paraxial nominal parameters.

With `imaging="centroid"` every pixel (corners, stripe points, stage frames) is the
centroid of the ray bundle filling the aperture stop ([`pupil_image`][]) instead of the
chief ray's hit; the noise realisation is the same as for `imaging="chief"` (same seed),
and points whose bundle is entirely vignetted or whose centroid leaves the sensor margin
are dropped (corners: NaN rows), never NaN-valued.

`write_truth` stores the truth as JSON (`"format": "scheimflux.truth/1"`) for tests and
benchmarks; `read_truth` reads it back. Everything is seeded and deterministic.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from numbers import Integral, Real

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ..geometry._stage import RotaryStage
from ..geometry._transforms import Pose
from ..io._files import load_json, write_json
from ..io._observations import Nominal, Observations, StageScan, View
from ..targets._target import Target
from ._gauges import GaugeScan, default_stage, gauge_scan
from ._lens import paraxial
from ._pupil import PupilSampling, pupil_grid, pupil_points
from ._rig import Rig
from ._scenes import (
    StripeProfile,
    _board_stripe_points,
    _field,
    _inside,
    _trace_stripes,
    board_poses,
)

__all__ = [
    "TRUTH_FORMAT",
    "Truth",
    "read_truth",
    "simulate_observations",
    "truth_from_dict",
    "truth_to_dict",
    "write_truth",
]

TRUTH_FORMAT = "scheimflux.truth/1"


@dataclasses.dataclass(frozen=True)
class Truth:
    """The exact state behind simulated observations (camera frame, mm, rad, px).

    **Fields:**
    - `board_poses`: `T_c_b` per view.
    - `laser_plane`: n = [A, B, C] of the laser plane n · X = 1, shape (3,).
    - `corners_px`: noise-free ray-traced corner pixels `(V, M, 2)`, NaN where not visible
      (a circle grid's: the area centroid of each circle's traced image).
    - `corners_c`: every corner in the camera frame `(V, M, 3)`.
    - `stripe_px`, `stripe_c`: per view, noise-free stripe pixels `(K, 2)` and their exact
      3-D points `(K, 3)` (same order as the observations' `stripe_px`).
    - `nominal_params`: the rig's paraxial thick-lens parameters
      (`rig.nominal_thick_lens_params()`: f, e, z0, phi, theta, x0, y0, dx, dy).
    - `rig`: a description of the simulated rig (lens, sensor pose after focusing,
      magnification, sensor size and pitch).
    - `stage`: the true `RotaryStage` (or None without a scan); `gauge_radius_mm`,
      `eccentricity_mm` (gauge axis offset from the table axis, measurement frame),
      `wobble_rad`.
    - `scan_px`, `scan_c`, `scan_m`: per frame, noise-free pixels and the exact points in
      the camera and measurement frames.
    - `seed`: the seed that produced the data.
    """

    board_poses: list[Pose]
    laser_plane: np.ndarray
    corners_px: np.ndarray
    corners_c: np.ndarray
    stripe_px: list[np.ndarray]
    stripe_c: list[np.ndarray]
    nominal_params: dict[str, float]
    rig: dict
    stage: RotaryStage | None = None
    gauge_radius_mm: float | None = None
    eccentricity_mm: tuple[float, float] | None = None
    wobble_rad: float = 0.0
    scan_px: list[np.ndarray] = dataclasses.field(default_factory=list)
    scan_c: list[np.ndarray] = dataclasses.field(default_factory=list)
    scan_m: list[np.ndarray] = dataclasses.field(default_factory=list)
    seed: int = 0


def _magnification(rig: Rig) -> float:
    """|β| on the axis: paraxial magnification at the focus point F0."""
    par = paraxial(rig.lens)
    z_lens = float(par.z_principal_image) - float(_field(rig).F0[2])
    return abs(float(par.efl) / (z_lens - float(par.z_focal_object)))


def _rig_description(rig: Rig) -> dict:
    par = paraxial(rig.lens)
    return {
        "lens": rig.lens.name,
        "efl_mm": float(par.efl),
        "magnification": _magnification(rig),
        "z0_mm": float(rig.z0),
        "phi_rad": float(rig.phi),
        "theta_rad": float(rig.theta),
        "x0_px": float(rig.x0),
        "y0_px": float(rig.y0),
        "pixel_pitch_mm": [float(rig.dx), float(rig.dy)],
        "sensor": [int(rig.sensor_size[0]), int(rig.sensor_size[1])],
    }


def nominal_of(rig: Rig) -> Nominal:
    """What a user knows before calibrating: focal length (1 mm), |β| (0.01), tilt (1°)."""
    par = paraxial(rig.lens)
    return Nominal(
        float(round(float(par.efl))),
        round(_magnification(rig), 2),
        (float(round(math.degrees(float(rig.phi)))), float(round(math.degrees(float(rig.theta))))),
    )


def simulate_observations(
    rig: Rig,
    board: Target,
    *,
    n_views: Integral = 15,
    corner_noise_px: Real = 0.03,
    stripe_noise_px: Real = 0.05,
    stage_scan: bool = True,
    n_frames: Integral = 36,
    delta_omega_deg: Real = 10.0,
    gauge_radius_mm: Real = 17.5,
    eccentricity_mm: ArrayLike | Sequence = (0.05, -0.03),
    wobble_rad: Real = 0.0,
    seed: Integral = 0,
    imaging: str = "chief",
    f_number: Real | None = None,
    pupil: PupilSampling | None = None,
    whole_boards: bool = False,
) -> tuple[Observations, Truth]:
    """Simulate a calibration data set by ray tracing through `rig`.

    **Arguments:**
    - `rig`: the simulated rig (`paper_rig()`, `build_rig(...)`).
    - `board`: the target (e.g. `Checkerboard(11, 8, 0.3)` at |β| = 1.5; a `CharucoBoard`
      or `CircleGrid` works too: only `points_mm`, `centre_mm` and `extent_mm` are used;
      a `CircleGrid`'s points are observed as the area centroids of its circles' traced
      images, as a blob detector measures them, and the observations state its
      `circle_diameter_mm`).
    - `n_views`: board poses ([`board_poses`][]); each also carries the laser line on the
      board ([`stripe_on_board`][]).
    - `corner_noise_px`, `stripe_noise_px`: Gaussian pixel noise (σ per coordinate).
    - `stage_scan`: also scan a ring gauge of `gauge_radius_mm` on a rotary table
      ([`default_stage`][], [`gauge_scan`][]): `n_frames` frames `delta_omega_deg` apart,
      the gauge off the table axis by `eccentricity_mm` and tilted by `wobble_rad`.
    - `seed`: all randomness (poses and noise) derives from it.
    - `imaging`: `"chief"` (default): a point's pixel is its chief ray's hit;
      `"centroid"`: the centroid of the bundle filling the stop ([`pupil_image`][]), what
      a sensor records at full aperture (coma, vignetting). Same poses and noise draws.
    - `f_number`: set the lens's working f-number first (default: the rig's stop).
    - `pupil`: the stop quadrature for `"centroid"` (default `pupil_grid(8)`, 136 rays).
    - `whole_boards`: keep every board whole inside the sensor (`board_poses(...,
      whole=True)`), as a checkerboard detector needs in rendered images; by default
      the sensor's border may cut a board (its outer corners then cover the field's edge).

    **Returns:** `(observations, truth)`: an `Observations` (noisy pixels, NaN for corners
    not seen; `nominal` with the focal length rounded to 1 mm, |β| to 0.01 and the tilt to
    1°) and the exact [`Truth`][].
    """
    seed = int(seed)
    if imaging not in ("chief", "centroid"):
        raise ValueError(f"imaging must be 'chief' or 'centroid', got {imaging!r}")
    if f_number is not None:
        rig = eqx.tree_at(lambda r: r.lens, rig, rig.lens.with_f_number(float(f_number)))
    views = board_poses(
        rig,
        board,
        int(n_views),
        seed=seed,
        noise_px=float(corner_noise_px),
        whole=bool(whole_boards),
    )
    field = _field(rig)
    stripe_sets = [_board_stripe_points(rig, field, v.T_c_b, board, 2.0) for v in views]
    stripes = _trace_stripes(rig, stripe_sets, float(stripe_noise_px), seed + 1, 5.0)

    stage = scan = None
    if stage_scan:
        stage = default_stage(rig, float(gauge_radius_mm), math.radians(float(delta_omega_deg)))
        scan = gauge_scan(
            rig,
            stage,
            float(gauge_radius_mm),
            int(n_frames),
            eccentricity_mm=eccentricity_mm,
            wobble_rad=float(wobble_rad),
            noise_px=float(stripe_noise_px),
            seed=seed + 2,
        )

    sampling = None
    if imaging == "centroid":
        sampling = pupil_grid(8) if pupil is None else pupil
        views, stripes, scan = _reimage(rig, sampling, views, stripes, scan)
    diameter = getattr(board, "diameter_mm", None)
    if diameter is not None:
        views = _circle_images(rig, sampling, views, float(diameter))

    w, h = rig.sensor_size
    obs = Observations(
        width=int(w),
        height=int(h),
        pixel_pitch_mm=(float(rig.dx), float(rig.dy)),
        board_points_mm=board.points_mm,
        circle_diameter_mm=None if diameter is None else float(diameter),
        views=[View(v.px, s.px) for v, s in zip(views, stripes)],
        nominal=nominal_of(rig),
        stage=None
        if scan is None
        else StageScan(float(delta_omega_deg), float(gauge_radius_mm), [f.px for f in scan.frames]),
    )
    truth = Truth(
        board_poses=[v.T_c_b for v in views],
        laser_plane=np.asarray(rig.laser_plane, dtype=np.float64),
        corners_px=np.stack([v.px_true for v in views]),
        corners_c=np.stack([v.points_c for v in views]),
        stripe_px=[s.px_true for s in stripes],
        stripe_c=[s.points_c for s in stripes],
        nominal_params=rig.nominal_thick_lens_params(),
        rig=dict(_rig_description(rig), imaging=imaging, f_number=_finite(rig.lens.f_number)),
        stage=stage,
        gauge_radius_mm=None if scan is None else scan.radius,
        eccentricity_mm=None if scan is None else scan.eccentricity_mm,
        wobble_rad=0.0 if scan is None else scan.wobble_rad,
        scan_px=[] if scan is None else [f.px_true for f in scan.frames],
        scan_c=[] if scan is None else [f.points_c for f in scan.frames],
        scan_m=[] if scan is None else [f.points_m for f in scan.frames],
        seed=seed,
    )
    return obs, truth


def _finite(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _polygon_centroids(p: np.ndarray) -> np.ndarray:
    """Area centroids `(..., 2)` of the closed polygons `p` `(..., K, 2)`."""
    mean = p.mean(axis=-2)
    q = p - mean[..., None, :]
    q1 = np.roll(q, -1, axis=-2)
    c = q[..., 0] * q1[..., 1] - q1[..., 0] * q[..., 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        return mean + np.sum((q + q1) * c[..., None], axis=-2) / (3.0 * c.sum(-1))[..., None]


_DISC_VERTICES = 64


def _circle_images(rig: Rig, sampling: PupilSampling | None, views, diameter: float):
    """A circle grid's observed points: the area centroid of each circle's traced image
    (what a blob detector measures), not the image of its centre; each point's noise
    draw and visibility kept. The outline is traced at 64 points (chief rays, or pupil
    centroids with `sampling`) and the polygons of 64 and 32 vertices extrapolated
    (Richardson, error ∝ K⁻⁴: ~1e-6 px for a 0.15 mm dot under an 8 mm lens). A circle
    whose outline does not trace entirely is not visible."""
    k = _DISC_VERTICES
    a = 2.0 * np.pi * np.arange(k) / k
    ring = 0.5 * diameter * np.stack([np.cos(a), np.sin(a), np.zeros(k)], axis=1)
    out = []
    for v in views:
        R = np.asarray(v.T_c_b.R, dtype=np.float64)
        X = (v.points_c[:, None, :] + ring @ R.T).reshape(-1, 3)
        if sampling is None:
            uv, ok = (np.asarray(x) for x in rig.project(jnp.asarray(X)))
        else:
            uv, ok = pupil_points(rig, X, sampling)[:2]
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, k, 2)
        ok = np.asarray(ok).reshape(-1, k).all(axis=1)
        c = (4.0 * _polygon_centroids(uv) - _polygon_centroids(uv[:, ::2])) / 3.0
        vis = v.visible & ok & np.all(np.isfinite(c), axis=1)
        c = np.where(vis[:, None], c, np.nan)
        out.append(dataclasses.replace(v, visible=vis, px_true=c, px=c + v.px - v.px_true))
    return out


def _reimage(rig: Rig, sampling: PupilSampling, views, stripes, scan):
    """Replace chief-ray pixels by pupil centroids, keeping each point's noise draw."""
    sets = [v.points_c for v in views] + [s.points_c for s in stripes]
    if scan is not None:
        sets += [f.points_c for f in scan.frames]
    sizes = [len(np.reshape(x, (-1, 3))) for x in sets]
    X = np.concatenate([np.reshape(x, (-1, 3)) for x in sets])
    uv_all, ok_all, _, _ = pupil_points(rig, X, sampling)
    parts, start = [], 0
    for size in sizes:
        parts.append((uv_all[start : start + size], ok_all[start : start + size]))
        start += size

    new_views = []
    for v, (uv, ok) in zip(views, parts[: len(views)]):
        vis = v.visible & ok & _inside(rig, uv, 10.0)  # the corner margin of board_poses
        uv = np.where(vis[:, None], uv, np.nan)
        new_views.append(dataclasses.replace(v, visible=vis, px_true=uv, px=uv + v.px - v.px_true))

    def profile(s, uv, ok, margin):
        keep = ok & _inside(rig, uv, margin)
        return keep, StripeProfile(s.points_c[keep], uv[keep], (uv + s.px - s.px_true)[keep])

    n = len(views)
    new_stripes = [profile(s, *parts[n + k], 5.0)[1] for k, s in enumerate(stripes)]
    if scan is not None:
        frames = []
        for k, f in enumerate(scan.frames):
            keep, prof = profile(f, *parts[n + len(stripes) + k], 5.0)
            frames.append(
                dataclasses.replace(
                    f, points_c=prof.points_c, points_m=f.points_m[keep], px_true=prof.px_true,
                    px=prof.px,
                )
            )  # fmt: skip
        scan = GaugeScan(scan.stage, scan.radius, scan.eccentricity_mm, scan.wobble_rad, frames)
    return new_views, new_stripes, scan


# ----------------------------------------------------------------------------- files


def _rows(a) -> list:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 1:
        return [float(c) for c in a]
    return [_rows(r) if r.ndim > 1 or np.all(np.isfinite(r)) else None for r in a]


def _pose_dict(T: Pose) -> dict:
    return {
        "rotvec": _rows(T.rotvec),
        "translation_mm": _rows(T.translation),
        "R": _rows(T.R),
    }


def truth_to_dict(truth: Truth) -> dict:
    """The truth as a JSON-ready dict (`"format": "scheimflux.truth/1"`; NaN → null)."""
    doc = {
        "format": TRUTH_FORMAT,
        "seed": int(truth.seed),
        "rig": truth.rig,
        "nominal_params": {k: float(v) for k, v in truth.nominal_params.items()},
        "laser_plane": _rows(truth.laser_plane),
        "board_poses": [_pose_dict(T) for T in truth.board_poses],
        "corners_px": [_rows(v) for v in truth.corners_px],
        "corners_c_mm": [_rows(v) for v in truth.corners_c],
        "stripe_px": [_rows(np.reshape(s, (-1, 2))) for s in truth.stripe_px],
        "stripe_c_mm": [_rows(np.reshape(s, (-1, 3))) for s in truth.stripe_c],
    }
    if truth.stage is not None:
        doc["stage"] = {
            "T_m_c": _pose_dict(truth.stage.T_m_c),
            "delta_omega_rad": float(truth.stage.delta_omega),
            "gauge_radius_mm": truth.gauge_radius_mm,
            "eccentricity_mm": list(truth.eccentricity_mm),
            "wobble_rad": float(truth.wobble_rad),
            "frames_px": [_rows(np.reshape(f, (-1, 2))) for f in truth.scan_px],
            "frames_c_mm": [_rows(np.reshape(f, (-1, 3))) for f in truth.scan_c],
            "frames_m_mm": [_rows(np.reshape(f, (-1, 3))) for f in truth.scan_m],
        }
    return doc


def _arr(rows, dim: int) -> np.ndarray:
    a = [[math.nan] * dim if r is None else r for r in rows]
    return np.asarray(a, dtype=np.float64).reshape(len(a), dim)


def _pose_from(d: dict) -> Pose:
    return Pose(np.asarray(d["rotvec"], dtype=np.float64), np.asarray(d["translation_mm"]))


def truth_from_dict(doc: dict) -> Truth:
    """Inverse of [`truth_to_dict`][]; raises `ValueError` on another format."""
    if not isinstance(doc, dict) or doc.get("format") != TRUTH_FORMAT:
        raise ValueError(f"not a {TRUTH_FORMAT} document")
    try:
        stage = doc.get("stage")
        return Truth(
            board_poses=[_pose_from(p) for p in doc["board_poses"]],
            laser_plane=np.asarray(doc["laser_plane"], dtype=np.float64),
            corners_px=np.stack([_arr(v, 2) for v in doc["corners_px"]]),
            corners_c=np.stack([_arr(v, 3) for v in doc["corners_c_mm"]]),
            stripe_px=[_arr(s, 2) for s in doc["stripe_px"]],
            stripe_c=[_arr(s, 3) for s in doc["stripe_c_mm"]],
            nominal_params={k: float(v) for k, v in doc["nominal_params"].items()},
            rig=dict(doc["rig"]),
            stage=None
            if stage is None
            else RotaryStage(
                pose=_pose_from(stage["T_m_c"]), delta_omega=float(stage["delta_omega_rad"])
            ),
            gauge_radius_mm=None if stage is None else float(stage["gauge_radius_mm"]),
            eccentricity_mm=None
            if stage is None
            else tuple(float(v) for v in stage["eccentricity_mm"]),
            wobble_rad=0.0 if stage is None else float(stage["wobble_rad"]),
            scan_px=[] if stage is None else [_arr(f, 2) for f in stage["frames_px"]],
            scan_c=[] if stage is None else [_arr(f, 3) for f in stage["frames_c_mm"]],
            scan_m=[] if stage is None else [_arr(f, 3) for f in stage["frames_m_mm"]],
            seed=int(doc.get("seed", 0)),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"malformed {TRUTH_FORMAT} document: {err}") from None


def write_truth(path: str | os.PathLike, truth: Truth, *, overwrite: bool = False) -> None:
    """Write the truth as JSON, atomically (never clobbers unless `overwrite`)."""
    write_json(path, truth_to_dict(truth), overwrite=overwrite)


def read_truth(path: str | os.PathLike) -> Truth:
    """Read a truth file written by [`write_truth`][]."""
    try:
        return truth_from_dict(load_json(path, "truth"))
    except ValueError as err:
        raise ValueError(f"{os.fspath(path)}: {err}") from None
