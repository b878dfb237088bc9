"""Corner reprojection residuals across the sensor: binned maps and a PNG of them."""

from __future__ import annotations

import numpy as np

from ..core._model import corner_errors_px
from ..core._result import Calibration


def _sensor_extent(cal: Calibration, size) -> tuple[float, float]:
    if size is not None:
        w, h = size
        return float(w), float(h)
    uv = np.asarray(cal.data.corners)[np.asarray(cal.data.corner_w) > 0]
    return float(np.ceil(uv[:, 0].max() + 1)), float(np.ceil(uv[:, 1].max() + 1))


def residual_map(cal: Calibration, *, bins: tuple[int, int] = (16, 12), size=None):
    """Corner reprojection residuals binned across the sensor.

    **Arguments:**
    - `bins`: `(nu, nv)` bins along u and v.
    - `size`: `(width, height)` of the sensor in px (e.g. `(obs.width, obs.height)`);
      by default the grid spans 0 … the largest detected corner coordinate.

    **Returns:** `(mean_u, mean_v, rms, counts)`, each of shape `(nv, nu)` (rows along
    v, like an image): the mean residual (projected − observed, px) per bin, the RMS of
    the residual vector length, and the number of detected corners per bin (NaN means
    and RMS where a bin is empty). Bins cover `[-0.5, width - 0.5)` × `[-0.5, height - 0.5)`.
    """
    nu, nv = (int(b) for b in bins)
    if nu < 1 or nv < 1:
        raise ValueError(f"bins must be positive, got {bins}")
    w, h = _sensor_extent(cal, size)
    mask = np.asarray(cal.data.corner_w) > 0
    uv = np.asarray(cal.data.corners)[mask]
    err = np.asarray(corner_errors_px(cal.params, cal.data))[mask]
    iu = np.clip(np.floor((uv[:, 0] + 0.5) / w * nu).astype(int), 0, nu - 1)
    iv = np.clip(np.floor((uv[:, 1] + 0.5) / h * nv).astype(int), 0, nv - 1)
    flat = iv * nu + iu
    counts = np.bincount(flat, minlength=nu * nv)
    su = np.bincount(flat, err[:, 0], minlength=nu * nv)
    sv = np.bincount(flat, err[:, 1], minlength=nu * nv)
    s2 = np.bincount(flat, np.sum(err**2, axis=1), minlength=nu * nv)
    safe = np.maximum(counts, 1)
    empty = counts == 0
    mean_u = np.where(empty, np.nan, su / safe).reshape(nv, nu)
    mean_v = np.where(empty, np.nan, sv / safe).reshape(nv, nu)
    rms = np.where(empty, np.nan, np.sqrt(s2 / safe)).reshape(nv, nu)
    return mean_u, mean_v, rms, counts.reshape(nv, nu)


def plot_residuals(
    cal: Calibration, path, *, bins: tuple[int, int] = (16, 12), size=None, dpi: int = 120
) -> None:
    """Write a PNG: binned mean corner residual vectors (quiver) and their RMS (heat map).

    Needs matplotlib (`pip install 'scheimflux[plot]'`); uses the Agg canvas directly,
    so it never touches pyplot's global state or the interactive backend.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:  # pragma: no cover - exercised only without matplotlib
        raise ImportError(
            "plot_residuals needs matplotlib: pip install 'scheimflux[plot]' (or 'matplotlib>=3.7')"
        ) from None
    mean_u, mean_v, rms, counts = residual_map(cal, bins=bins, size=size)
    w, h = _sensor_extent(cal, size)
    nv, nu = counts.shape
    cu = (np.arange(nu) + 0.5) * w / nu - 0.5
    cv = (np.arange(nv) + 0.5) * h / nv - 0.5
    U, V = np.meshgrid(cu, cv)
    fig = Figure(figsize=(12, 4.8))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    ok = counts > 0
    length = np.hypot(mean_u, mean_v)
    ref = float(np.nanmax(length)) if ok.any() and np.nanmax(length) > 0 else 1.0
    q = ax1.quiver(
        U[ok],
        V[ok],
        mean_u[ok],
        mean_v[ok],  # v grows downwards, as does the (inverted) y axis below
        angles="xy",
        scale_units="xy",
        scale=ref / (0.9 * w / nu),
        color="tab:blue",
    )
    ax1.quiverkey(q, 0.82, 1.03, ref, f"{ref:.3g} px", labelpos="E")
    ax1.set_xlim(-0.5, w - 0.5)
    ax1.set_ylim(h - 0.5, -0.5)
    ax1.set_aspect("equal")
    ax1.set_xlabel("u (px)")
    ax1.set_ylabel("v (px)")
    ax1.set_title("mean corner residual per bin")
    im = ax2.imshow(
        np.ma.masked_invalid(rms),
        extent=(-0.5, w - 0.5, h - 0.5, -0.5),
        origin="upper",
        cmap="viridis",
        interpolation="nearest",
    )
    fig.colorbar(im, ax=ax2, label="RMS residual (px)")
    ax2.set_xlabel("u (px)")
    ax2.set_title(f"RMS per bin (overall {cal.reprojection_rms_px:.3g} px per coordinate)")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi, format="png")
