"""The rotary stage (paper eq. 13)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from ._transforms import Pose, rot_z


class RotaryStage(eqx.Module):
    """A rotary table: camera-to-measurement transform and the step angle.

    Frame i of a scan is mapped as `X_m = R_i (R_m_c X_c + t_m_c)` with `R_i` the
    rotation about `z_m` by `i · delta_omega` (paper eq. 13, `t_i = 0`).

    **Arguments:**
    - `R_m_c`: 3×3 rotation (camera → measurement), or give `pose=` instead.
    - `t_m_c`: translation (mm), shape (3,).
    - `delta_omega`: rotation between consecutive frames (rad).
    """

    T_m_c: Pose
    delta_omega: Float[Array, ""]

    def __init__(self, R_m_c=None, t_m_c=None, delta_omega=0.0, *, pose: Pose | None = None):
        if pose is None:
            if R_m_c is None or t_m_c is None:
                raise ValueError("RotaryStage needs R_m_c and t_m_c, or pose=")
            pose = Pose.from_matrix(R_m_c, t_m_c)
        self.T_m_c = pose
        self.delta_omega = jnp.asarray(delta_omega, dtype=float)

    @property
    def R_m_c(self) -> Float[Array, "3 3"]:
        return self.T_m_c.R

    @property
    def t_m_c(self) -> Float[Array, "3"]:
        return self.T_m_c.translation

    def frame_rotation(
        self, frame_index: Int[ArrayLike, ""] | Float[ArrayLike, ""]
    ) -> Float[Array, "3 3"]:
        """`R_i`, the rotation about `z_m` by `i · delta_omega`."""
        return rot_z(jnp.asarray(frame_index, dtype=self.delta_omega.dtype) * self.delta_omega)

    def to_measurement(self, X_c: Float[ArrayLike, "3"], frame_index) -> Float[Array, "3"]:
        """Map one camera-frame point of frame `frame_index` to the measurement frame."""
        return self.frame_rotation(frame_index) @ self.T_m_c.apply(jnp.asarray(X_c))
