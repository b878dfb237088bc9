"""Lens prescriptions: shipped files, JSON validation, the `scheimflux lens` command."""

import copy
import json

import numpy as np
import pytest

from scheimflux.cli._main import main
from scheimflux.simulate._lens import (
    lens_from_dict,
    load_lens,
    paraxial,
    read_lens,
    resolve_lens,
    shipped_lenses,
)

_SINGLET = {
    "name": "test-singlet",
    "wavelength_nm": 656.3,
    "surfaces": [
        {"radius": 51.5, "thickness": 10.0, "index": 1.51432, "stop": True, "semi_diameter": 10.0},
        {"radius": -51.5, "thickness": 0.0, "index": 1.0},
    ],
}


def _edit(fn):
    data = copy.deepcopy(_SINGLET)
    fn(data)
    return data


def test_shipped_lenses_load_and_round_trip():
    assert {"singlet", "achromat", "double-gauss"} <= set(shipped_lenses())
    for name in shipped_lenses():
        lens = load_lens(name)
        assert lens.wavelength_nm == 656.3
        again = lens_from_dict(lens.to_dict())
        np.testing.assert_array_equal(again.radii, lens.radii)
        np.testing.assert_array_equal(again.thicknesses, lens.thicknesses)
        assert again.stop == lens.stop


def test_double_gauss_is_a_realistic_objective():
    lens = load_lens("double-gauss")
    par = paraxial(lens)
    n_glass = int(np.sum(np.asarray(lens.indices) > 1.0))
    assert n_glass == 6  # six elements (two cemented doublets)
    assert 50.0 <= float(par.efl) <= 100.0
    f_number = float(par.efl) / (2 * float(par.entrance_pupil_semi_diameter))
    assert 2.5 < f_number < 3.5
    # The nominal image plane (last thickness) is at the back focal point.
    np.testing.assert_allclose(par.z_focal_image, float(np.sum(lens.thicknesses)), atol=1e-3)


def test_read_lens_file_and_resolve(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(_SINGLET))
    lens = read_lens(path)
    assert lens.name == "test-singlet" and lens.stop == 0
    assert resolve_lens(str(path)).name == "test-singlet"
    assert resolve_lens("double-gauss").name == "double-gauss"
    with pytest.raises(ValueError, match="neither a lens file nor a shipped lens"):
        resolve_lens("no-such-lens")
    with pytest.raises(ValueError, match="unknown lens"):
        load_lens("no-such-lens")


def test_scaled_lens():
    lens = load_lens("double-gauss")
    np.testing.assert_allclose(paraxial(lens.scaled(0.5)).efl, 0.5 * paraxial(lens).efl, rtol=1e-14)


def _no_stop(d):
    d["surfaces"][0].pop("stop")


def _two_stops(d):
    d["surfaces"][1]["stop"] = True


def _thin(d):
    d["surfaces"][0]["thickness"] = 0.0


def _negative_last(d):
    d["surfaces"][1]["thickness"] = -1.0


def _bad_index(d):
    d["surfaces"][0]["index"] = 0.0


def _radius_zero(d):
    d["surfaces"][0]["radius"] = 0


def _missing_radius(d):
    d["surfaces"][1].pop("radius")


def _missing_surfaces(d):
    d.pop("surfaces")


def _typo(d):
    d["surfaces"][0]["thicknes"] = 1.0


def _string_index(d):
    d["surfaces"][0]["index"] = "1.5"


def _afocal(d):
    d["surfaces"] = [
        {"radius": None, "thickness": 5.0, "index": 1.5, "stop": True},
        {"radius": None, "thickness": 0.0, "index": 1.0},
    ]


def _tir(d):
    # Plane front, strongly curved back: sin i = 1.5 * 8 / 10 > 1 at the marginal height.
    d["surfaces"] = [
        {"radius": None, "thickness": 5.0, "index": 1.5, "stop": True, "semi_diameter": 8.0},
        {"radius": -10.0, "thickness": 0.0, "index": 1.0},
    ]


@pytest.mark.parametrize(
    "edit, message",
    [
        (_no_stop, "no aperture stop"),
        (_two_stops, "more than one aperture stop"),
        (_thin, "surface 0: thickness must be positive"),
        (_negative_last, "last thickness must be >= 0"),
        (_bad_index, "surface 0: index must be positive"),
        (_radius_zero, "radius 0 is not allowed"),
        (_missing_radius, "surface 1: missing key 'radius'"),
        (_missing_surfaces, "missing key 'surfaces'"),
        (_typo, "unknown key"),
        (_string_index, "index must be a number"),
        (_afocal, "afocal"),
        (_tir, "surface 1: the on-axis marginal ray .* totally internally reflected"),
    ],
)
def test_validation_errors(edit, message):
    with pytest.raises(ValueError, match=message):
        lens_from_dict(_edit(edit))


def test_last_thickness_zero_is_allowed():
    lens = lens_from_dict(_SINGLET)
    assert float(lens.thicknesses[-1]) == 0.0


def test_malformed_json(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{"name": "x", "surfaces": [}')
    with pytest.raises(ValueError, match="malformed JSON"):
        read_lens(path)
    path.write_text("[1, 2]")
    with pytest.raises(ValueError, match="must be a JSON object"):
        read_lens(path)
    with pytest.raises(FileNotFoundError):
        read_lens(tmp_path / "missing.json")


def test_cli_lens_json_matches_paraxial(capsys):
    assert main(["lens", "singlet", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    par = paraxial(load_lens("singlet"))
    np.testing.assert_allclose(rep["efl_mm"], par.efl, rtol=1e-12)
    np.testing.assert_allclose(
        rep["principal_points_mm"], [par.z_principal_object, par.z_principal_image], rtol=1e-12
    )
    np.testing.assert_allclose(rep["principal_separation_mm"], par.e, rtol=1e-12)
    np.testing.assert_allclose(
        rep["focal_points_mm"], [par.z_focal_object, par.z_focal_image], rtol=1e-12
    )
    assert rep["principal_separation_mm"] == pytest.approx(
        rep["principal_points_mm"][1] - rep["principal_points_mm"][0]
    )
    ep = rep["entrance_pupil_mm"]
    np.testing.assert_allclose(ep["position"], par.z_entrance_pupil, atol=1e-12)
    np.testing.assert_allclose(ep["diameter"], 20.0, rtol=1e-12)  # stop on the front surface
    assert rep["exit_pupil_mm"]["diameter"] > 0


def test_cli_lens_text_table(capsys, tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(_SINGLET))
    assert main(["lens", str(path)]) == 0
    out = capsys.readouterr().out
    par = paraxial(lens_from_dict(_SINGLET))
    assert "test-singlet" in out
    assert f"{float(par.efl):.4f} mm" in out
    assert f"z = {float(par.z_principal_image):.4f} mm" in out
    assert f"{float(par.e):.4f} mm" in out


def test_cli_lens_errors(capsys, tmp_path):
    assert main(["lens", "no-such-lens"]) == 1
    assert "neither a lens file nor a shipped lens" in capsys.readouterr().err
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(_edit(_two_stops)))
    assert main(["lens", str(path)]) == 1
    assert "more than one aperture stop" in capsys.readouterr().err
    assert main(["lens", "--list"]) == 0
    assert "double-gauss" in capsys.readouterr().out
