"""`scheimflux report`: a self-contained HTML page whose every image decodes."""

import base64
import html
import json
import os
import sys
from html.parser import HTMLParser

import cv2
import numpy as np

from scheimflux.cli._main import main
from scheimflux.io import write_points


def _coverage_doc():
    from scheimflux.geometry._coverage import coverage_of

    g = np.linspace(200.0, 900.0, 6)
    corners = np.stack(np.meshgrid(g, g - 100.0), axis=-1).reshape(-1, 2)
    return coverage_of([corners], [np.zeros((0, 2))], (1600, 1200)).to_dict()


def _calibration_doc():
    cam = {"f": (97.0, "mm"), "e": (-2.4, "mm"), "z0": (249.5, "mm"), "phi": (2.87, "deg"),
           "theta": (13.3, "deg"), "x0": (796.2, "px"), "y0": (594.0, "px"),
           "dx": (0.0044, "mm"), "dy": (0.0044, "mm")}
    labels = ["camera.e", "camera.z0", "camera.x0", "camera.y0"]
    corr = [[1.0, 0.999, 0.1, 0.0], [0.999, 1.0, 0.1, 0.0], [0.1, 0.1, 1.0, 0.2],
            [0.0, 0.0, 0.2, 1.0]]
    return {
        "format": "scheimflux.calibration/1",
        "model": "thick-lens",
        "sensor": {"width": 1600, "height": 1200},
        "camera": {k: {"value": v, "unit": u} for k, (v, u) in cam.items()}
        | {"distortion": {"model": "none"}},
        "laser_plane": {"n_per_mm": [8.6e-4, 3.6e-4, 3.17e-3]},
        "board_poses": {"rotvec": [[0.0, 0.0, 3.1]], "translation_mm": [[0.0, 0.0, 157.0]]},
        "coverage": _coverage_doc(),
        "diagnostics": {
            "std": {"camera.e": 0.01, "camera.z0": 0.02, "camera.x0": 0.5, "camera.y0": 0.4},
            "camera_correlation": {"labels": labels, "matrix": corr},
            "warnings": ["strongly correlated: camera.e and camera.z0 (ρ = +0.9990)"],
            "frozen": ["camera.dx", "camera.dy", "camera.f", "camera.phi", "camera.theta"],
        },
        "software": {"name": "scheimflux", "version": "0.1.0"},
    }


class _Images(HTMLParser):
    def __init__(self):
        super().__init__()
        self.src, self.sections = [], 0

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.src.append(dict(attrs)["src"])
        self.sections += tag == "section"


def test_report_html_parses_and_every_image_decodes(tmp_path, capsys):
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(_calibration_doc()))
    pts = str(tmp_path / "points.json")
    write_points(pts, [np.random.default_rng(0).normal(size=(500, 3))], "camera")
    out, pngs = str(tmp_path / "report.html"), tmp_path / "png"
    pngs.mkdir()
    rc = main(["report", str(cal), "--points", pts, "--out", out, "--png-dir", str(pngs)])
    assert rc == 0, capsys.readouterr().err
    with open(out, encoding="utf-8") as fh:
        text = fh.read()
    parser = _Images()
    parser.feed(text)
    parser.close()
    # correlation, coverage, points (residual and model-error maps need observations)
    assert parser.sections >= 7 and len(parser.src) == 3
    for src in parser.src:
        assert src.startswith("data:image/png;base64,")
        img = cv2.imdecode(np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8),
                           cv2.IMREAD_COLOR)
        assert img is not None and img.shape[0] > 50 and img.shape[1] > 50
    for name in os.listdir(pngs):
        assert cv2.imread(str(pngs / name)) is not None
    assert "camera.e and camera.z0" in text and "97" in text
    assert "Residual maps need the observations" in text
    assert "The model-error map needs the observations" in text
    assert "of the sensor" in text
    # never overwritten without --overwrite
    assert main(["report", str(cal), "--out", out]) == 1
    assert "--overwrite" in capsys.readouterr().err


def test_report_without_matplotlib_is_one_line(tmp_path, capsys, monkeypatch):
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(_calibration_doc()))
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    rc = main(["report", str(cal), "--out", str(tmp_path / "r.html")])
    err = capsys.readouterr().err
    assert rc == 1 and "matplotlib" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r.html").exists()


def test_report_of_a_file_written_by_calibrate_shows_its_sigmas_and_warnings(tmp_path, capsys):
    # `calibrate` keeps sigma, the correlation and the identifiability warnings under
    # diagnostics.uncertainty and the quality warnings under diagnostics.quality; the
    # report read them from diagnostics itself, so on every real file each free
    # parameter showed "fixed / not given", no correlation and "No identifiability
    # warning". Ray-traced observations, the file as the CLI writes it.
    import dataclasses

    from scheimflux.io import write_observations
    from scheimflux.simulate import paper_rig, simulate_observations
    from scheimflux.targets import Checkerboard

    obs, _ = simulate_observations(
        paper_rig(refine=False), Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    views = [dataclasses.replace(v, board_motion_px=float("nan") if i == 1 else 0.01)
             for i, v in enumerate(obs.views)]  # fmt: skip
    write_observations(tmp_path / "obs.json", dataclasses.replace(obs, views=views))
    cal, out = tmp_path / "cal.json", str(tmp_path / "report.html")
    argv = ["calibrate", str(tmp_path / "obs.json"), "--distortion", "none", "--out", str(cal)]
    assert main(argv) == 0, capsys.readouterr().err
    assert main(["report", str(cal), "--out", out]) == 0, capsys.readouterr().err
    doc = json.loads(cal.read_text())["diagnostics"]
    with open(out, encoding="utf-8") as fh:
        text = fh.read()
    std = doc["uncertainty"]["std"]
    for name in ("e", "z0", "x0", "y0"):
        row = text.split(f"<td>{name}</td>", 1)[1].split("</tr>", 1)[0]
        assert "fixed" not in row and f"{std['camera.' + name]:.9g}" in row, row
    assert "f</td><td>97</td><td>fixed / not given" in text  # held, rightly
    assert "correlation matrix" in text and "holds no correlation matrix" not in text
    for w in doc["uncertainty"]["warnings"] + doc["quality"]["warnings"]:
        assert html.escape(w) in text, w
    assert any("could not be measured" in w for w in doc["quality"]["warnings"])
