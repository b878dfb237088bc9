"""Screening of the observations before a solve and after it: pixels off the sensor or
beyond a field radius left out and counted, outliers found by robust statistics, and how
well the board stripe points determine the laser plane.

The solve steps use these; the quality gates (`..trust._gates`) judge with them.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...io._observations import Observations, StageScan, near_centre, within_radius

# Residuals beyond this many robust standard deviations are rejected after the solve.
# For Gaussian noise a corner (2-D) is beyond 5 σ with probability exp(−12.5) ≈ 4e-6, a
# stripe point (1-D) with 6e-7: with 10⁴ observations, no good one is lost.
REJECT_SIGMA = 5.0
# Half a pixel beyond the outermost pixel centres: the sensor's edge.
_EDGE = 0.5


# ----------------------------------------------------------------------------- screening


def _inside(px: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rows of `px` `(N, 2)` that are finite and on the sensor."""
    u, v = px[:, 0], px[:, 1]
    with np.errstate(invalid="ignore"):
        return (
            np.isfinite(u)
            & np.isfinite(v)
            & (u >= -_EDGE)
            & (u <= width - _EDGE)
            & (v >= -_EDGE)
            & (v <= height - _EDGE)
        )


def screen_observations(obs: Observations) -> tuple[Observations, dict]:
    """Leave out every pixel outside the declared sensor, and count them.

    A pixel that is not on the sensor cannot have been observed by it: a stripe from a
    frame of another size, swapped `(v, u)` columns, or a detector's wild guess. Corners
    outside become "not detected" (NaN), stripe and gauge pixels are dropped.

    **Returns:** `(screened observations, counts)`; counts has `corners_outside_sensor`,
    `stripe_outside_sensor` and `gauge_outside_sensor`.
    """
    W, H = int(obs.width), int(obs.height)
    n_corner = n_stripe = n_gauge = 0
    views = []
    for view in obs.views:
        c = np.array(view.corners_px, dtype=np.float64).reshape(-1, 2)
        seen = np.all(np.isfinite(c), axis=1)
        bad_c = seen & ~_inside(c, W, H)
        c[bad_c] = np.nan
        s = np.asarray(view.stripe_px, dtype=np.float64).reshape(-1, 2)
        finite = np.all(np.isfinite(s), axis=1)
        keep = _inside(s, W, H)
        n_corner += int(bad_c.sum())
        n_stripe += int((finite & ~keep).sum())
        views.append(dataclasses.replace(view, corners_px=c, stripe_px=s[keep]))
    stage = obs.stage
    if stage is not None:
        frames = []
        for f in stage.frames:
            f = np.asarray(f, dtype=np.float64).reshape(-1, 2)
            keep = _inside(f, W, H)
            n_gauge += int((np.all(np.isfinite(f), axis=1) & ~keep).sum())
            frames.append(f[keep])
        stage = StageScan(stage.delta_omega_deg, stage.gauge_radius_mm, frames)
    counts = {
        "corners_outside_sensor": n_corner,
        "stripe_outside_sensor": n_stripe,
        "gauge_outside_sensor": n_gauge,
    }
    return dataclasses.replace(obs, views=views, stage=stage), counts


def screen_field(obs: Observations, radius_px: float) -> tuple[Observations, dict]:
    """Leave out every pixel farther than `radius_px` from the sensor's centre, and count
    them: a calibration inside the part of the field the user trusts (e.g. where the lens
    does not vignette: there a clipped ray bundle's centroid is not the image of one ray,
    docs/noncentral.md).

    The centre is the middle of the sensor, `((width − 1) / 2, (height − 1) / 2)`.
    Corners beyond the radius become "not detected" (NaN); stripe, gauge and table-target
    laser-line pixels are dropped; table-target corners become NaN.

    **Returns:** `(screened observations, counts)`; counts has `field_radius_px` and
    `corners_beyond_radius`, `stripe_beyond_radius`, `gauge_beyond_radius` (table-target
    corners and line pixels are counted with the corners and the stripe).

    **Raises:** `ValueError` for a radius that is not a positive finite number.
    """
    try:
        radius = float(radius_px)
    except (TypeError, ValueError):
        raise ValueError(
            f"the field radius must be a number of pixels, got {radius_px!r}"
        ) from None
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"the field radius must be a positive number of pixels, got {radius_px!r}")
    def near(px):
        return near_centre(obs, np.asarray(px, dtype=np.float64).reshape(-1, 2), radius)

    def n_corners(views_px):
        return sum(int(np.all(np.isfinite(c), axis=-1).sum()) for c in views_px)

    cut = within_radius(obs, radius)
    n_corner = n_corners(v.corners_px for v in obs.views) - n_corners(
        v.corners_px for v in cut.views
    )
    n_stripe = sum(len(v.stripe_px) for v in obs.views) - sum(len(v.stripe_px) for v in cut.views)
    n_gauge = 0
    stage = obs.stage
    if stage is not None:
        frames = [np.asarray(f, dtype=np.float64).reshape(-1, 2) for f in stage.frames]
        kept = [f[near(f)] for f in frames]
        n_gauge = sum(len(f) for f in frames) - sum(len(f) for f in kept)
        stage = StageScan(stage.delta_omega_deg, stage.gauge_radius_mm, kept)
    table = obs.stage_target
    if table is not None:
        c = np.array(table.corners_px, dtype=np.float64)
        seen = np.all(np.isfinite(c), axis=-1)
        far = seen & ~near(c).reshape(seen.shape)
        c[far] = np.nan
        lines = [np.asarray(s, dtype=np.float64).reshape(-1, 2) for s in table.stripe_px]
        kept = tuple(s[near(s)] for s in lines)
        n_corner += int(far.sum())
        n_stripe += sum(len(s) for s in lines) - sum(len(s) for s in kept)
        table = dataclasses.replace(table, corners_px=c, stripe_px=kept)
    counts = {
        "field_radius_px": radius,
        "corners_beyond_radius": n_corner,
        "stripe_beyond_radius": n_stripe,
        "gauge_beyond_radius": n_gauge,
    }
    return dataclasses.replace(cut, stage=stage, stage_target=table), counts


# ----------------------------------------------------------------------------- outliers


def robust_sigma(r: np.ndarray) -> float:
    """1.4826 × the median absolute residual: σ of Gaussian noise, blind to outliers."""
    r = np.asarray(r, dtype=np.float64)
    return float(1.4826 * np.median(np.abs(r))) if r.size else math.nan


def outlier_masks(
    corner_err_px: np.ndarray,
    corner_w: np.ndarray,
    stripe_r: np.ndarray,
    stripe_w: np.ndarray,
    gauge_r: np.ndarray | None = None,
    gauge_w: np.ndarray | None = None,
    *,
    threshold: float = REJECT_SIGMA,
    corner_sigma: float = 0.0,
    sigma: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Which observations lie beyond `threshold` robust standard deviations.

    Corners: the length `e` of the reprojection error; for 2-D Gaussian noise of σ per
    coordinate `e` is Rayleigh-distributed with median σ √(2 ln 2), so σ̂ =
    median(e) / 1.1774 and a corner is out when `e > threshold · σ̂`. Stripe and gauge
    points: a signed distance, σ̂ = 1.4826 · median |r| ([`robust_sigma`][]). The scale
    is the larger of σ̂ and the stated σ (`corner_sigma` px; `sigma` in the units of the
    stripe and gauge residuals): a stated σ that is too small does not reject good data,
    and nearly noise-free data (σ̂ ≪ σ) do not lose their largest model residuals.

    **Arguments:** the corner errors `(V, M, 2)` px with weights `(V, M)`; the stripe
    residuals and weights `(V, K)`; optionally the gauge residuals and weights `(F, L)`.

    **Returns:** boolean masks (True: reject) of the corner, stripe and gauge shapes.
    """
    used = corner_w > 0
    e = np.linalg.norm(corner_err_px, axis=-1)
    s = float(np.median(e[used])) / math.sqrt(2 * math.log(2)) if used.any() else math.inf
    corner_out = used & (e > threshold * max(s, corner_sigma))

    def scalar(r, w):
        u = w > 0
        if not u.any():
            return np.zeros(r.shape, bool)
        return u & (np.abs(r) > threshold * max(robust_sigma(r[u]), sigma))

    gauge_out = None if gauge_r is None else scalar(gauge_r, gauge_w)
    return corner_out, scalar(stripe_r, stripe_w), gauge_out


def excess_kurtosis(r: np.ndarray) -> float:
    """`mean(r⁴) / mean(r²)² − 3` about zero (0 for Gaussian noise)."""
    r = np.asarray(r, dtype=np.float64)
    m2 = float(np.mean(r**2)) if r.size else 0.0
    if m2 == 0.0:
        return 0.0
    return float(np.mean(r**4) / m2**2 - 3.0)


# ----------------------------------------------------------------------------- the plane


def plane_conditioning(
    points: np.ndarray, view: np.ndarray, sigma_mm: float, *, min_spread: float = 20.0
) -> dict:
    """How well the board stripe points determine the laser plane; raises if they do not.

    The points of one board pose lie on one line (the board ∩ the laser plane), and a
    line leaves the plane free to turn about it. With `s₀ ≥ s₁ ≥ s₂` the singular values
    of the centred points `(N, 3)`, `s₁ / √N` is their RMS spread across the best line
    within the plane. A total-least-squares plane through N points with noise σ normal
    to it has its normal tilted by σ / s_k (rad) about the k-th in-plane axis, and its
    offset uncertain by σ / √N: these are the predicted σ reported.

    **Arguments:**
    - `points` `(N, 3)` mm and the board view of each, `view` `(N,)`.
    - `sigma_mm`: the stripe points' noise (mm).
    - `min_spread`: the spread across the line must be at least this many σ.

    **Returns:** a JSON-ready dict: `n_points`, `n_views`, `singular_values`,
    `spread_across_line_mm`, `normal_sigma_rad` (about the weak and the strong in-plane
    axis), `offset_sigma_mm`.
    """
    points = np.asarray(points, dtype=np.float64)
    views = np.unique(np.asarray(view))
    if len(views) < 2:
        raise ValueError(
            f"the laser line was seen on {len(views)} board pose(s): a plane needs the line "
            "on at least 2 board poses at different depths or tilts (one line leaves the "
            "plane free to turn about it); add views with the laser on the board"
        )
    n = len(points)
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    spread = float(s[1] / math.sqrt(n))
    info = {
        "n_points": int(n),
        "n_views": int(len(views)),
        "singular_values": [float(x) for x in s],
        "spread_across_line_mm": spread,
        "normal_sigma_rad": [float(sigma_mm / s[1]), float(sigma_mm / s[0])],
        "offset_sigma_mm": float(sigma_mm / math.sqrt(n)),
    }
    if not spread >= min_spread * sigma_mm:
        raise ValueError(
            f"the stripe points of the {len(views)} board poses lie on one line (spread "
            f"across it {spread * 1e3:.3g} µm, {spread / sigma_mm:.2g} × the stripe σ "
            f"{sigma_mm * 1e3:.3g} µm; need {min_spread:g} ×): the laser plane is not "
            "determined; use board poses at different depths or tilts"
        )
    return info


def board_plane_angles_deg(board_normals: np.ndarray, plane_normal: np.ndarray) -> np.ndarray:
    """Angle (deg) between each board plane and the laser plane."""
    nb = board_normals / np.linalg.norm(board_normals, axis=-1, keepdims=True)
    nl = plane_normal / np.linalg.norm(plane_normal)
    c = np.clip(np.abs(nb @ nl), 0.0, 1.0)
    return np.degrees(np.arccos(c))
