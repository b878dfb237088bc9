"""Calibration reports: one self-contained HTML page with embedded PNG images."""

from ._html import Report as Report, build_report as build_report, write_report as write_report

__all__ = [
    "build_report",
    "Report",
    "write_report",
]
