"""Capture folders → observations: target detection, board stripes, dropped views,
previews."""

from ._folder import (
    IMAGE_SUFFIXES as IMAGE_SUFFIXES,
    CaptureView as CaptureView,
    find_captures as find_captures,
    read_image as read_image,
)
from ._preview import write_preview as write_preview
from ._region import board_region as board_region, board_stripe as board_stripe
from ._workflow import (
    CaptureReport as CaptureReport,
    detect_captures as detect_captures,
    extract_scan as extract_scan,
)
