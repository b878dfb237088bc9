"""Optical glasses: refractive index n(λ) from Sellmeier coefficients.

The Schott catalogue gives each glass as a three-term Sellmeier formula,

    n²(λ) − 1 = Σᵢ Bᵢ λ² / (λ² − Cᵢ),    λ in µm, Cᵢ in µm²,

valid from the near UV to ~2.5 µm. The table below holds the glasses of the shipped
prescriptions (`lenses/*.json`), with the catalogue's tabulated nd (587.56 nm, the
helium d line) and Abbe number νd so that the coefficients can be checked.

Source: SCHOTT optical glass data sheets / `SCHOTT.AGF` Zemax catalogue (Sellmeier 1
formula), as also reproduced by refractiveindex.info (shelf "glass", books SCHOTT-*).
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["GLASSES", "Glass", "glass_index", "known_glasses"]

#: Wavelength of the helium d line, nm (where nd is tabulated).
D_LINE_NM = 587.5618


@dataclasses.dataclass(frozen=True)
class Glass:
    """A catalogue glass.

    **Fields:** `name`; `b`, `c`: the Sellmeier coefficients B₁..₃ and C₁..₃ (µm²);
    `nd`, `vd`: the catalogue's tabulated index at 587.56 nm and Abbe number (for checks);
    `catalogue`: where the coefficients come from.
    """

    name: str
    b: tuple[float, float, float]
    c: tuple[float, float, float]
    nd: float
    vd: float
    catalogue: str = "SCHOTT"

    def index(self, wavelength_nm: float) -> float:
        """n(λ) by the Sellmeier formula (λ in nm); raises outside 300 nm … 2.5 µm."""
        lam = float(wavelength_nm)
        if not (300.0 <= lam <= 2500.0):
            raise ValueError(
                f"glass {self.name}: wavelength {wavelength_nm} nm is outside the Sellmeier "
                "range 300 … 2500 nm"
            )
        l2 = (lam * 1e-3) ** 2
        n2 = 1.0 + sum(b * l2 / (l2 - c) for b, c in zip(self.b, self.c))
        return math.sqrt(n2)


def _g(name, b, c, nd, vd) -> tuple[str, Glass]:
    return name, Glass(name, tuple(b), tuple(c), nd, vd)


#: The glass table, by catalogue name.
GLASSES: dict[str, Glass] = dict(
    [
        _g("N-BK7", (1.03961212, 0.231792344, 1.01046945),
           (0.00600069867, 0.0200179144, 103.560653), 1.51680, 64.17),
        _g("N-KF9", (1.19286778, 0.0893346571, 0.920819805),
           (0.00839154696, 0.0404010786, 112.572446), 1.52346, 51.54),
        _g("LF5", (1.28035628, 0.163505973, 0.893930112),
           (0.00929854416, 0.0449135769, 110.493685), 1.58144, 40.85),
        _g("F5", (1.31044630, 0.196034260, 0.966129770),
           (0.00958633048, 0.0457627627, 115.011883), 1.60342, 38.03),
        _g("N-SK2", (1.28189012, 0.257738258, 0.968186040),
           (0.00727191640, 0.0242823527, 110.377773), 1.60738, 56.65),
        _g("F2", (1.34533359, 0.209073176, 0.937357162),
           (0.00997743871, 0.0470450767, 111.886764), 1.62004, 36.37),
        _g("N-SK16", (1.34317774, 0.241144399, 0.994317969),
           (0.00704687339, 0.0229005000, 92.7508526), 1.62041, 60.32),
        _g("SF5", (1.46141885, 0.247713019, 0.949995832),
           (0.0111826126, 0.0508594669, 112.041888), 1.67270, 32.21),
    ]
)  # fmt: skip


def known_glasses() -> list[str]:
    """Names of the glasses in the table."""
    return sorted(GLASSES)


def glass_index(name: str, wavelength_nm: float) -> float:
    """Refractive index of catalogue glass `name` at `wavelength_nm` (Sellmeier).

    **Raises:** `ValueError` naming the known glasses for an unknown name, or for a
    wavelength outside the formula's range.
    """
    glass = GLASSES.get(name)
    if glass is None:
        raise ValueError(f"unknown glass {name!r}; known glasses: {', '.join(known_glasses())}")
    return glass.index(wavelength_nm)
