"""The whole printout of `scheimflux calibrate`: the file's document, then what the
calibration can be trusted for (`trust._summary`)."""

from __future__ import annotations

from ._file import calibration_to_dict
from .trust._summary import CAMERA_ONLY_NOTE, format_summary, format_trust, trust_entries

__all__ = ["calibration_summary"]


def calibration_summary(cal, doc: dict | None = None) -> str:
    """Everything `scheimflux calibrate` prints about a calibration.

    **Arguments:**
    - `cal`: a `Calibration`.
    - `doc`: its calibration document when already built (what is written to CAL.json);
      by default `calibration_to_dict(cal, diagnostics=trust_entries(cal))`.

    **Returns:** [`format_summary`][] of the document, then [`format_trust`][] of `cal`,
    then a note for a camera-only calibration, one item a line.
    """
    if doc is None:
        doc = calibration_to_dict(cal, diagnostics=trust_entries(cal))
    parts = [format_summary(doc), format_trust(cal)]
    if cal.params.plane is None:
        parts.append(CAMERA_ONLY_NOTE)
    return "\n".join(parts)

