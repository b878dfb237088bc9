"""Capture folders → observations: target detection, board stripes, dropped views,
previews."""

from ._folder import (
    IMAGE_SUFFIXES as IMAGE_SUFFIXES,
    CaptureView as CaptureView,
    find_captures as find_captures,
    read_image as read_image,
)
from ._laser import (
    fill_holes as fill_holes,
    near_laser as near_laser,
    off_local_grid as off_local_grid,
    target_holes as target_holes,
)
from ._preview import write_preview as write_preview
from ._region import board_region as board_region, board_stripe as board_stripe
from ._session import detect_session as detect_session
from ._workflow import (
    CaptureReport as CaptureReport,
    detect_captures as detect_captures,
    extract_scan as extract_scan,
)

__all__ = [
    "board_region",
    "board_stripe",
    "CaptureReport",
    "CaptureView",
    "detect_captures",
    "detect_session",
    "extract_scan",
    "fill_holes",
    "find_captures",
    "IMAGE_SUFFIXES",
    "near_laser",
    "off_local_grid",
    "read_image",
    "target_holes",
    "write_preview",
]
