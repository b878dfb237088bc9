"""`channel="auto"`: pick the colour channel (or combination) in which the laser shows best.

Each candidate signal (grey, each colour minus the other two, each plain colour) is
downsampled 4x; its two-sided ridge response (`_ridge`) is taken along v and along u,
and per scan line the largest response above four times its noise is kept. The score
is the sum of these maxima over the scan lines divided by the candidate's noise: a
long, clear line scores high, glints (a few scan lines) and checker edges (no
two-sided response) do not. White light and a grey target cancel in `X-minus-others`,
so a coloured laser on a checkerboard is taken from there (preferred over the plain
colour down to half its score); a grey image is always `"grey"`.
"""

from __future__ import annotations

import numpy as np

from ._coarse import downsample
from ._image import channel_image, estimate_noise
from ._ridge import ridge_offset, ridge_response

CANDIDATES = (
    "grey",
    "red-minus-others",
    "green-minus-others",
    "blue-minus-others",
    "red",
    "green",
    "blue",
)


def _score(signal: np.ndarray, width_px: float, mask_small: np.ndarray | None) -> float:
    small = downsample(signal)
    noise = max(estimate_noise(signal), 0.3) * 0.354
    d = ridge_offset(width_px)
    best = 0.0
    for axis in (0, 1):
        r = ridge_response(small, d, axis)
        if mask_small is not None:
            r = np.where(mask_small, r, 0.0)
        peak = r.max(axis=axis)
        best = max(best, float(np.sum(peak[peak > 4.0 * noise])) / noise)
    return best


def pick_channel(img: np.ndarray, width_px: float, mask_small: np.ndarray | None = None) -> str:
    """The candidate channel with the highest ridge score (see the module docstring);
    `"grey"` for grey images and for colour images whose channels are equal."""
    return ranked_channels(img, width_px, mask_small)[0]


def ranked_channels(
    img: np.ndarray, width_px: float, mask_small: np.ndarray | None = None
) -> tuple[str, ...]:
    """All candidates, the one `pick_channel` takes first, the others by falling score;
    `("grey",)` for grey images and for colour images whose channels are equal."""
    if img.ndim == 2:
        return ("grey",)
    if np.array_equal(img[:, :, 0], img[:, :, 1]) and np.array_equal(img[:, :, 1], img[:, :, 2]):
        return ("grey",)
    scores = {c: _score(channel_image(img, c)[0], width_px, mask_small) for c in CANDIDATES}
    best = max(scores, key=scores.get)
    # A laser seen best in one plain colour is taken from that colour minus the others
    # when it still scores half as well there: white light, grey targets, checker edges
    # and white glints cancel in the combination, at sqrt(1.5) times the noise.
    combined = f"{best}-minus-others"
    if best in ("red", "green", "blue") and scores[combined] >= 0.5 * scores[best]:
        best = combined
    rest = sorted((c for c in CANDIDATES if c != best), key=lambda c: -scores[c])
    return (best, *rest)
