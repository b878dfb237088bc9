"""A calibration report people read: one self-contained HTML page (PNG images embedded as
base64), the same PNGs beside it.

Sections: the camera parameters ± σ, the camera parameters' correlation matrix,
identifiability warnings, the corner residuals over the sensor and per view (with the
observations), the sensor's coverage by calibration data, a Fig.-3-style map of the
model error over the field (with the observations), the laser plane and the stage, and
views of a point cloud.
"""

from __future__ import annotations

import base64
import html
import io
import math
import os

import numpy as np

__all__ = ["Report", "build_report", "write_report"]


def _matplotlib():
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise ImportError(
            "the report needs matplotlib: pip install 'scheimflux[plot]'"
        ) from None
    return Figure, FigureCanvasAgg


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    return f"{v:.9g}" if isinstance(v, (int, float)) else html.escape(str(v))


class Report:
    """The report's pieces: `sections` (title, HTML) and `images` (name → PNG bytes)."""

    def __init__(self, title: str):
        self.title = title
        self.sections: list[tuple[str, str]] = []
        self.images: dict[str, bytes] = {}

    def add(self, title: str, body: str) -> None:
        self.sections.append((title, body))

    def image(self, name: str, png: bytes, caption: str) -> str:
        self.images[name] = png
        data = base64.b64encode(png).decode("ascii")
        return (
            f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )

    def html(self) -> str:
        body = "\n".join(
            f"<section><h2>{html.escape(t)}</h2>\n{b}\n</section>" for t, b in self.sections
        )
        return (
            "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(self.title)}</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:auto}"
            "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 8px;"
            "text-align:right}img{max-width:100%}.warn{color:#a30}"
            f"</style></head><body><h1>{html.escape(self.title)}</h1>\n{body}\n"
            "</body></html>\n"
        )


def _table(rows, header) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _parameters(rep: Report, doc: dict, diag) -> None:
    cam = doc.get("camera", {})
    std = (diag.get("std") or {}) if isinstance(diag, dict) else {}
    rows = []
    for name, entry in cam.items():
        if not isinstance(entry, dict) or "value" not in entry:
            continue
        s = std.get(f"camera.{name}")
        unit = entry.get("unit", "")
        if s is not None and unit == "deg":
            s = math.degrees(s)
        rows.append([html.escape(name), _fmt(entry["value"]), _fmt(s) if s is not None
                     else "fixed / not given", html.escape(unit)])
    rep.add(
        f"Camera ({html.escape(str(doc.get('model', '?')))})",
        _table(rows, ["parameter", "value", "± σ", "unit"]),
    )


def _correlation(rep: Report, diag) -> None:
    cc = diag.get("camera_correlation") if isinstance(diag, dict) else None
    if not cc or not cc.get("labels"):
        rep.add("Correlation", "<p>The file holds no correlation matrix (calibrate writes "
                "it with the diagnostics).</p>")
        return
    Figure, Canvas = _matplotlib()
    labels = [lab.replace("camera.", "") for lab in cc["labels"]]
    M = np.array([[np.nan if v is None else v for v in row] for row in cc["matrix"]], float)
    fig = Figure(figsize=(1.0 + 0.6 * len(labels), 0.6 + 0.6 * len(labels)))
    Canvas(fig)
    ax = fig.subplots()
    im = ax.imshow(M, vmin=-1, vmax=1, cmap="RdBu_r")
    ax.set_xticks(range(len(labels)), labels, rotation=45)
    ax.set_yticks(range(len(labels)), labels)
    for i in range(len(labels)):
        for j in range(len(labels)):
            if np.isfinite(M[i, j]):
                ax.text(j, i, f"{M[i, j]:+.2f}", ha="center", va="center", fontsize=7)
    fig.colorbar(im, ax=ax)
    fig.tight_layout()
    rep.add("Correlation of the camera parameters",
            rep.image("correlation.png", _png(fig), "correlation matrix"))


def _warnings(rep: Report, diag) -> None:
    warns = list(diag.get("warnings", []) or []) if isinstance(diag, dict) else []
    body = ("<ul>" + "".join(f'<li class="warn">{html.escape(str(w))}</li>' for w in warns)
            + "</ul>") if warns else "<p>No identifiability warning.</p>"
    rep.add("Identifiability", body)


def _quality_warnings(rep: Report, quality) -> None:
    warns = quality.get("warnings") if isinstance(quality, dict) else None
    if warns:
        rep.add("Quality warnings", "<ul>" + "".join(
            f'<li class="warn">{html.escape(str(w))}</li>' for w in warns) + "</ul>")


def _residuals(rep: Report, cal) -> None:
    if cal is None:
        rep.add("Residuals", "<p>Residual maps need the observations the calibration was "
                "computed from (--observations).</p>")
        return
    from ..calibration import residual_map

    Figure, Canvas = _matplotlib()
    size = getattr(cal, "sensor_size", None)
    mean_u, mean_v, rms, counts = residual_map(cal, size=size)
    fig = Figure(figsize=(7, 4.5))
    Canvas(fig)
    ax = fig.subplots()
    im = ax.imshow(np.ma.masked_invalid(rms), cmap="viridis")
    fig.colorbar(im, ax=ax, label="RMS corner residual (px)")
    ax.set_title("corner residuals over the sensor (binned)")
    parts = [rep.image("residuals_sensor.png", _png(fig), "residuals over the sensor")]
    err, w, uv = _corner_errors(cal)
    n = err.shape[0]
    cols = min(n, 4)
    fig = Figure(figsize=(3.2 * cols, 2.6 * math.ceil(n / cols)))
    Canvas(fig)
    axes = np.atleast_1d(fig.subplots(math.ceil(n / cols), cols)).ravel()
    for v in range(n):
        ok = w[v]
        axes[v].quiver(uv[v, ok, 0], uv[v, ok, 1], err[v, ok, 0], err[v, ok, 1],
                       angles="xy", color="tab:blue")
        axes[v].invert_yaxis()
        rms_v = float(np.sqrt(np.mean(err[v, ok] ** 2))) if ok.any() else math.nan
        axes[v].set_title(f"view {v}: RMS {rms_v:.3g} px", fontsize=8)
    for ax in axes[n:]:
        ax.set_visible(False)
    fig.tight_layout()
    parts.append(rep.image("residuals_views.png", _png(fig), "residual vectors per view"))
    rep.add("Corner residuals", "\n".join(parts))


def _corner_errors(cal):
    """Reprojection errors per view `(V, M, 2)` px, the detected mask and the pixels."""
    import jax

    from ..calibration.core._model import board_images_px

    data, params = cal.data, cal.params

    def one_view(pose, uv_obs):
        uv = board_images_px(params.camera, pose, data.board, data.circle_ring)
        return uv - uv_obs

    err = np.asarray(jax.jit(jax.vmap(one_view))(params.board_poses, data.corners))
    return err, np.asarray(data.corner_w) > 0, np.asarray(data.corners)


def _coverage(rep: Report, doc: dict, cal) -> None:
    """The sensor region covered by calibration data, with the corners over it."""
    from ..geometry._coverage import Coverage

    cd, sensor = doc.get("coverage"), doc.get("sensor")
    if cd is None or not isinstance(sensor, dict):
        rep.add("Coverage of the sensor", "<p>Coverage unknown: the file records no coverage "
                "of the sensor (written before coverage was recorded, or without a sensor "
                "size). Points cannot be flagged as extrapolated.</p>")
        return
    cov = Coverage.from_dict(cd, (sensor["width"], sensor["height"]))
    Figure, Canvas = _matplotlib()
    fig = Figure(figsize=(7, 4.8))
    Canvas(fig)
    ax = fig.subplots()
    w, h = cov.sensor_size
    ax.imshow(cov.grid, cmap="Greens", vmin=0, vmax=1.6, origin="upper",
              extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    if cal is not None:
        uv = np.asarray(cal.data.corners)[np.asarray(cal.data.corner_w) > 0]
        ax.plot(uv[:, 0], uv[:, 1], ".", ms=1.5, color="k")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(f"covered by calibration data: {100 * cov.fraction:.0f} % of the sensor")
    fig.tight_layout()
    text = (f"<p>{html.escape(cov.summary())}. Reconstructed points whose pixel lies outside "
            "(white) are extrapolated by the model: errors there can be several times "
            "larger; <code>scheimflux reconstruct</code> counts them.</p>")
    rep.add("Coverage of the sensor",
            text + rep.image("coverage.png", _png(fig), "sensor coverage"))


def _model_error(rep: Report, cal) -> None:
    """Fig.-3-style map: the systematic corner residual on the laser plane (µm)."""
    if cal is None or cal.plane is None:
        rep.add("Model error over the field", "<p>The model-error map needs the "
                "observations (--observations) and a laser plane.</p>")
        return
    from ._model_error import model_error_map

    m = model_error_map(cal)
    Figure, Canvas = _matplotlib()
    fig = Figure(figsize=(7, 4.8))
    Canvas(fig)
    ax = fig.subplots()
    ext = (m.edges_u[0], m.edges_u[-1], m.edges_v[-1], m.edges_v[0])
    im = ax.imshow(np.ma.masked_invalid(m.error_um), cmap="magma", extent=ext)
    fig.colorbar(im, ax=ax, label="model error on the laser plane (µm)")
    vv, uu = np.nonzero(np.isfinite(m.error_um) & ~m.significant)
    cu = 0.5 * (m.edges_u[1:] + m.edges_u[:-1])
    cv = 0.5 * (m.edges_v[1:] + m.edges_v[:-1])
    ax.plot(cu[uu], cv[vv], "x", color="w", ms=4, label="within noise")
    if len(uu):
        ax.legend(loc="lower right", fontsize=7)
    ax.set_title("systematic corner residual mapped onto the laser plane")
    fig.tight_layout()
    finite = m.error_um[np.isfinite(m.error_um)]
    sig = m.significant
    text = (f"<p>Mean corner residual per bin (noise averages out, model error does not), "
            f"mapped through the camera onto the laser plane: the error a point "
            f"reconstructed at that pixel carries (the paper's Fig. 3 against the data, not "
            f"a ray tracer). Median {np.median(finite):.3g} µm, max {finite.max():.3g} µm; "
            f"{int(sig.sum())} of {finite.size} bins exceed twice the noise of their mean "
            f"(x: within noise).</p>") if finite.size else "<p>No corner in any bin.</p>"
    rep.add("Model error over the field",
            text + rep.image("model_error.png", _png(fig), "model error over the field"))


def _plane_stage(rep: Report, doc: dict) -> None:
    rows = []
    lp = doc.get("laser_plane")
    if isinstance(lp, dict):
        for k in ("n_per_mm", "unit_normal", "distance_mm"):
            if k in lp:
                rows.append([html.escape(f"laser plane {k}"), _fmt_vec(lp[k])])
    st = doc.get("stage")
    if isinstance(st, dict):
        for k, v in st.items():
            rows.append([html.escape(f"stage {k}"), _fmt_vec(v)])
    rep.add("Laser plane and stage", _table(rows, ["quantity", "value"]) if rows else
            "<p>No laser plane or stage in this calibration.</p>")


def _fmt_vec(v) -> str:
    if isinstance(v, dict) and "value" in v:
        return _fmt_vec(v["value"]) + " " + html.escape(str(v.get("unit", "")))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt_vec(x) for x in v) + "]"
    return _fmt(v)


def _points(rep: Report, points: np.ndarray, name: str) -> None:
    Figure, Canvas = _matplotlib()
    fig = Figure(figsize=(12, 4))
    Canvas(fig)
    axes = fig.subplots(1, 3)
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        ax.plot(points[:, i], points[:, j], ",", color="tab:blue")
        ax.set_xlabel("xyz"[i] + " (mm)")
        ax.set_ylabel("xyz"[j] + " (mm)")
        ax.set_aspect("equal", adjustable="datalim")
    fig.tight_layout()
    rep.add(f"Points: {html.escape(name)} ({len(points)} points)",
            rep.image("points.png", _png(fig), "point cloud, three projections"))


def build_report(calibration: str, *, observations: str | None = None,
                 points: str | None = None) -> Report:
    """Build the report of a calibration file (with its observations: residual maps).

    **Raises:** `ImportError` without matplotlib; `ValueError` / `FileNotFoundError`
    for unreadable inputs.
    """
    _matplotlib()
    import json

    from ..calibration import read_calibration
    from ..io import read_observations

    cal = None
    if observations is not None:
        cal = read_calibration(calibration, observations=read_observations(observations))
    else:
        read_calibration(calibration)  # validates the file
    with open(calibration, encoding="utf-8") as fh:
        doc = json.load(fh)
    diag = doc.get("diagnostics", {})
    if not isinstance(diag, dict):
        diag = {}
    # `calibrate` keeps σ, the correlation and the identifiability warnings in
    # diagnostics.uncertainty, the quality warnings in diagnostics.quality (the report
    # read them from diagnostics itself: every free parameter showed "fixed / not given")
    unc = diag.get("uncertainty") if isinstance(diag.get("uncertainty"), dict) else diag
    rep = Report(f"scheimflux calibration report: {os.path.basename(calibration)}")
    _parameters(rep, doc, unc)
    _correlation(rep, unc)
    _warnings(rep, unc)
    _quality_warnings(rep, diag.get("quality"))
    _residuals(rep, cal)
    _coverage(rep, doc, cal)
    _model_error(rep, cal)
    _plane_stage(rep, doc)
    if points is not None:
        from ..metrology._workflow import read_points

        pts, _ = read_points(points)
        _points(rep, pts, os.path.basename(points))
    return rep


def write_report(rep: Report, out: str, *, png_dir: str | None = None,
                 overwrite: bool = False) -> list[str]:
    """Write the HTML (and the PNGs into `png_dir`); returns the paths written."""
    from ..io._files import check_writable, write_atomic

    targets = [out] + ([os.path.join(png_dir, n) for n in rep.images] if png_dir else [])
    for path in targets:
        check_writable(path, overwrite=overwrite)
    write_atomic(out, rep.html(), overwrite=overwrite)
    for name, png in rep.images.items() if png_dir else ():
        write_atomic(os.path.join(png_dir, name), png, overwrite=overwrite)
    return targets
