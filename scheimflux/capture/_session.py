"""A whole calibration session from image folders: the capture folder's views, the
rotary-stage scan, the sensor and the nominal values, as one `Observations`.

This is what `scheimflux detect` runs; the command only parses its options, calls
[`detect_session`][] and prints the report.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence

from ..io._observations import Nominal, Observations
from ..targets._target import Target
from ._stage_target import detect_stage_target
from ._workflow import CaptureReport, detect_captures, extract_scan

__all__ = ["detect_session"]


def detect_session(
    folder: str | os.PathLike,
    target: Target,
    *,
    pixel_pitch_mm: Sequence[float] | None = None,
    focal_length_mm: float | None = None,
    magnification: float | None = None,
    tilt_deg: Sequence[float] | None = None,
    scan: str | os.PathLike | None = None,
    delta_omega_deg: float | None = None,
    gauge_radius_mm: float | None = None,
    stage_target: str | os.PathLike | None = None,
    stage_target_board: Target | None = None,
    stripe_width_px: float | None = None,
    margin_px: float | None = None,
    min_points: int = 6,
    mirrored: bool = False,
    preview_dir: str | os.PathLike | None = None,
    on_note: Callable[[str], None] | None = None,
) -> tuple[Observations, CaptureReport]:
    """Observations of a calibration session: the target and the board stripes of every
    view in `folder` ([`detect_captures`][]), optionally the stage scan in `scan`
    ([`extract_scan`][]).

    **Arguments:**
    - `folder`, `target`, `pixel_pitch_mm`, `stripe_width_px`, `margin_px`,
      `min_points`, `mirrored`, `preview_dir`: as for `detect_captures`.
    - `focal_length_mm`, `magnification`, `tilt_deg`: nominal values recorded in the
      file (any subset; none: no nominal block).
    - `scan`: folder of rotary-stage scan frames; needs `delta_omega_deg` (stage step
      per frame) and `gauge_radius_mm` (nominal gauge radius). Its frames must have the
      board images' size.
    - `stage_target`: folder of a target fixed to the rotary table, one image per
      table step in natural name order, `NAME_off.EXT` beside a step image its laser-off
      image ([`detect_stage_target`][]: the laser line on the target into each step's
      `stripe_px`); needs `delta_omega_deg`. `stage_target_board`: that target
      (default: `target`).
    - `on_note`: called with each one-line remark while running (dropped views, notes,
      ignored files, scan frames kept empty, no pixel pitch).

    **Returns:** `(observations, report)`; the report's notes hold every remark made.

    **Raises:** `ValueError` (one line, naming the file or option) for a folder without
    capture images, images of different sizes, a target found in no view, a scan
    without its step or radius (or a step or radius without a scan), or a scan folder
    without images; `FileNotFoundError`/`NotADirectoryError` for missing folders.
    """
    say = on_note or (lambda m: None)
    if scan is None and gauge_radius_mm is not None:
        raise ValueError("gauge_radius_mm needs a scan folder")
    if scan is None and stage_target is None and delta_omega_deg is not None:
        raise ValueError("delta_omega_deg needs a scan or a stage-target folder")
    if stage_target is not None and delta_omega_deg is None:
        raise ValueError(
            f"the stage target {os.fspath(stage_target)} needs delta_omega_deg (the table step)"
        )
    if scan is not None and (delta_omega_deg is None or gauge_radius_mm is None):
        raise ValueError(f"the scan {os.fspath(scan)} needs delta_omega_deg and gauge_radius_mm")
    nominal = None
    if focal_length_mm is not None or magnification is not None or tilt_deg is not None:
        nominal = Nominal(
            focal_length_mm, magnification, None if tilt_deg is None else tuple(tilt_deg)
        )
    obs, report = detect_captures(
        folder,
        target,
        pixel_pitch_mm=pixel_pitch_mm,
        nominal=nominal,
        stripe_width_px=stripe_width_px,
        margin_px=margin_px,
        min_points=min_points,
        mirrored=mirrored,
        preview_dir=preview_dir,
        on_view=lambda k, m: say(m),
    )

    def note(m: str) -> None:  # kept in the report and said as it happens
        report.notes.append(m)
        say(m)

    # the scan and stage-target folders given may lie inside the capture folder (as
    # `scheimflux simulate --images` writes them): read, not ignored
    given = {os.path.realpath(p) for p in (scan, stage_target) if p is not None}
    ignored = [n for n in report.ignored
               if os.path.realpath(os.path.join(folder, n.rstrip("/"))) not in given]  # fmt: skip
    if ignored:
        shown = ", ".join(ignored[:5]) + (" ..." if len(ignored) > 5 else "")
        note(f"ignored {len(ignored)} name(s) not like a capture "
             f"(view_<k>[_board|_stripe|_off].<ext>): {shown}")
    if scan is not None:
        stage = extract_scan(
            scan,
            delta_omega_deg,
            gauge_radius_mm,
            stripe_width_px=stripe_width_px,
            shape=(obs.height, obs.width),
            on_frame=note,
        )
        obs = dataclasses.replace(obs, stage=stage)
    if stage_target is not None:
        views = detect_stage_target(
            stage_target,
            target if stage_target_board is None else stage_target_board,
            delta_omega_deg,
            shape=(obs.height, obs.width),
            stripe_width_px=stripe_width_px,
            margin_px=margin_px,
            min_points=min_points,
            mirrored=mirrored,
            on_step=note,
            diameters_mm=report.table_circle_diameters_mm,
        )
        obs = dataclasses.replace(obs, stage_target=views)
    if obs.pixel_pitch_mm is None:
        note(
            "no pixel pitch given (--pixel-pitch-mm): none recorded; the thick-lens model "
            "needs it"
        )
    return obs, report
