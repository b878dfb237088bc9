"""STRIPES.json reader/writer and the `scheimflux extract` command, end to end."""

import json
import os

import cv2
import numpy as np
import pytest

from scheimflux.cli._main import main
from scheimflux.io._stripes import read_stripes, write_stripes
from scheimflux.simulate._render_stripe import render_stripe


def test_round_trip(tmp_path):
    path = tmp_path / "stripes.json"
    frames = [np.array([[1.5, 2.25], [3.0, np.nan], [4.0, 5.0]]), np.zeros((0, 2))]
    write_stripes(path, frames)
    data = json.loads(path.read_text())
    assert data["format"] == "scheimflux.stripes/1"
    back = read_stripes(path)
    assert len(back) == 2
    np.testing.assert_array_equal(back[0], [[1.5, 2.25], [4.0, 5.0]])  # NaN row omitted
    assert back[1].shape == (0, 2)
    assert os.listdir(tmp_path) == ["stripes.json"]  # no temporary left behind


def test_no_clobber(tmp_path):
    path = tmp_path / "stripes.json"
    write_stripes(path, [np.ones((1, 2))])
    with pytest.raises(FileExistsError, match="overwrite"):
        write_stripes(path, [np.zeros((2, 2))])
    assert read_stripes(path)[0].shape == (1, 2)
    write_stripes(path, [np.zeros((2, 2))], overwrite=True)
    assert read_stripes(path)[0].shape == (2, 2)


def test_write_errors(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        write_stripes(tmp_path / "a.json", [np.zeros((3, 3))])
    with pytest.raises(ValueError, match="infinite"):
        write_stripes(tmp_path / "b.json", [np.array([[1.0, np.inf]])])
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "JSON object"),
        ('{"format": "other/1", "frames": []}', "unsupported format"),
        ('{"points": []}', "missing key 'frames'"),
        ('{"frames": {}}', "must be a list"),
        ('{"frames": [[[1, 2, 3]]]}', "frame 0 must be a list of"),
        ('{"frames": [[], [["a", 2]]]}', "frame 1 must be a list of"),
        ('{"frames": [[[1, NaN]]]}', "non-finite"),
    ],
)
def test_read_errors(tmp_path, content, message):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        read_stripes(path)


def test_read_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_stripes(tmp_path / "nope.json")


def _frames_dir(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    truths = {}
    for i, name in enumerate(["f1.png", "f2.png", "f10.png"]):
        img, truth = render_stripe(
            (120, 200), lambda u, i=i: 50.3 + 5 * i + 0.05 * u, width_px=5, seed=i
        )
        cv2.imwrite(str(folder / name), img)
        truths[name] = truth
    (folder / "f3.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    (folder / "notes.txt").write_text("not a frame")
    return folder, truths


def test_cli_end_to_end(tmp_path, capsys):
    folder, truths = _frames_dir(tmp_path)
    out = tmp_path / "stripes.json"
    rc = main(["extract", str(folder), "--out", str(out), "--width-px", "5"])
    captured = capsys.readouterr()
    assert rc == 0
    assert "f3.png" in captured.err
    assert "skipped 1" in captured.out
    frames = read_stripes(out)
    # Natural order: f1, f2, f3 (unreadable: empty), f10.
    assert [len(f) for f in frames][2] == 0
    assert len(frames) == 4
    for index, name in [(0, "f1.png"), (1, "f2.png"), (3, "f10.png")]:
        truth = truths[name]
        pts = frames[index]
        assert len(pts) == 200
        cols = pts[:, 0].astype(int)
        np.testing.assert_allclose(pts[:, 1], truth.uv[cols, 1], atol=0.1)

    # No clobbering without --overwrite; centroid with --overwrite works.
    rc = main(["extract", str(folder), "--out", str(out)])
    assert rc == 1
    assert "--overwrite" in capsys.readouterr().err
    rc = main(["extract", str(folder), "--out", str(out), "--method", "centroid", "--overwrite"])
    assert rc == 0
    assert len(read_stripes(out)) == 4


def test_cli_errors(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["extract", str(empty), "--out", str(tmp_path / "a.json")]) == 1
    assert "no image files" in capsys.readouterr().err
    (empty / "bad.png").write_bytes(b"garbage")
    assert main(["extract", str(empty), "--out", str(tmp_path / "a.json")]) == 1
    err = capsys.readouterr().err
    assert "bad.png" in err and "could be read" in err
    assert not (tmp_path / "a.json").exists()
    assert main(["extract", str(tmp_path / "missing"), "--out", str(tmp_path / "a.json")]) == 1
    assert "not a folder" in capsys.readouterr().err


def test_confidence_round_trip_and_old_files(tmp_path):
    path = tmp_path / "stripes.json"
    frames = [np.array([[1.0, 2.0], [3.0, np.nan], [4.0, 5.0]]), np.zeros((0, 2))]
    write_stripes(path, frames, confidence=[np.array([0.5, 0.1, 1.0]), np.zeros(0)])
    back, conf = read_stripes(path, confidence=True)
    np.testing.assert_array_equal(conf[0], [0.5, 1.0])  # follows the dropped NaN row
    assert conf[1].shape == (0,)
    np.testing.assert_array_equal(read_stripes(path)[0], back[0])
    # a file without confidences (older, or simulated centres) reads as NaN
    old = tmp_path / "old.json"
    old.write_text('{"format": "scheimflux.stripes/1", "frames": [[[1, 2], [3, 4]]]}')
    pts, conf = read_stripes(old, confidence=True)
    assert pts[0].shape == (2, 2) and np.isnan(conf[0]).all()
    with pytest.raises(ValueError, match="confidences for"):
        write_stripes(tmp_path / "c.json", frames, confidence=[np.ones(2), np.zeros(0)])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        write_stripes(tmp_path / "d.json", frames, confidence=[np.full(3, 2.0), np.zeros(0)])
    bad = tmp_path / "bad.json"
    bad.write_text('{"frames": [[[1, 2]]], "confidence": [[0.5, 0.5]]}')
    with pytest.raises(ValueError, match="1 points but 2 confidences"):
        read_stripes(bad, confidence=True)


def test_cli_colour_laser_off_pairs_and_bad_frames(tmp_path, capsys):
    from scheimflux.simulate import render_capture, score_stripe

    folder = tmp_path / "caps"
    folder.mkdir()
    shape = (240, 320)
    truths = {}
    for i, angle in enumerate((10.0, 80.0)):
        kw = dict(shape=shape, colour=True, line_angle_deg=angle, line_offset_px=7.0, seed=i)
        on, truth = render_capture(**kw)
        off, _ = render_capture(laser_on=False, **kw)
        cv2.imwrite(str(folder / f"pose{i}.png"), on)
        cv2.imwrite(str(folder / f"pose{i}_off.png"), off)
        truths[i] = truth
    cv2.imwrite(str(folder / "pose2.png"), np.zeros((100, 100), np.uint8))  # wrong size
    cv2.imwrite(str(folder / "pose3.jpg"), np.zeros(shape, np.uint8))  # blank
    out = tmp_path / "s.json"
    rc = main(["extract", str(folder), "--out", str(out), "--laser-off", "_off"])
    captured = capsys.readouterr()
    assert rc == 0
    assert "pose2.png" in captured.err and "differs" in captured.err
    assert "pose3.jpg" in captured.err and "no laser line" in captured.err
    frames, conf = read_stripes(out, confidence=True)
    assert len(frames) == 4  # laser-off files are not frames; bad frames keep their place
    assert len(frames[2]) == 0 and len(frames[3]) == 0
    for i in (0, 1):
        orient = "vertical-scan" if i == 0 else "horizontal-scan"
        s = score_stripe(frames[i], orient, truths[i], shape)
        assert s.false_rate == 0.0 and s.coverage > 0.9
        assert np.all((conf[i] > 0) & (conf[i] <= 1))
    # without the pairs the laser-off images are frames too (and hold no line)
    rc = main(["extract", str(folder), "--out", str(out), "--overwrite", "--channel", "red"])
    assert rc == 0 and len(read_stripes(out)) == 6
    assert "pose0_off.png: no laser line" in capsys.readouterr().err
