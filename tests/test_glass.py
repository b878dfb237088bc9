"""Glass indices from Sellmeier coefficients, glass-named prescriptions, the Tessar lens."""

import copy
import json

import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.simulate._glass import D_LINE_NM, GLASSES, glass_index
from scheimflux.simulate._lens import _LENS_DIR, lens_from_dict, load_lens, paraxial
from scheimflux.simulate._trace import trace

# Fraunhofer F and C lines (nm), for the Abbe number νd = (nd − 1) / (nF − nC).
_F_LINE, _C_LINE = 486.1327, 656.2725


@pytest.mark.parametrize("name", sorted(GLASSES))
def test_sellmeier_reproduces_catalogue_nd_and_abbe_number(name):
    glass = GLASSES[name]
    nd = glass_index(name, D_LINE_NM)
    # The catalogue tabulates nd to 5 decimals: the formula must round to it.
    assert abs(nd - glass.nd) <= 0.6e-5
    vd = (nd - 1.0) / (glass_index(name, _F_LINE) - glass_index(name, _C_LINE))
    assert abs(vd - glass.vd) <= 0.006  # νd is tabulated to 2 decimals
    # Normal dispersion: the index falls with wavelength across the visible.
    lam = np.linspace(400.0, 1000.0, 13)
    assert np.all(np.diff([glass.index(x) for x in lam]) < 0)


def test_shipped_indices_agree_with_their_glasses():
    """Every shipped surface naming a glass of the table has that glass's n(λ)."""
    checked = 0
    for path in sorted(_LENS_DIR.glob("*.json")):
        doc = json.loads(path.read_text())
        lens = load_lens(path.stem)
        for i, s in enumerate(doc["surfaces"]):
            if s.get("glass") in GLASSES:
                n = glass_index(s["glass"], doc["wavelength_nm"])
                # Older files round indices to 5 decimals (and SF5 ~3e-5 from Sellmeier).
                assert abs(float(lens.indices[i]) - n) < 5e-5, (path.stem, i)
                checked += 1
    assert checked >= 6


def _doc():
    return json.loads((_LENS_DIR / "tessar.json").read_text())


def test_glass_errors_and_wavelength_override():
    doc = _doc()
    bad = copy.deepcopy(doc)
    bad["surfaces"][0]["glass"] = "UNOBTAINIUM"
    with pytest.raises(ValueError, match="unknown glass 'UNOBTAINIUM'"):
        lens_from_dict(bad, source="t.json")
    bad = copy.deepcopy(doc)
    bad["surfaces"][0]["index"] = 1.7  # contradicts N-SK2 at 656.3 nm
    with pytest.raises(ValueError, match="surface 0: index 1.7 disagrees with glass N-SK2"):
        lens_from_dict(bad, source="t.json")
    bad = copy.deepcopy(doc)
    del bad["surfaces"][1]["index"]  # air surface without index or glass
    with pytest.raises(ValueError, match="surface 1: missing key 'index'"):
        lens_from_dict(bad, source="t.json")
    with pytest.raises(ValueError, match="outside the Sellmeier range"):
        load_lens("tessar", wavelength_nm=200.0)
    # Another wavelength: every glass re-evaluated, air untouched.
    blue = load_lens("tessar", wavelength_nm=450.0)
    assert blue.wavelength_nm == 450.0
    for i, s in enumerate(doc["surfaces"]):
        want = glass_index(s["glass"], 450.0) if "glass" in s else 1.0
        assert float(blue.indices[i]) == pytest.approx(want, abs=1e-12)
    # Double Gauss glasses (SK2, SK16, F5 labels) are not all in the table: refuse.
    with pytest.raises(ValueError, match="cannot evaluate index"):
        load_lens("double-gauss", wavelength_nm=450.0)


def _ynu_efl(radii, thick, n_after) -> tuple[float, float]:
    """Independent paraxial trace (y, u form, not the matrices of `paraxial`): EFL, BFD."""
    y, u, n = 1.0, 0.0, 1.0
    for i, (r, t, n2) in enumerate(zip(radii, thick, n_after)):
        c = 0.0 if not np.isfinite(r) else 1.0 / r
        u = (n * u - y * c * (n2 - n)) / n2  # refraction: n'u' = nu - y c (n' - n)
        n = n2
        if i < len(radii) - 1:
            y = y + t * u
    return -1.0 / u, -y / u


def test_tessar_focal_length_f_number_and_focus():
    lens = load_lens("tessar")
    par = paraxial(lens)
    efl, bfd = _ynu_efl(*(np.asarray(a) for a in (lens.radii, lens.thicknesses, lens.indices)))
    np.testing.assert_allclose(float(par.efl), efl, rtol=1e-12)
    assert efl == pytest.approx(8.0, abs=1e-3)  # scaled to f = 8 mm
    assert float(lens.f_number) == pytest.approx(4.5, abs=2e-3)  # f/4.5 (stop to 0.1 µm)
    # Last thickness = back focal distance (nominal image plane at F').
    assert float(lens.thicknesses[-1]) == pytest.approx(float(bfd), abs=1e-5)
    # A real ray parallel to the axis at 1 % of the pupil crosses the axis at F′ up to
    # spherical aberration ∝ h² (≈ 1e-4 of the focal length at this height).
    h = 0.01 * float(par.entrance_pupil_semi_diameter)
    tr = trace(lens.surfaces(), jnp.asarray([0.0, h, -1.0]), jnp.asarray([0.0, 0.0, 1.0]))
    p, d = np.asarray(tr.point), np.asarray(tr.direction)
    z_cross = p[2] - p[1] * d[2] / d[1]
    assert bool(tr.ok)
    assert z_cross == pytest.approx(float(par.z_focal_image), abs=1e-5)
    # Four elements, three groups (one cemented interface).
    assert int(np.sum(np.asarray(lens.indices) > 1.0)) == 4
    assert lens.num_surfaces == 8 and lens.stop == 4


def test_with_f_number_round_trip():
    lens = load_lens("double-gauss")
    for n in (2.8, 8.0, 16.0):
        assert float(lens.with_f_number(n).f_number) == pytest.approx(n, rel=1e-12)
    with pytest.raises(ValueError, match="f_number must be a positive number"):
        lens.with_f_number(0.0)
