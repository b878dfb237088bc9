"""Input checks that run before tracing, so shape mistakes give a clear message."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def as_points(x, last: int, name: str):
    """Return `x` as a floating array whose last axis has length `last`.

    Raises `ValueError` naming the argument when the shape is wrong, before any tracing.
    Integer input is promoted to the default float type; float32 and float64 are kept;
    float16, bfloat16 and booleans are refused.
    """
    arr = x if hasattr(x, "dtype") and hasattr(x, "shape") else np.asarray(x)
    if arr.ndim == 0 or arr.shape[-1] != last:
        raise ValueError(f"{name} must have shape (..., {last}), got shape {tuple(arr.shape)}")
    if arr.dtype == bool:  # True/False are not coordinates (a mask passed by mistake?)
        raise ValueError(f"{name} must be numbers, got a boolean array (a mask?)")
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        if not jnp.issubdtype(arr.dtype, jnp.integer):
            raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
        arr = jnp.asarray(arr, dtype=float)
    elif jnp.dtype(arr.dtype).itemsize < 4:
        # float16 / bfloat16 hold pixels to 1 px above 1024 and points to ~0.1 mm at
        # 150 mm: refused rather than upcast, as the precision is already lost.
        raise ValueError(
            f"{name} is {jnp.dtype(arr.dtype).name}, too coarse for metrology; "
            "pass float32 or float64"
        )
    return jnp.asarray(arr)


def batched(fn, x, core: int):
    """Apply a one-point function `fn` over all leading axes of `x` with `jax.vmap`.

    `core` is the number of trailing axes `fn` consumes. Outputs keep the leading
    batch shape of `x` (an empty batch shape calls `fn` directly).
    """
    batch = x.shape[: x.ndim - core]
    if not batch:
        return fn(x)
    flat = x.reshape((-1,) + x.shape[x.ndim - core :])
    out = jax.vmap(fn)(flat)
    return jax.tree.map(lambda o: o.reshape(batch + o.shape[1:]), out)


# ----------------------------------------------------------------------------- physics
#
# Bounds of physically possible values, checked where a camera, plane or stage is built
# from concrete numbers (constructors, the calibration-file reader); skipped for JAX
# tracers, so nothing changes under jit, vmap or grad.

MAX_TILT_DEG = 80.0
"""The largest sensor tilt (|phi|, |theta|, OpenCV's |tau_x|, |tau_y|) accepted. Adapters and
tilt-shift mounts tilt the lens by ±10–15°, but the model's tilt is the sensor's against
the image-side axis, which the Scheimpflug condition makes larger in tangent by |β|
(tan θ′ = |β| tan θ): rigs at |β| = 2 with a steep laser plane reach 50–75°, and the
simulator builds them. Beyond 80° the light meets the sensor within 10° of grazing,
where the cover glass reflects most of it and a pixel's footprint is foreshortened more
than sixfold; at 90° the model degenerates (the issue's 89° gave a 17.5 mm gauge at
17.68 mm with no warning)."""

MAX_LENGTH_MM = 1e6
"""The largest length (mm) accepted for a translation, a principal-plane distance or a
sensor distance: 1 km, beyond any laboratory or industrial triangulation rig by three
orders of magnitude (a `t_m_c` of 1e300 mm gives points at 1e300 mm)."""


def concrete(x):
    """`x` as a NumPy array, or None when it is (or holds) a JAX tracer: inside `jit`,
    `vmap` or `grad` a value has no number to check."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x, dtype=float)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None
    except (TypeError, ValueError):
        return None


def check_physical(
    owner: str,
    name: str,
    value,
    *,
    positive: bool = False,
    nonzero: bool = False,
    max_abs: float | None = None,
    unit: str = "",
    why: str = "",
) -> None:
    """Raise `ValueError` naming `owner.name` when the concrete `value` is not finite,
    zero (with `nonzero`), not > 0 (with `positive`), or beyond `max_abs` in magnitude;
    a tracer is skipped."""
    arr = concrete(value)
    if arr is None:
        return
    shown = arr.tolist()
    suffix = f" {unit}" if unit else ""
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}.{name} must be finite, got {shown}{suffix}")
    if nonzero and not np.all(arr != 0):
        raise ValueError(f"{owner}.{name} must not be zero{why}")
    if positive and not np.all(arr > 0):
        raise ValueError(f"{owner}.{name} must be positive, got {shown}{suffix}{why}")
    if max_abs is not None and not np.all(np.abs(arr) <= max_abs):
        raise ValueError(
            f"{owner}.{name} = {shown}{suffix} is beyond any real rig "
            f"(|{name}| <= {max_abs:g}{suffix}){why}"
        )


def check_tilt(owner: str, name: str, value) -> None:
    """A sensor tilt in radians within ±`MAX_TILT_DEG` (see there); tracers skipped."""
    arr = concrete(value)
    if arr is None:
        return
    check_physical(owner, name, arr, unit="rad")
    if not np.all(np.abs(arr) <= np.radians(MAX_TILT_DEG)):
        deg = np.degrees(arr).tolist()
        raise ValueError(
            f"{owner}.{name} = {deg}° is beyond any Scheimpflug camera's sensor tilt "
            f"(|tilt| <= {MAX_TILT_DEG:g}°)"
        )
