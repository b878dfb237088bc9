"""How far the joint solve moved the camera from what its corners alone determine.

The corners-only solve (`calibrate_camera`) is the reference: its camera has the
covariance `Σ = s² (JᵀJ)⁺` of the corners, with `s²` their own variance factor (the
data's noise where it exceeds the stated one; the stated σ is a floor). The joint solve
adds the laser lines; where they are unbiased and weighted by their noise, the joint
camera differs from the reference by
`Δ` with covariance `Σ − Σ_joint ≤ Σ`, so `d² = Δᵀ Σ⁺ Δ` is at most chi-square
distributed with one degree of freedom per camera parameter. A `d²` beyond its
`1 − TAIL` quantile is a finding — stripe points off their boards, a line from the wrong
view, a bent board, stripe weights far too high — not a refinement: the workflow then
keeps the corners' camera and fits the laser plane (and stage) to it, and says so. (The
workflow checks it for the models whose corners determine the camera — OpenCV's, the
pinhole —, not for the thick lens, whose tilt and axis point the lines determine.)
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core._solve import split

__all__ = ["CameraShift", "TAIL", "camera_shift"]

# The chi-square tail beyond which the joint camera is "moved" (1e-4: about 3.7σ one
# parameter at a time; a data set calibrated 10 000 times is wrongly held once).
TAIL = 1e-4


@dataclasses.dataclass(frozen=True)
class CameraShift:
    """The joint camera against the corners-only camera.

    **Fields:** `d2`: Mahalanobis distance squared in the corners' covariance; `limit`:
    its chi-square quantile at `1 − TAIL`; `dof`: camera parameters compared; `worst`:
    `(label, corners-only value, joint value, σ)` of the parameter moved most in its σ;
    `s2`: the corners' variance factor the covariance carries; `table`: every compared
    parameter's `(label, corners-only value, joint value, σ)`, side by side.
    """

    d2: float
    limit: float
    dof: int
    worst: tuple
    s2: float
    table: tuple = ()

    @property
    def moved(self) -> bool:
        """Whether the move is beyond the chi-square quantile at `1 − TAIL`."""
        return not self.d2 <= self.limit

    @property
    def sigma(self) -> float:
        """The move in "σ": `sqrt(d²)` (one parameter: its move in its own σ)."""
        return math.sqrt(max(self.d2, 0.0))

    def message(self) -> str:
        label, a, b, s = self.worst
        return (
            f"the joint solve moved the camera {self.sigma:.3g} σ from what its corners "
            f"alone determine (chi-square {self.d2:.3g} over {self.dof} parameters, limit "
            f"{self.limit:.3g}; most: {label} {a:.6g} -> {b:.6g}, σ {s:.3g})"
        )

    def to_dict(self) -> dict:
        label, a, b, s = self.worst
        return {
            "d2": float(self.d2),
            "limit": float(self.limit),
            "dof": int(self.dof),
            "moved": bool(self.moved),
            "worst": {
                "parameter": label, "corners": float(a), "joint": float(b), "sigma": float(s)
            },
            "parameters": {
                lab: {"corners": float(x), "joint": float(y), "sigma": float(z)}
                for lab, x, y, z in self.table
            },
        }


def chi2_tail(x: float, dof: int) -> float:
    """`P(X > x)` for X chi-square with `dof` degrees of freedom (the regularised upper
    incomplete gamma function)."""
    from jax.scipy.special import gammaincc

    return float(gammaincc(0.5 * dof, 0.5 * max(float(x), 0.0)))


def chi2_quantile(dof: int, tail: float = TAIL) -> float:
    """The `x` with `P(X > x) = tail` for X chi-square with `dof` degrees of freedom
    (bisection on [`chi2_tail`][] to 1e-10 relative)."""
    lo, hi = 0.0, float(dof)
    while chi2_tail(hi, dof) > tail:
        lo, hi = hi, 2.0 * hi + 1.0
    while hi - lo > 1e-10 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2_tail(mid, dof) > tail else (lo, mid)
    return 0.5 * (lo + hi)


def _free_values(fit) -> dict:
    x, _, _ = split(fit.params, fit.free_mask)
    return dict(zip(fit.labels, np.asarray(x, dtype=np.float64)))


def camera_shift(camera_fit, joint_fit, *, tail: float = TAIL) -> CameraShift | None:
    """[`CameraShift`][] of a joint solve against its corners-only solve; None where
    either solve kept no normal matrix (e.g. read back from a file) or they share no free
    camera parameter."""
    if camera_fit.normal_matrix is None or joint_fit.labels is None:
        return None
    labels = list(camera_fit.labels)
    joint = _free_values(joint_fit)
    cam = [i for i, lab in enumerate(labels) if lab.startswith("camera.") and lab in joint]
    if not cam:
        return None
    H = np.asarray(camera_fit.normal_matrix, dtype=np.float64)
    n, p = int(camera_fit.n_observations), H.shape[0]
    s2 = 2.0 * float(camera_fit.cost) / (n - p) if n > p else math.nan
    if not (math.isfinite(s2) and s2 > 0):
        return None
    # the stated σ is a floor, as for every σ of the calibration: corners that fit better
    # than stated (a model error below the noise, noise-free data) do not shrink the
    # camera's covariance below what the statement allows
    s2 = max(s2, 1.0)
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
    cov = s2 * (d[:, None] * np.linalg.pinv(H * np.outer(d, d), rcond=1e-12) * d[None, :])
    ref = _free_values(camera_fit)
    delta = np.array([joint[labels[i]] - ref[labels[i]] for i in cam])
    C = cov[np.ix_(cam, cam)]
    sd = np.sqrt(np.clip(np.diag(C), 0.0, None))
    s = np.where(sd > 0, sd, 1.0)
    Cn = C / np.outer(s, s)  # correlation: the pseudo-inverse in unit-free terms
    z = delta / s
    d2 = float(z @ np.linalg.pinv(Cn, rcond=1e-10, hermitian=True) @ z)
    k = int(np.argmax(np.abs(z)))
    lab = labels[cam[k]]
    worst = (lab, float(ref[lab]), float(joint[lab]), float(sd[k]))
    table = tuple(
        (labels[i], float(ref[labels[i]]), float(joint[labels[i]]), float(sd[j]))
        for j, i in enumerate(cam)
    )
    return CameraShift(d2, chi2_quantile(len(cam), tail), len(cam), worst, s2, table)
