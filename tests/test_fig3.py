"""A tiny Fig. 3 reproduction (scripts/fig3.py): one |β|, a few pixels."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "scripts" / "fig3.py"


@pytest.fixture(scope="module")
def fig3():
    spec = importlib.util.spec_from_file_location("fig3", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def result(fig3):
    # 5 × 5 pixels (the principal pixel among them), paraxially placed sensor, no fits
    return fig3.run_beta(1.0, grid=(5, 5), refine=False, fit=False)


@pytest.fixture(scope="module")
def fitted(fig3):
    return fig3.run_beta(1.0, grid=(5, 5), refine=False, fit=True)


def test_numbers_finite_and_truth_converged(result):
    assert result["valid"].all()
    assert result["truth_residual_px_max"] < 1e-9
    for k, s in result["stats"].items():
        assert np.isfinite(s["max_um"]) and np.isfinite(s["rms_um"]), k


def test_thick_lens_beats_pinhole_with_paraxial_data(result):
    """The paper's claim (Fig. 3): with the same paraxial data the pinhole (e = 0) error
    grows with the field, the thick lens stays small. True here by far (e = −33 mm)."""
    s = result["stats"]
    assert s["ideal/thick_lens"]["max_um"] < 0.1 * s["ideal/pinhole"]["max_um"]
    # the pinhole is exact on the axis and off by |e| · field angle away from it
    uv, err = result["uv"], result["errors_um"]["ideal/pinhole"]
    r = np.hypot(uv[:, 0] - 799.5, uv[:, 1] - 599.5)
    assert r.min() == 0.0 and err[np.argmin(r)] < 1.0
    assert err[np.argmax(r)] > 300.0


@pytest.mark.slow
def test_fitted_models_reach_the_homography_floor(fitted):
    """After fitting, both central models are limited by the real lens's departure from a
    homography (distortion), not by the model: they agree within a few percent."""
    s = fitted["stats"]
    floor = s["fitted/homography"]["rms_um"]
    assert floor < 1.0  # sub-micrometre: the real lens is nearly distortion-free here
    for k in ("fitted/thick_lens", "fitted/pinhole"):
        assert s[k]["rms_um"] <= 1.05 * floor + 1e-3, k
    assert s["fitted/thick_lens"]["rms_um"] < s["ideal/thick_lens"]["rms_um"]


def test_outputs(fig3, result, tmp_path):
    import json

    fig3.plot([result], tmp_path / "fig3.png")
    (tmp_path / "fig3.json").write_text(json.dumps(fig3.to_json([result])))
    assert (tmp_path / "fig3.png").stat().st_size > 10_000
    assert "ideal/pinhole" in fig3.table([result])
