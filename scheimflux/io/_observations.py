"""The observations file, `"format": "scheimflux.observations/1"` (JSON).

```
{"format": "scheimflux.observations/1",
 "sensor": {"width": 1600, "height": 1200, "pixel_pitch_mm": [0.0044, 0.0044]},
 "nominal": {"focal_length_mm": 97, "magnification": 1.5, "tilt_deg": [0, 13]},  # optional
 "board_points_mm": [[x, y, z], ...],
 "circle_diameter_mm": 0.15,                                                     # optional
 "views": [{"corners_px": [[u, v] or null, ...], "stripe_px": [[u, v], ...],
            "source": ["view_0_board.png", "view_0_stripe.png"],              # optional
            "board_motion_px": 0.012,                                          # optional
            "stripe_sigma_px": 0.21}, ...],                                    # optional
 "dropped_views": [{"view": 3, "images": ["view_3.jpg"],                           # optional
                    "reason": "no 11x8 checkerboard found ..."}, ...],
 "stage": {"delta_omega_deg": 10, "gauge_radius_mm": 17.5,                        # optional
           "frames": [[[u, v], ...], ...]},
 "stage_target": {"delta_omega_deg": 30,                                          # optional
                  "board_points_mm": [[x, y, z], ...],
                  "circle_diameter_mm": 0.15,                                   # optional
                  "views": [{"table_step": 0, "corners_px": [[u, v] or null, ...],
                             "stripe_px": [[u, v], ...],                        # optional
                             "source": ["step_000.png"]}, ...],
                  "dropped_views": [{"table_step": 4, "images": ["step_004.png"],
                                     "reason": "..."}]}}
```
`corners_px` follows the order of `board_points_mm`; null marks a corner not detected.
`circle_diameter_mm` says that the board's points are the centres of circles of that
diameter (a circle grid) and that `corners_px` are the centroids of their images, as a
blob detector measures them; calibration then predicts the centroid of each circle's
image instead of the image of its centre (they differ under perspective and
distortion). Absent: the points are imaged as points (checkerboard, ChArUco corners).
`sensor.pixel_pitch_mm` is optional (null or absent when the datasheet value was not
given to `detect`; the thick-lens model needs it). `source` names the image files a view
was measured in; `dropped_views` lists the captures left out (target not found, image
unreadable, ...) with the capture's view number, its image names and the reason.
`board_motion_px` is the board's motion measured between a view's laser-off image (a
pair's board image, or `view_<k>_off`) and its laser-on image (px; null: it could not be
measured, the laser-on image showing the board too faintly; absent: no laser-off image,
or not measured). `stripe_sigma_px` is the noise σ (px) of the view's stripe centres
across the line, where it was measured (a speckled laser line, whose centres scatter
several times a clean line's: `detect` writes it); `calibrate` weights the view's
stripe points by the larger of it and its `sigma_stripe_px`. Absent: not measured (the
stated `sigma_stripe_px` applies). `stage_target` holds a target fixed to the rotary
table, imaged at table steps `table_step` (angle `table_step · delta_omega_deg`; steps
strictly increasing, a step whose image showed no target is listed in its
`dropped_views` and keeps its number); its `board_points_mm` may be another target than
the calibration boards' (its own `circle_diameter_mm` for a circle grid). Files without
these keys (older files) read as before.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os

import numpy as np

from ._files import load_json, write_json

FORMAT = "scheimflux.observations/1"

# The keys each level of the file may hold; anything else is refused (a misspelt optional
# key would otherwise be ignored silently and change the result). "comment" is free text.
TOP_KEYS = (
    "format", "sensor", "nominal", "board_points_mm", "circle_diameter_mm", "views",
    "dropped_views", "stage", "stage_target", "comment",
)  # fmt: skip
SENSOR_KEYS = ("width", "height", "pixel_pitch_mm")
NOMINAL_KEYS = ("focal_length_mm", "magnification", "tilt_deg")
VIEW_KEYS = ("corners_px", "stripe_px", "source", "board_motion_px", "stripe_sigma_px")
DROPPED_KEYS = ("view", "images", "reason")
STAGE_KEYS = ("delta_omega_deg", "gauge_radius_mm", "frames")
STAGE_TARGET_KEYS = (
    "delta_omega_deg", "board_points_mm", "circle_diameter_mm", "views", "dropped_views",
)  # fmt: skip
STAGE_TARGET_VIEW_KEYS = ("table_step", "corners_px", "stripe_px", "source")
STAGE_TARGET_DROPPED_KEYS = ("table_step", "images", "reason")


@dataclasses.dataclass(frozen=True)
class Nominal:
    """Nominal device values a user knows before calibration (all optional)."""

    focal_length_mm: float | None = None
    magnification: float | None = None
    tilt_deg: tuple[float, float] | None = None  # (phi, theta)


@dataclasses.dataclass(frozen=True)
class View:
    """One board pose: corner pixels (NaN rows where not detected) and stripe pixels."""

    corners_px: np.ndarray  # (M, 2) float64
    stripe_px: np.ndarray  # (K, 2) float64
    source: tuple[str, ...] = ()  # image file names the view was measured in
    # the board's motion between the view's laser-off and laser-on images (px); NaN: it
    # could not be measured; None: no laser-off image (or not measured)
    board_motion_px: float | None = None
    # the stripe centres' noise σ across the line (px) as measured in the images (a
    # speckled line); None: not measured
    stripe_sigma_px: float | None = None

    @property
    def corner_mask(self) -> np.ndarray:
        return np.all(np.isfinite(self.corners_px), axis=1)


@dataclasses.dataclass(frozen=True)
class DroppedView:
    """A capture left out of the observations: its view number, images and the reason."""

    view: int
    images: tuple[str, ...]
    reason: str


@dataclasses.dataclass(frozen=True)
class StageScan:
    """A gauge of known radius scanned on the rotary table."""

    delta_omega_deg: float
    gauge_radius_mm: float
    frames: list[np.ndarray]  # each (K_i, 2)


@dataclasses.dataclass(frozen=True)
class StageTargetViews:
    """A target fixed to the rotary table, imaged at several table steps.

    **Fields:**
    - `delta_omega_deg`: the table step (non-zero); view k was taken at the angle
      `table_steps[k] · delta_omega_deg`.
    - `board_points_mm` `(M, 3)`: the target's points (its own board).
    - `table_steps` `(F,)`: strictly increasing table steps of the views kept.
    - `corners_px`: `(F, M, 2)` corner pixels, NaN where not detected.
    - `sources`: per view the image names; `dropped`: the steps left out, as
      [`DroppedView`][] with `view` = the table step.
    - `stripe_px`: per view the laser line's pixels on the target (empty: none; the
      laser plane's distance from the target then ties the plane to the table).
    - `circle_diameter_mm`: the target's points are centres of circles of this diameter
      and `corners_px` the centroids of their images (as `Observations`'); None: points.
    """

    delta_omega_deg: float
    board_points_mm: np.ndarray
    table_steps: np.ndarray
    corners_px: np.ndarray
    sources: tuple[tuple[str, ...], ...] = ()
    dropped: list[DroppedView] = dataclasses.field(default_factory=list)
    stripe_px: tuple[np.ndarray, ...] = ()  # per view (K, 2): the laser line on the target
    circle_diameter_mm: float | None = None  # as `Observations.circle_diameter_mm`


@dataclasses.dataclass(frozen=True)
class Observations:
    """Everything calibration needs, as read from or written to an observations file."""

    width: int
    height: int
    pixel_pitch_mm: tuple[float, float] | None  # None: not given (datasheet value unknown)
    board_points_mm: np.ndarray  # (M, 3)
    views: list[View]
    nominal: Nominal | None = None
    stage: StageScan | None = None
    dropped: list[DroppedView] = dataclasses.field(default_factory=list)
    stage_target: StageTargetViews | None = None
    # the board's points are centres of circles of this diameter (mm) and `corners_px`
    # the centroids of their images; None: points imaged as points
    circle_diameter_mm: float | None = None

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        """All views' corners stacked, `(V, M, 2)`, and the detection mask `(V, M)`."""
        uv = np.stack([v.corners_px for v in self.views])
        return uv, np.all(np.isfinite(uv), axis=-1)


def near_centre(obs: Observations, px, radius_px: float) -> np.ndarray:
    """Which rows of the pixels `px` `(..., 2)` lie within `radius_px` of the sensor's
    centre `((width - 1) / 2, (height - 1) / 2)` (False for NaN rows)."""
    c = np.array([(obs.width - 1) / 2.0, (obs.height - 1) / 2.0])
    with np.errstate(invalid="ignore"):
        return np.linalg.norm(np.asarray(px, dtype=np.float64) - c, axis=-1) <= radius_px


def within_radius(obs: Observations, radius_px: float) -> Observations:
    """`obs` without the corners (NaN) and stripe pixels farther than `radius_px` from the
    sensor's centre (e.g. to calibrate inside a lens's unvignetted field)."""
    views = []
    for v in obs.views:
        cp = np.array(v.corners_px, dtype=float)
        cp[~near_centre(obs, cp, radius_px) & np.all(np.isfinite(cp), axis=1)] = np.nan
        sp = np.array(v.stripe_px, dtype=float).reshape(-1, 2)
        sp = sp[near_centre(obs, sp, radius_px)]
        views.append(dataclasses.replace(v, corners_px=cp, stripe_px=sp))
    return dataclasses.replace(obs, views=views)


class ObservationsError(ValueError):
    """A malformed observations file; the message names the problem."""


def _points(value, where: str, dim: int, *, allow_null: bool = False) -> np.ndarray:
    if not isinstance(value, list):
        raise ObservationsError(f"{where} must be a list of [{'u, v' if dim == 2 else 'x, y, z'}]")
    rows = []
    for i, p in enumerate(value):
        if p is None and allow_null:
            rows.append([math.nan] * dim)
            continue
        if (
            not isinstance(p, list)
            or len(p) != dim
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in p)
        ):
            raise ObservationsError(f"{where}[{i}] must be {dim} numbers, got {p!r}")
        if not all(math.isfinite(c) for c in p):
            raise ObservationsError(f"{where}[{i}] is not finite: {p!r}")
        rows.append([float(c) for c in p])
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), dim)


def _require(d: dict, key: str, where: str):
    if not isinstance(d, dict):
        raise ObservationsError(f"{where} must be an object")
    if key not in d:
        raise ObservationsError(f"missing key {where}.{key}" if where else f"missing key {key!r}")
    return d[key]


def _check_keys(d, allowed: tuple[str, ...], where: str) -> None:
    """Refuse keys of the object `d` not in `allowed`, suggesting the closest allowed one."""
    if not isinstance(d, dict):
        return  # the caller reports the wrong type
    for key in d:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            at = f"{where}.{key}" if where else str(key)
            raise ObservationsError(f"unknown key {at!r}{hint}; allowed here: {', '.join(allowed)}")


def _number(value, where: str, *, positive: bool = False) -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise ObservationsError(f"{where} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ObservationsError(f"{where} must be positive, got {value!r}")
    return float(value)


def _circle_diameter(doc: dict, board: np.ndarray, where: str) -> float | None:
    """An optional `circle_diameter_mm` of the object `doc` whose points are `board`."""
    at = f"{where}.circle_diameter_mm" if where else "circle_diameter_mm"
    value = doc.get("circle_diameter_mm")
    if value is None:
        return None
    value = _number(value, at, positive=True)
    if not np.all(board[:, 2] == board[0, 2]):
        raise ObservationsError(f"{at} needs a flat board (board_points_mm with one z)")
    return value


def parse_observations(doc) -> Observations:
    """Validate a decoded observations document; raises `ObservationsError`."""
    if not isinstance(doc, dict):
        raise ObservationsError("observations must be a JSON object")
    fmt = doc.get("format")
    if fmt != FORMAT:
        raise ObservationsError(f"format must be {FORMAT!r}, got {fmt!r}")
    _check_keys(doc, TOP_KEYS, "")
    sensor = _require(doc, "sensor", "")
    _check_keys(sensor, SENSOR_KEYS, "sensor")
    width = _number(_require(sensor, "width", "sensor"), "sensor.width", positive=True)
    height = _number(_require(sensor, "height", "sensor"), "sensor.height", positive=True)
    pitch = sensor.get("pixel_pitch_mm")
    if pitch is not None:
        if not isinstance(pitch, list) or len(pitch) != 2:
            raise ObservationsError("sensor.pixel_pitch_mm must be [dx, dy] or null")
        pitch = tuple(_number(p, "sensor.pixel_pitch_mm", positive=True) for p in pitch)

    nominal = None
    if doc.get("nominal") is not None:
        nd = doc["nominal"]
        if not isinstance(nd, dict):
            raise ObservationsError("nominal must be an object")
        _check_keys(nd, NOMINAL_KEYS, "nominal")
        tilt = nd.get("tilt_deg")
        if tilt is not None:
            if not isinstance(tilt, list) or len(tilt) != 2:
                raise ObservationsError("nominal.tilt_deg must be [phi, theta]")
            tilt = tuple(_number(t, "nominal.tilt_deg") for t in tilt)
        f = nd.get("focal_length_mm")
        m = nd.get("magnification")
        nominal = Nominal(
            None if f is None else _number(f, "nominal.focal_length_mm", positive=True),
            None if m is None else _number(m, "nominal.magnification", positive=True),
            tilt,
        )

    board = _points(_require(doc, "board_points_mm", ""), "board_points_mm", 3)
    if len(board) < 4:
        raise ObservationsError(f"board_points_mm has {len(board)} points; at least 4 needed")
    diameter = _circle_diameter(doc, board, "")
    views_doc = _require(doc, "views", "")
    if not isinstance(views_doc, list):
        raise ObservationsError("views must be a list")
    views = []
    for i, vd in enumerate(views_doc):
        _check_keys(vd, VIEW_KEYS, f"views[{i}]")
        corners = _points(
            _require(vd, "corners_px", f"views[{i}]"), f"views[{i}].corners_px", 2, allow_null=True
        )
        if len(corners) != len(board):
            raise ObservationsError(
                f"views[{i}].corners_px has {len(corners)} entries but board_points_mm has "
                f"{len(board)} (use null for corners that were not detected)"
            )
        stripe = _points(vd.get("stripe_px", []), f"views[{i}].stripe_px", 2)
        names = _names(vd.get("source", []), f"views[{i}].source")
        where = f"views[{i}]"
        views.append(View(corners, stripe, names, _motion(vd, where), _stripe_sigma(vd, where)))

    dropped = []
    dropped_doc = doc.get("dropped_views", [])
    if not isinstance(dropped_doc, list):
        raise ObservationsError("dropped_views must be a list")
    for i, dd in enumerate(dropped_doc):
        where = f"dropped_views[{i}]"
        _check_keys(dd, DROPPED_KEYS, where)
        k = _require(dd, "view", where)
        if not isinstance(k, int) or isinstance(k, bool) or k < 0:
            raise ObservationsError(f"{where}.view must be a view number >= 0, got {k!r}")
        reason = _require(dd, "reason", where)
        if not isinstance(reason, str):
            raise ObservationsError(f"{where}.reason must be a string")
        dropped.append(DroppedView(k, _names(dd.get("images", []), f"{where}.images"), reason))

    stage = None
    if doc.get("stage") is not None:
        sd = doc["stage"]
        _check_keys(sd, STAGE_KEYS, "stage")
        dw = _number(_require(sd, "delta_omega_deg", "stage"), "stage.delta_omega_deg")
        r = _number(
            _require(sd, "gauge_radius_mm", "stage"), "stage.gauge_radius_mm", positive=True
        )
        frames_doc = _require(sd, "frames", "stage")
        if not isinstance(frames_doc, list) or not frames_doc:
            raise ObservationsError("stage.frames must be a non-empty list of frames")
        frames = [_points(f, f"stage.frames[{i}]", 2) for i, f in enumerate(frames_doc)]
        stage = StageScan(dw, r, frames)

    target = None
    if doc.get("stage_target") is not None:
        target = _parse_stage_target(doc["stage_target"])
    if stage is not None and target is not None and stage.delta_omega_deg != target.delta_omega_deg:
        raise ObservationsError(
            f"stage.delta_omega_deg ({stage.delta_omega_deg:g}) and "
            f"stage_target.delta_omega_deg ({target.delta_omega_deg:g}) differ: one table, "
            "one step"
        )
    return Observations(
        int(width), int(height), pitch, board, views, nominal, stage, dropped, target, diameter
    )


def _step(value, where: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise ObservationsError(f"{where} must be a table step >= 0, got {value!r}")
    return int(value)


def _parse_stage_target(sd) -> StageTargetViews:
    if not isinstance(sd, dict):
        raise ObservationsError("stage_target must be an object")
    _check_keys(sd, STAGE_TARGET_KEYS, "stage_target")
    dw = _number(_require(sd, "delta_omega_deg", "stage_target"), "stage_target.delta_omega_deg")
    if dw == 0.0:
        raise ObservationsError("stage_target.delta_omega_deg must be a non-zero angle")
    board = _points(
        _require(sd, "board_points_mm", "stage_target"), "stage_target.board_points_mm", 3
    )
    if len(board) < 4:
        raise ObservationsError(
            f"stage_target.board_points_mm has {len(board)} points; at least 4 needed"
        )
    diameter = _circle_diameter(sd, board, "stage_target")
    views_doc = _require(sd, "views", "stage_target")
    if not isinstance(views_doc, list) or not views_doc:
        raise ObservationsError("stage_target.views must be a non-empty list")
    steps, corners, sources, stripes = [], [], [], []
    for i, vd in enumerate(views_doc):
        where = f"stage_target.views[{i}]"
        if not isinstance(vd, dict):
            raise ObservationsError(f"{where} must be an object")
        _check_keys(vd, STAGE_TARGET_VIEW_KEYS, where)
        steps.append(_step(_require(vd, "table_step", where), f"{where}.table_step"))
        c = _points(_require(vd, "corners_px", where), f"{where}.corners_px", 2, allow_null=True)
        if len(c) != len(board):
            raise ObservationsError(
                f"{where}.corners_px has {len(c)} entries but stage_target.board_points_mm "
                f"has {len(board)} (use null for corners that were not detected)"
            )
        corners.append(c)
        stripes.append(_points(vd.get("stripe_px", []), f"{where}.stripe_px", 2))
        sources.append(_names(vd.get("source", []), f"{where}.source"))
    if any(b <= a for a, b in zip(steps, steps[1:])):
        raise ObservationsError(
            f"stage_target.views: table steps {steps} are not strictly increasing "
            "(one view per step, in table order)"
        )
    dropped = []
    dd_doc = sd.get("dropped_views", [])
    if not isinstance(dd_doc, list):
        raise ObservationsError("stage_target.dropped_views must be a list")
    for i, dd in enumerate(dd_doc):
        where = f"stage_target.dropped_views[{i}]"
        _check_keys(dd, STAGE_TARGET_DROPPED_KEYS, where)
        k = _step(_require(dd, "table_step", where), f"{where}.table_step")
        if k in steps:
            raise ObservationsError(f"{where}: table step {k} is also a kept view")
        reason = _require(dd, "reason", where)
        if not isinstance(reason, str):
            raise ObservationsError(f"{where}.reason must be a string")
        dropped.append(DroppedView(k, _names(dd.get("images", []), f"{where}.images"), reason))
    return StageTargetViews(
        dw, board, np.asarray(steps, dtype=np.int64), np.stack(corners), tuple(sources), dropped,
        tuple(stripes) if any(len(x) for x in stripes) else (), diameter,
    )  # fmt: skip


def _motion(vd: dict, where: str) -> float | None:
    """A view's `board_motion_px`: a number >= 0, null (not measurable: NaN) or absent."""
    if "board_motion_px" not in vd:
        return None
    m = vd["board_motion_px"]
    if m is None:
        return math.nan
    if isinstance(m, bool) or not isinstance(m, (int, float)) or not 0 <= m < math.inf:
        raise ObservationsError(
            f"{where}.board_motion_px must be a number of pixels >= 0 or null, got {m!r}"
        )
    return float(m)


def _stripe_sigma(vd: dict, where: str) -> float | None:
    """A view's `stripe_sigma_px`: a number > 0, or absent (None)."""
    if "stripe_sigma_px" not in vd:
        return None
    s = vd["stripe_sigma_px"]
    if isinstance(s, bool) or not isinstance(s, (int, float)) or not 0 < s < math.inf:
        raise ObservationsError(
            f"{where}.stripe_sigma_px must be a number of pixels > 0, got {s!r}"
        )
    return float(s)


def _names(value, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(n, str) for n in value):
        raise ObservationsError(f"{where} must be a list of file names")
    return tuple(value)


def read_observations(path: str | os.PathLike) -> Observations:
    """Read and validate an observations file; errors name the file and the problem."""
    doc = load_json(path, "observations")
    try:
        return parse_observations(doc)
    except ObservationsError as err:
        raise ObservationsError(f"{os.fspath(path)}: {err}") from None


def _rows(a: np.ndarray) -> list:
    return [None if not np.all(np.isfinite(r)) else [float(c) for c in r] for r in a]


def observations_to_dict(obs: Observations) -> dict:
    doc = {
        "format": FORMAT,
        "sensor": {
            "width": int(obs.width),
            "height": int(obs.height),
        },
    }
    if obs.pixel_pitch_mm is not None:
        doc["sensor"]["pixel_pitch_mm"] = [float(p) for p in obs.pixel_pitch_mm]
    if obs.nominal is not None:
        n = obs.nominal
        doc["nominal"] = {
            k: v
            for k, v in (
                ("focal_length_mm", n.focal_length_mm),
                ("magnification", n.magnification),
                ("tilt_deg", None if n.tilt_deg is None else list(n.tilt_deg)),
            )
            if v is not None
        }
    doc["board_points_mm"] = _rows(np.asarray(obs.board_points_mm))
    if obs.circle_diameter_mm is not None:
        doc["circle_diameter_mm"] = float(obs.circle_diameter_mm)
    doc["views"] = [
        {
            "corners_px": _rows(np.asarray(v.corners_px)),
            "stripe_px": [r for r in _rows(np.asarray(v.stripe_px)) if r is not None],
            **({"source": list(v.source)} if v.source else {}),
            **(
                {}
                if v.board_motion_px is None
                else {
                    "board_motion_px": None
                    if math.isnan(v.board_motion_px)
                    else float(v.board_motion_px)
                }
            ),
            **({} if v.stripe_sigma_px is None else {"stripe_sigma_px": float(v.stripe_sigma_px)}),
        }
        for v in obs.views
    ]
    if obs.dropped:
        doc["dropped_views"] = [
            {"view": int(d.view), "images": list(d.images), "reason": str(d.reason)}
            for d in obs.dropped
        ]
    if obs.stage is not None:
        doc["stage"] = {
            "delta_omega_deg": float(obs.stage.delta_omega_deg),
            "gauge_radius_mm": float(obs.stage.gauge_radius_mm),
            "frames": [
                [r for r in _rows(np.asarray(f).reshape(-1, 2)) if r is not None]
                for f in obs.stage.frames
            ],
        }
    if obs.stage_target is not None:
        t = obs.stage_target
        doc["stage_target"] = {
            "delta_omega_deg": float(t.delta_omega_deg),
            "board_points_mm": _rows(np.asarray(t.board_points_mm)),
            **(
                {}
                if t.circle_diameter_mm is None
                else {"circle_diameter_mm": float(t.circle_diameter_mm)}
            ),
            "views": [
                {
                    "table_step": int(k),
                    "corners_px": _rows(np.asarray(c)),
                    **(
                        {"stripe_px": [r for r in _rows(np.asarray(t.stripe_px[i])) if r]}
                        if i < len(t.stripe_px) and len(t.stripe_px[i])
                        else {}
                    ),
                    **(
                        {"source": list(t.sources[i])}
                        if i < len(t.sources) and t.sources[i]
                        else {}
                    ),
                }
                for i, (k, c) in enumerate(zip(t.table_steps, t.corners_px))
            ],
        }
        if t.dropped:
            doc["stage_target"]["dropped_views"] = [
                {"table_step": int(d.view), "images": list(d.images), "reason": str(d.reason)}
                for d in t.dropped
            ]
    return doc


def write_observations(path, obs: Observations, *, overwrite: bool = False) -> None:
    """Write an observations file atomically (never clobbers unless `overwrite`)."""
    parse_observations(observations_to_dict(obs))  # refuse to write what we couldn't read
    write_json(path, observations_to_dict(obs), overwrite=overwrite)
