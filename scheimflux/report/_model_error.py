"""A Fig.-3-style map of the calibrated model's error over the field, from the data.

The paper's Fig. 3 shows, over the image, how far the object point a model recovers from
a pixel lies from the true one. Against a real lens the truth is not known; what the
calibration does know is where its model misses the board corners systematically. The
binned **mean** corner residual (the noise averages out, the model error does not) is
that miss in the image; mapped through the calibrated camera onto the laser plane it is
the object-side error in µm that a point reconstructed at that pixel would carry, the
quantity of Fig. 3. (The ray-traced Fig. 3 itself, against the law of refraction, is
`scripts/fig3.py`, docs/fig3.md.)
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["ModelErrorMap", "model_error_map"]


@dataclasses.dataclass(frozen=True)
class ModelErrorMap:
    """The systematic corner residual over the sensor, in px and on the laser plane.

    **Fields:** (each `(nv, nu)`, NaN where a bin holds no corner)
    - `error_um`: object-side length on the laser plane of the mean residual vector
      (µm): the error of a point reconstructed from a pixel of that bin.
    - `mean_px`: `(nv, nu, 2)` mean residual (projected − observed, px).
    - `noise_px`: what noise alone gives for `|mean|`: `σ_corner √(2 / n)` (the RMS length
      of the mean of n 2-D residuals of σ per coordinate).
    - `counts`: corners per bin; `edges_u`, `edges_v`: the bin edges (px).
    """

    error_um: np.ndarray
    mean_px: np.ndarray
    noise_px: np.ndarray
    counts: np.ndarray
    edges_u: np.ndarray
    edges_v: np.ndarray

    @property
    def significant(self) -> np.ndarray:
        """Bins whose mean residual exceeds twice what noise gives (model error shows)."""
        with np.errstate(invalid="ignore"):
            return np.linalg.norm(self.mean_px, axis=-1) > 2 * self.noise_px


def model_error_map(cal, *, bins: tuple[int, int] = (16, 12)) -> ModelErrorMap:
    """The binned systematic corner residual of `cal`, and its size on the laser plane.

    **Arguments:**
    - `cal`: a `Calibration` with its data (read with its observations) and laser plane.
    - `bins`: `(nu, nv)` bins over the sensor.

    **Returns:** a [`ModelErrorMap`][].
    """
    from ..calibration import residual_map
    from ..reconstruct import stripe_to_camera

    if cal.plane is None:
        raise ValueError("the model-error map needs a laser plane (a camera-only calibration)")
    size = getattr(cal, "sensor_size", None)
    mean_u, mean_v, _, counts = residual_map(cal, bins=bins, size=size)
    w, h = size
    nu, nv = (int(b) for b in bins)
    eu = np.linspace(-0.5, w - 0.5, nu + 1)
    ev = np.linspace(-0.5, h - 0.5, nv + 1)
    cu, cv = np.meshgrid(0.5 * (eu[1:] + eu[:-1]), 0.5 * (ev[1:] + ev[:-1]))
    centre = np.stack([cu, cv], axis=-1)
    mean = np.stack([mean_u, mean_v], axis=-1)
    # the observed pixel of a corner lies at projected − residual: a point seen at the
    # bin centre truly sits where the model sends centre − mean
    shifted = centre - np.nan_to_num(mean)
    both = np.concatenate([centre.reshape(-1, 2), shifted.reshape(-1, 2)])
    pts = np.asarray(stripe_to_camera(cal.camera, cal.plane, both).points)
    a, b = pts[: nu * nv], pts[nu * nv :]
    err = 1e3 * np.linalg.norm(a - b, axis=1).reshape(nv, nu)
    err = np.where(counts > 0, err, np.nan)
    sigma = float(cal.data.sigma_corner_px)
    with np.errstate(divide="ignore"):
        noise = np.where(counts > 0, sigma * np.sqrt(2.0 / np.maximum(counts, 1)), np.nan)
    return ModelErrorMap(err, mean, noise, counts, eu, ev)
