"""Two-sided ridge response and the scan direction chosen from it.

A bright line is brighter than the image on *both* sides of it; a step edge (a checker
edge, the rim of a dot) is brighter on one side only. The two-sided response

    R_e(p) = min(I(p) - I(p - d e), I(p) - I(p + d e))

along a unit direction `e` is positive on a ridge crossing `e` and zero or negative on
a step, whatever the step's height. It is computed on the 4x-downsampled image, so it
is cheap: it positions the coarse track and decides the scan direction.

Scan direction: the energies `sum R_e⁺` for `e` along v, u and the two diagonals form
the ridge-normal tensor `T = Σ_e E_e e eᵀ`; its leading eigenvector is the dominant
direction across the lines (vertical-scan when it is closer to v than to u). Its
coherence `(λ1 - λ2) / (λ1 + λ2)` measures how clearly one direction dominates: lines
in several directions (or none) give a low coherence, reported as ambiguous.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from . import _fast

# Coherence of the ridge-normal tensor below which the scan direction is ambiguous. A
# single straight line gives about 0.5 (the response falls off slowly with the angle),
# a 45-degree line 0.3-0.4; two crossing lines or isotropic blobs well below 0.15.
AMBIGUOUS_COHERENCE = 0.12
# The unit directions (u, v) of the four two-sided responses of `scan_direction`: along
# v, along u and the two diagonals.
_DIRECTIONS = (
    (0.0, 1.0),
    (1.0, 0.0),
    (math.sqrt(0.5), math.sqrt(0.5)),
    (math.sqrt(0.5), -math.sqrt(0.5)),
)


def ridge_offset(width_px: float, factor: int = 4) -> int:
    """Offset `d` (coarse pixels) of the two-sided response for a line of FWHM
    `width_px` on a `factor`-times downsampled image: one line width plus one coarse
    pixel, at least 2. (With `d = 1` a line centred on a block boundary becomes a
    two-pixel plateau whose response is zero.)"""
    return max(2, int(round(width_px / factor)) + 1)


def ridge_response(small: np.ndarray, d: int, axis: int) -> np.ndarray:
    """Two-sided ridge response of `small` along `axis` (0: v, rows; 1: u) at offset `d`,
    same shape, 0 where a side falls outside the image."""
    out = np.zeros_like(small)
    if axis == 0:
        c = small[d:-d]
        out[d:-d] = np.minimum(c - small[: -2 * d], c - small[2 * d :])
    else:
        c = small[:, d:-d]
        out[:, d:-d] = np.minimum(c - small[:, : -2 * d], c - small[:, 2 * d :])
    return out


def scan_direction(
    small: np.ndarray, d: int, weight: np.ndarray | None, floor: float
) -> tuple[str, float, float]:
    """The scan direction from the ridge-normal tensor of `small` (4x downsampled image).

    **Arguments:**
    - `small`: the downsampled image (image frame: rows v, columns u).
    - `d`: offset of the two-sided response (coarse pixels).
    - `weight`: optional (same shape) weights in [0, 1] (the mask), or None.
    - `floor`: responses below it (noise) are ignored.

    **Returns:** `(orientation, normal_angle_deg, coherence)`: `"vertical-scan"` or
    `"horizontal-scan"`, the angle of the dominant line normal from the u axis in
    [0, 180), and the tensor's coherence in [0, 1] (0 when there is no ridge at all).
    """
    # One more 2 x 2 reduction: the direction needs no fine detail (4x cheaper).
    h2, w2 = small.shape[0] // 2, small.shape[1] // 2
    if min(h2, w2) >= 8:
        small = cv2.resize(small[: 2 * h2, : 2 * w2], (w2, h2), interpolation=cv2.INTER_AREA)
        if weight is not None:
            weight = cv2.resize(
                weight[: 2 * h2, : 2 * w2].astype(np.float32), (w2, h2),
                interpolation=cv2.INTER_AREA,
            )
        d = max(2, int(round(d / 2)))
        floor = floor / 2.0  # block-mean noise halves
    dd = max(1, int(round(d / math.sqrt(2.0))))

    # Interior responses only (outside it `ridge_response` gives 0, which `> floor`
    # never passes): the same positive parts, in the same order, as the full arrays.
    def interior():  # the responses on the interior, where each is defined
        c, cd = small[d:-d], small[dd:-dd, dd:-dd]
        yield np.minimum(c - small[: -2 * d], c - small[2 * d :]), np.s_[d:-d]
        c = small[:, d:-d]
        yield np.minimum(c - small[:, : -2 * d], c - small[:, 2 * d :]), np.s_[:, d:-d]
        yield (
            np.minimum(cd - small[: -2 * dd, : -2 * dd], cd - small[2 * dd :, 2 * dd :]),
            np.s_[dd:-dd, dd:-dd],
        )
        yield (
            np.minimum(cd - small[: -2 * dd, 2 * dd :], cd - small[2 * dd :, : -2 * dd]),
            np.s_[dd:-dd, dd:-dd],
        )

    if _fast.enabled and weight is None and small.dtype == np.float32:
        # the positive responses below from one compiled call (the same float32 values
        # in the same order: the same sums)
        pos, count = _fast.ridge_positive(np.ascontiguousarray(small), d, dd, floor)
        energies = [pos[k, : count[k]].sum() for k in range(4)]
    else:
        energies = []
        for resp, where in interior():
            r = resp - floor
            if weight is not None:
                r = r * weight[where]
            energies.append(np.sum(r[r > 0]))
    # the tensor T = [[a, b], [b, c]], summed in float64 in the order of the directions
    a = b = c = 0.0
    for e, (eu, ev) in zip(energies, _DIRECTIONS):
        e = float(e)
        a += e * (eu * eu)
        b += e * (eu * ev)
        c += e * (ev * ev)
    if not a + c > 0:
        return "vertical-scan", 90.0, 0.0
    # eigen-decomposition of the symmetric 2 x 2 tensor in closed form: eigenvalues
    # (a + c) / 2 ± hypot((a - c) / 2, b), leading eigenvector at half the angle of
    # (a - c, 2 b)
    coherence = math.hypot(0.5 * (a - c), b) / (0.5 * (a + c))
    theta = 0.5 * math.atan2(2.0 * b, a - c)
    nu, nv = math.cos(theta), math.sin(theta)
    angle = math.degrees(theta) % 180.0
    orientation = "vertical-scan" if abs(nv) >= abs(nu) else "horizontal-scan"
    return orientation, angle, coherence


def is_ambiguous(coherence: float) -> bool:
    """No dominant line direction (lines in several directions, blobs, or no line)."""
    return coherence < AMBIGUOUS_COHERENCE
