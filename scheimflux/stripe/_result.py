"""`StripeResult`: the sub-pixel centres found in one image."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class StripeResult:
    """Laser-stripe centres of one image, one entry per scan line.

    With `orientation="vertical-scan"` there is one entry per image column `u` (the stripe
    runs mostly left–right); with `"horizontal-scan"` one entry per row `v`. Pixel (0, 0) is
    the centre of the top-left pixel; u grows to the right, v downwards.

    **Fields:**
    - `uv`: sub-pixel centres `(u, v)`, shape (N, 2), float64; NaN where `valid` is False.
      The scan coordinate is exact (the column `u` for a vertical scan), the other one is
      where the stripe's centre line crosses that scan line.
    - `strength`: line strength, shape (N,): `-sigma² · ∂²I/∂n²` (scale-normalised second
      derivative across the stripe, in the image's grey levels) for Steger; the
      background-subtracted peak grey level for the centroid method; 0 where invalid.
    - `width`: estimated full width at half maximum across the stripe in pixels, shape (N,);
      NaN where invalid or not measurable.
    - `valid`: shape (N,), bool: a centre was found, strong enough and consistent with its
      neighbours. Gaps and rejected reflections are False.
    - `saturated`: shape (N,), bool: the stripe's peak reached the saturation level there
      (the centre is still measured, from the plateau).
    - `orientation`: `"vertical-scan"` or `"horizontal-scan"`, the scan actually used.
    - `method`: `"steger"` or `"centroid"`.
    - `confidence`: shape (N,), in [0, 1]: the strength over four times the acceptance
      threshold (capped at 1) times the profile's symmetry (1 for a symmetric profile,
      0 at the asymmetry limit); 0 where invalid. Default: `valid` as 0/1.
    - `segment`: shape (N,), int: the line segment a valid centre was linked into (-1
      where invalid).
    - `channel`: the channel (or combination) of a colour image that was used, `"grey"`
      for grey images.
    - `ambiguous`: True when the image showed no dominant line direction (several line
      directions, blobs or no line), so `orientation="auto"` was a guess.
    - `normal_angle_deg`: the dominant direction across the lines, degrees from the u
      axis in [0, 180) (90: a horizontal line), from the ridge-normal tensor.
    - `steep`: shape (N,), bool: the centre was found by the other scan direction, where
      the line runs too steep for `orientation`'s scan lines (a curved line; with
      `orientation="auto"` only). Where any is True the entries are the line's centres
      in order along it (the steep parts inserted at their place), no longer one per
      scan line. Default: all False.
    - `steep_left_out_px`, `steep_left_out_fraction`: the length (px along the line) and
      fraction of the line found by the other scan direction but not returned, because
      `orientation` was given (one centre per scan line asked for); 0 otherwise.
    - `speckle_px`: where the line was found speckled (nearly every profile asymmetric,
      at random along the line: laser speckle), the robust scatter (px, across the
      line) of its centres about a straight line through their neighbours; the
      centres are then kept with a looser asymmetry bound and are each off by about
      that much (`detect` writes it as the view's `stripe_sigma_px`, by which
      `calibrate` weights the view's stripe points). 0 for a line that is not speckled.
    """

    uv: np.ndarray
    strength: np.ndarray
    width: np.ndarray
    valid: np.ndarray
    saturated: np.ndarray
    orientation: str = "vertical-scan"
    method: str = "steger"
    confidence: np.ndarray | None = None
    segment: np.ndarray | None = None
    channel: str = "grey"
    ambiguous: bool = False
    normal_angle_deg: float = float("nan")
    steep: np.ndarray | None = None
    steep_left_out_px: float = 0.0
    steep_left_out_fraction: float = 0.0
    speckle_px: float = 0.0

    def __post_init__(self):
        n = self.uv.shape[0]
        if self.steep is None:
            object.__setattr__(self, "steep", np.zeros(n, bool))
        if self.confidence is None:
            object.__setattr__(self, "confidence", np.asarray(self.valid, np.float64))
        if self.segment is None:
            object.__setattr__(self, "segment", np.where(self.valid, 0, -1).astype(np.intp))
        if self.uv.shape != (n, 2):
            raise ValueError(f"StripeResult.uv must have shape (N, 2), got {self.uv.shape}")
        for name in ("strength", "width", "valid", "saturated", "confidence", "segment", "steep"):
            if getattr(self, name).shape != (n,):
                raise ValueError(
                    f"StripeResult.{name} must have shape ({n},), got {getattr(self, name).shape}"
                )

    @property
    def valid_uv(self) -> np.ndarray:
        """The valid centres only, shape (M, 2), float64."""
        return self.uv[self.valid]

    @property
    def valid_confidence(self) -> np.ndarray:
        """The confidence of the valid centres only, shape (M,), float64."""
        return np.asarray(self.confidence, np.float64)[self.valid]

    def __len__(self) -> int:
        return self.uv.shape[0]
