"""Stripe pixels → rays → laser plane → camera and measurement frames."""

from ._reconstruct import (
    Reconstruction as Reconstruction,
    Status as Status,
    intersect_ray_plane as intersect_ray_plane,
    stripe_to_camera as stripe_to_camera,
    stripe_to_measurement as stripe_to_measurement,
)
from ._stream import (
    iter_reconstruct as iter_reconstruct,
    reconstruct_frames as reconstruct_frames,
)

__all__ = [
    "intersect_ray_plane",
    "iter_reconstruct",
    "reconstruct_frames",
    "Reconstruction",
    "Status",
    "stripe_to_camera",
    "stripe_to_measurement",
]
