"""Lens prescriptions: the `Lens` pytree, JSON files, validation and paraxial data.

A prescription is a list of surfaces in lens coordinates (mm, object on the left, light
travelling towards +z, first vertex at z = 0). Each surface has a radius (`null` or
infinite for a plane; positive when the centre of curvature lies to the right), the
thickness to the next vertex (for the last surface: the distance to the nominal image
plane, or 0), the refractive index of the medium *after* the surface (object space is
air, n = 1), optionally a clear semi-diameter, and exactly one surface is the aperture
stop (often a plane surface with index 1.0).

JSON format (`scheimflux/simulate/lenses/*.json`):

```json
{"name": "double-gauss", "wavelength_nm": 656.3,
 "surfaces": [{"radius": 56.2, "thickness": 8.75, "index": 1.6188, "semi_diameter": 29.0},
              {"radius": null, "thickness": 12.4, "index": 1.0, "stop": true}, ...]}
```

A surface may name its glass (`"glass": "N-SK16"`) instead of giving `"index"`: the index
is then computed from the glass's Sellmeier coefficients at `wavelength_nm` (the table in
`_glass.py`). When both are given and the glass is in the table, they must agree to
2e-4 (the rounding of older files). Passing `wavelength_nm=` to the loaders re-evaluates
every glass at another wavelength.

Paraxial data come from a y–nu (ABCD) trace with reduced angles nu; every quantity is
returned as a z position in lens coordinates.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._glass import GLASSES, glass_index
from ._trace import Surfaces

_LENS_DIR = Path(__file__).parent / "lenses"
_SURFACE_KEYS = {"radius", "thickness", "index", "stop", "semi_diameter", "glass", "comment"}
_TOP_KEYS = {"name", "wavelength_nm", "surfaces", "description", "source", "comment"}


class Lens(eqx.Module):
    """A sequential lens prescription (a pytree: radii, thicknesses, indices are leaves).

    **Fields:**

    - `radii`: surface radii (mm), `inf` for planes, shape `(n,)`.
    - `thicknesses`: distance from each vertex to the next (the last: to the nominal image
      plane, or 0), shape `(n,)`.
    - `indices`: refractive index of the medium after each surface (object space: 1.0).
    - `semi_diameters`: clear semi-diameters (mm), `inf` where unknown.
    - `stop`: index of the aperture stop surface (static).
    - `name`, `wavelength_nm`: static metadata.

    Build one with [`load_lens`][], [`read_lens`][] or [`lens_from_dict`][] (which validate
    the prescription); the constructor itself does not validate values.
    """

    radii: Float[Array, " n"]
    thicknesses: Float[Array, " n"]
    indices: Float[Array, " n"]
    semi_diameters: Float[Array, " n"]
    stop: int = eqx.field(static=True)
    name: str = eqx.field(static=True, default="lens")
    wavelength_nm: float = eqx.field(static=True, default=656.3)

    def __check_init__(self):
        n = self.radii.shape[0]
        for field in (self.thicknesses, self.indices, self.semi_diameters):
            if field.shape != (n,):
                raise ValueError("radii, thicknesses, indices and semi_diameters must match")
        if not 0 <= self.stop < n:
            raise ValueError(f"stop index {self.stop} out of range for {n} surfaces")

    @property
    def num_surfaces(self) -> int:
        return self.radii.shape[0]

    @property
    def vertices(self) -> Float[Array, " n"]:
        """z of every vertex (the first at 0)."""
        return jnp.concatenate([jnp.zeros(1), jnp.cumsum(self.thicknesses[:-1])])

    @property
    def curvatures(self) -> Float[Array, " n"]:
        """1 / radius (0 for planes)."""
        return 1.0 / self.radii

    def surfaces(self) -> Surfaces:
        """The surfaces for the ray tracer (object space is air)."""
        n_before = jnp.concatenate([jnp.ones(1), self.indices[:-1]])
        return Surfaces(
            self.vertices,
            self.curvatures,
            n_before,
            self.indices,
            self.semi_diameters,
            self.stop,
        )

    def scaled(self, factor: float, *, name: str | None = None) -> Lens:
        """The same design scaled by `factor` (radii, thicknesses, semi-diameters)."""
        return Lens(
            self.radii * factor,
            self.thicknesses * factor,
            self.indices,
            self.semi_diameters * factor,
            self.stop,
            name if name is not None else f"{self.name}x{factor:g}",
            self.wavelength_nm,
        )

    def with_stop_semi_diameter(self, semi_diameter: float) -> Lens:
        """The same lens with the aperture stop opened or closed to `semi_diameter` mm."""
        sd = self.semi_diameters.at[self.stop].set(semi_diameter)
        return eqx.tree_at(lambda lens: lens.semi_diameters, self, sd)

    @property
    def f_number(self) -> Float[Array, ""]:
        """Working f-number at infinity, N = f / (2 × entrance-pupil semi-diameter)."""
        par = paraxial(self)
        return par.efl / (2.0 * par.entrance_pupil_semi_diameter)

    def with_f_number(self, f_number: float) -> Lens:
        """The same lens with the stop set for f-number `f_number` (N = f / D_entrance)."""
        if not (f_number > 0 and math.isfinite(f_number)):
            raise ValueError(f"f_number must be a positive number, got {f_number}")
        par = paraxial(self)
        sd = float(par.efl) / (2.0 * float(f_number) * abs(float(par.entrance_pupil_magnification)))
        return self.with_stop_semi_diameter(sd)

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready prescription (inverse of [`lens_from_dict`][])."""
        surfaces = []
        for i in range(self.num_surfaces):
            r = float(self.radii[i])
            sd = float(self.semi_diameters[i])
            s: dict[str, Any] = {
                "radius": r if math.isfinite(r) else None,
                "thickness": float(self.thicknesses[i]),
                "index": float(self.indices[i]),
            }
            if i == self.stop:
                s["stop"] = True
            if math.isfinite(sd):
                s["semi_diameter"] = sd
            surfaces.append(s)
        return {"name": self.name, "wavelength_nm": self.wavelength_nm, "surfaces": surfaces}


class Paraxial(eqx.Module):
    """First-order (paraxial) data of a lens; all positions are z in lens coordinates (mm).

    **Fields:**

    - `efl`: effective focal length 1/Φ (image-side focal length f′ = n′/Φ in air).
    - `z_principal_object`, `z_principal_image`: principal points H and H′.
    - `z_focal_object`, `z_focal_image`: focal points F and F′.
    - `z_entrance_pupil`, `entrance_pupil_magnification`: paraxial image of the stop
      through the surfaces before it, and its size relative to the stop.
    - `z_exit_pupil`, `exit_pupil_magnification`: the same through the surfaces after it.
    - `stop_semi_diameter`: `inf` when the prescription gives none.
    - `z_last_vertex`: z of the last vertex.

    The scheimflux camera frame (DESIGN.md) has its origin at H′ and +z towards the object,
    so a lens-coordinate z maps to camera z_c = z_H′ − z; the principal separation of the
    thick-lens model is e = z_H′ − z_H (the camera-frame z of H, see `e`).
    """

    efl: Float[Array, ""]
    z_principal_object: Float[Array, ""]
    z_principal_image: Float[Array, ""]
    z_focal_object: Float[Array, ""]
    z_focal_image: Float[Array, ""]
    z_entrance_pupil: Float[Array, ""]
    entrance_pupil_magnification: Float[Array, ""]
    z_exit_pupil: Float[Array, ""]
    exit_pupil_magnification: Float[Array, ""]
    stop_semi_diameter: Float[Array, ""]
    z_last_vertex: Float[Array, ""]

    @property
    def e(self) -> Float[Array, ""]:
        """Principal separation e = z_H′ − z_H: H lies at camera-frame (0, 0, e)."""
        return self.z_principal_image - self.z_principal_object

    @property
    def entrance_pupil_semi_diameter(self) -> Float[Array, ""]:
        return jnp.abs(self.entrance_pupil_magnification) * self.stop_semi_diameter

    @property
    def exit_pupil_semi_diameter(self) -> Float[Array, ""]:
        return jnp.abs(self.exit_pupil_magnification) * self.stop_semi_diameter

    def object_distance(self, magnification: float | Float[Array, ""]) -> Float[Array, ""]:
        """Lens z of the (real) object plane imaged with lateral magnification −|β|."""
        return self.z_focal_object - self.efl / jnp.abs(magnification)

    def image_distance(self, magnification: float | Float[Array, ""]) -> Float[Array, ""]:
        """Lens z of the image plane for lateral magnification −|β| (Newton)."""
        return self.z_focal_image + self.efl * jnp.abs(magnification)


def _matrices(lens: Lens):
    """Refraction and transfer matrices on (y, n u) for each surface."""
    c = lens.curvatures
    n_before = jnp.concatenate([jnp.ones(1), lens.indices[:-1]])
    power = c * (lens.indices - n_before)
    one, zero = jnp.ones(()), jnp.zeros(())
    refr = [jnp.array([[one, zero], [-power[i], one]]) for i in range(lens.num_surfaces)]
    trans = [
        jnp.array([[one, lens.thicknesses[i] / lens.indices[i]], [zero, one]])
        for i in range(lens.num_surfaces)
    ]
    return refr, trans


def _chain(refr, trans, start: int, stop: int, *, end_with_transfer: bool):
    """Product of the matrices of surfaces start..stop-1 (first applied first)."""
    m = jnp.eye(2)
    for i in range(start, stop):
        m = refr[i] @ m
        if i < stop - 1 or end_with_transfer:
            m = trans[i] @ m
    return m


def paraxial(lens: Lens) -> Paraxial:
    """Paraxial cardinal points and pupils of `lens` by a y–nu (ABCD) trace.

    Differentiable with respect to the prescription. Object space is air; the image-space
    index is that after the last surface.
    """
    refr, trans = _matrices(lens)
    n = lens.num_surfaces
    system = _chain(refr, trans, 0, n, end_with_transfer=False)
    (a, _), (c, d) = system[0], system[1]
    power = -c
    n_img = lens.indices[-1]
    z_last = lens.vertices[-1]
    z_fi = z_last + a * n_img / power
    z_hi = z_last + (a - 1.0) * n_img / power
    z_fo = -d / power
    z_ho = (1.0 - d) / power
    front = _chain(refr, trans, 0, lens.stop, end_with_transfer=True)
    rear = _chain(refr, trans, lens.stop, n, end_with_transfer=False)
    z_ep = front[0, 1] / front[0, 0]
    m_ep = 1.0 / front[0, 0]
    z_xp = z_last - n_img * rear[0, 1] / rear[1, 1]
    m_xp = 1.0 / rear[1, 1]
    return Paraxial(
        efl=1.0 / power,
        z_principal_object=z_ho,
        z_principal_image=z_hi,
        z_focal_object=z_fo,
        z_focal_image=z_fi,
        z_entrance_pupil=z_ep,
        entrance_pupil_magnification=m_ep,
        z_exit_pupil=z_xp,
        exit_pupil_magnification=m_xp,
        stop_semi_diameter=lens.semi_diameters[lens.stop],
        z_last_vertex=z_last,
    )


# ----------------------------------------------------------------------------- loading


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{what} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{what} must be finite, got {value!r}")
    return value


_INDEX_TOL = 2e-4  # explicit index vs Sellmeier: older files give indices to 5 decimals


def _surface_index(s: dict, where: str, wavelength: float, override: bool) -> float:
    """The index after a surface: explicit, or from its glass's Sellmeier formula."""
    glass = s.get("glass")
    if glass is not None and not isinstance(glass, str):
        raise ValueError(f"{where}: 'glass' must be a string, got {glass!r}")
    known = glass in GLASSES
    if "index" not in s:
        if glass is None:
            raise ValueError(f"{where}: missing key 'index' (or a 'glass' to compute it from)")
        return glass_index(glass, wavelength)  # raises, naming the known glasses
    n = _number(s["index"], f"{where}: index")
    if known:
        n_glass = glass_index(glass, wavelength)
        if override:
            return n_glass
        if abs(n - n_glass) > _INDEX_TOL:
            raise ValueError(
                f"{where}: index {n} disagrees with glass {glass} at {wavelength} nm "
                f"({n_glass:.5f}, Sellmeier)"
            )
    elif override and n != 1.0:
        raise ValueError(
            f"{where}: cannot evaluate index {n} at another wavelength: name a known glass "
            f"({', '.join(sorted(GLASSES))})"
        )
    return n


def lens_from_dict(
    data: Any, *, source: str = "lens", wavelength_nm: float | None = None
) -> Lens:
    """Build and validate a [`Lens`][] from a parsed JSON prescription.

    `wavelength_nm` (default: the file's) re-evaluates every surface's glass index at
    another wavelength (every glass surface must then name a glass of the table).

    **Raises:** `ValueError` with a message naming the offending surface for: a missing or
    malformed key, no aperture stop or more than one, a zero radius, a non-positive
    thickness (the last surface may have thickness 0), an index ≤ 0, a non-positive
    semi-diameter, an afocal system, or total internal reflection of the paraxial on-axis
    marginal ray (checked at the aperture set by the known semi-diameters).
    """
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a lens must be a JSON object, got {type(data).__name__}")
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ValueError(
            f"{source}: unknown key(s) {sorted(unknown)}; allowed: {sorted(_TOP_KEYS)}"
        )
    for key in ("name", "wavelength_nm", "surfaces"):
        if key not in data:
            raise ValueError(f"{source}: missing key {key!r}")
    name = data["name"]
    if not isinstance(name, str) or not name:
        raise ValueError(f"{source}: 'name' must be a non-empty string")
    wavelength = _number(data["wavelength_nm"], f"{source}: 'wavelength_nm'")
    if wavelength <= 0:
        raise ValueError(f"{source}: 'wavelength_nm' must be positive, got {wavelength}")
    override = wavelength_nm is not None and float(wavelength_nm) != wavelength
    if wavelength_nm is not None:
        wavelength = _number(wavelength_nm, f"{source}: wavelength_nm")
    surfaces = data["surfaces"]
    if not isinstance(surfaces, list) or len(surfaces) < 1:
        raise ValueError(f"{source}: 'surfaces' must be a non-empty list")
    radii, thick, index, sds, stops = [], [], [], [], []
    last = len(surfaces) - 1
    for i, s in enumerate(surfaces):
        where = f"{source}: surface {i}"
        if not isinstance(s, dict):
            raise ValueError(f"{where}: must be a JSON object")
        unknown = set(s) - _SURFACE_KEYS
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {sorted(unknown)}")
        for key in ("radius", "thickness"):
            if key not in s:
                raise ValueError(f"{where}: missing key {key!r}")
        r = s["radius"]
        r = math.inf if r is None else _number(r, f"{where}: radius")
        if r == 0.0:
            raise ValueError(f"{where}: radius 0 is not allowed (use null for a plane)")
        t = _number(s["thickness"], f"{where}: thickness")
        if t <= 0.0 and i < last:
            raise ValueError(f"{where}: thickness must be positive, got {t}")
        if t < 0.0:
            raise ValueError(f"{where}: the last thickness must be >= 0, got {t}")
        n = _surface_index(s, where, wavelength, override)
        if n <= 0.0:
            raise ValueError(f"{where}: index must be positive, got {n}")
        sd = s.get("semi_diameter")
        sd = math.inf if sd is None else _number(sd, f"{where}: semi_diameter")
        if sd <= 0.0:
            raise ValueError(f"{where}: semi_diameter must be positive, got {sd}")
        stop = s.get("stop", False)
        if not isinstance(stop, bool):
            raise ValueError(f"{where}: 'stop' must be true or false")
        if stop:
            stops.append(i)
        radii.append(r)
        thick.append(t)
        index.append(n)
        sds.append(sd)
    if not stops:
        raise ValueError(f'{source}: no aperture stop; mark one surface with "stop": true')
    if len(stops) > 1:
        raise ValueError(f"{source}: more than one aperture stop (surfaces {stops})")
    arrays = [np.asarray(v, dtype=np.float64) for v in (radii, thick, index, sds)]
    _check_first_order(*arrays, source)
    return Lens(*(jnp.asarray(a) for a in arrays), stops[0], name, wavelength)


def _check_first_order(r, t, n_after, sd, source: str) -> None:
    """Reject afocal systems and paraxial marginal-ray TIR (host-side NumPy)."""
    n_before = np.concatenate([[1.0], n_after[:-1]])
    c = 1.0 / r
    # y-nu trace of the on-axis ray from infinity, entering at unit height.
    ys, us = [], []
    y, nu = 1.0, 0.0
    for i in range(len(r)):
        ys.append(y)
        us.append(nu / n_before[i])
        nu = nu - y * c[i] * (n_after[i] - n_before[i])
        y = y + t[i] * nu / n_after[i]
    if abs(nu) < 1e-12:
        raise ValueError(f"{source}: the lens is afocal (zero power); it has no focal length")
    ys = np.asarray(ys)
    known = np.isfinite(sd) & (np.abs(ys) > 0)
    if not known.any():
        return
    height = float(np.min(sd[known] / np.abs(ys[known])))
    for i in range(len(r)):
        incidence = (us[i] + ys[i] * c[i]) * height  # paraxial angle of incidence
        if abs(n_before[i] * incidence / n_after[i]) > 1.0:
            raise ValueError(
                f"{source}: surface {i}: the on-axis marginal ray (entrance height "
                f"{height:.4g} mm) is totally internally reflected"
            )


def read_lens(path: str | os.PathLike, *, wavelength_nm: float | None = None) -> Lens:
    """Load and validate a lens prescription from a JSON file (see [`lens_from_dict`][])."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"no such lens file: {path}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: malformed JSON: {err}") from None
    return lens_from_dict(data, source=str(path), wavelength_nm=wavelength_nm)


def shipped_lenses() -> list[str]:
    """Names of the prescriptions shipped in `scheimflux/simulate/lenses/`."""
    return sorted(p.stem for p in _LENS_DIR.glob("*.json"))


def load_lens(name: str, *, wavelength_nm: float | None = None) -> Lens:
    """Load a shipped prescription by name (e.g. `"double-gauss"`); see [`shipped_lenses`][].

    `wavelength_nm`: evaluate the glasses at another wavelength (Sellmeier)."""
    names = shipped_lenses()
    if name not in names:
        raise ValueError(f"unknown lens {name!r}; shipped lenses: {', '.join(names)}")
    text = (_LENS_DIR / f"{name}.json").read_text()
    return lens_from_dict(json.loads(text), source=f"{name}.json", wavelength_nm=wavelength_nm)


def resolve_lens(name_or_path: str | os.PathLike) -> Lens:
    """A shipped lens by name, or else a prescription file by path."""
    if isinstance(name_or_path, str) and name_or_path in shipped_lenses():
        return load_lens(name_or_path)
    path = Path(name_or_path)
    if not path.exists():
        raise ValueError(
            f"{str(name_or_path)!r} is neither a lens file nor a shipped lens "
            f"({', '.join(shipped_lenses())})"
        )
    return read_lens(path)
