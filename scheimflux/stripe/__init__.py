"""Sub-pixel laser-stripe centre extraction (Steger's Hessian method, grey centroid).

NumPy/OpenCV only: never called inside traced JAX code.
"""

from ._extract import extract_stripe as extract_stripe, extract_stripes as extract_stripes
from ._folder import (
    FrameStripes as FrameStripes,
    frame_files as frame_files,
    iter_folder_stripes as iter_folder_stripes,
)
from ._image import CHANNELS as CHANNELS
from ._kernels import steger_sigma as steger_sigma
from ._mask import region_mask as region_mask
from ._result import StripeResult as StripeResult

__all__ = [
    "CHANNELS",
    "extract_stripe",
    "extract_stripes",
    "frame_files",
    "FrameStripes",
    "iter_folder_stripes",
    "region_mask",
    "steger_sigma",
    "StripeResult",
]
