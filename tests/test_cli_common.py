"""The helpers the subcommands share (scheimflux.cli._common)."""

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from scheimflux.cli._common import (
    CLIError,
    list_images,
    natural_key,
    read_grey,
    refuse_to_clobber,
    require_positive,
)
from scheimflux.cli._main import main


def test_refuse_to_clobber_names_the_first_existing_path(tmp_path):
    a, b, c = (str(tmp_path / n) for n in ("a.json", "b.json", "c.json"))
    refuse_to_clobber(a, b, overwrite=False)  # nothing there yet
    for path in (b, c):
        open(path, "w").close()
    with pytest.raises(CLIError, match=r"b\.json exists; pass --overwrite to replace it$"):
        refuse_to_clobber(a, b, c, overwrite=False)
    refuse_to_clobber(a, b, c, overwrite=True)


def test_refuse_to_clobber_counts_a_folder(tmp_path):
    with pytest.raises(CLIError, match="exists"):
        refuse_to_clobber(str(tmp_path), overwrite=False)


def test_require_positive():
    args = SimpleNamespace(a=1.0, b=None, zero=0.0, neg=-2.0, nan=math.nan, inf=math.inf)
    require_positive(args, "a", "b")  # None means "not given" and is skipped
    require_positive(args, "zero", zero_ok=True)
    with pytest.raises(CLIError, match=r"^--zero must be positive, got 0\.0$"):
        require_positive(args, "a", "zero")
    with pytest.raises(CLIError, match=r"^--neg must be >= 0, got -2\.0$"):
        require_positive(args, "neg", zero_ok=True)
    for name in ("nan", "inf"):
        with pytest.raises(CLIError, match=f"--{name} must be positive"):
            require_positive(args, name)


def test_require_positive_names_the_flag():
    with pytest.raises(CLIError, match="^--square-mm must be positive"):
        require_positive(SimpleNamespace(square_mm=-1.0), "square_mm")


def test_natural_key():
    names = ["f10.png", "F2.png", "f1.png", "g.png", "10.png", "f2a.png"]
    assert sorted(names, key=natural_key) == [
        "10.png", "f1.png", "F2.png", "f2a.png", "f10.png", "g.png",
    ]  # fmt: skip


def test_list_images(tmp_path):
    for name in ("frame10.PNG", "frame2.png", "frame1.tif", "notes.txt", "x.jpg"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "sub.png").mkdir()  # a folder, not an image
    got = list_images(str(tmp_path), (".png", ".tif"))
    assert [p.rsplit("/", 1)[-1] for p in got] == ["frame1.tif", "frame2.png", "frame10.PNG"]
    with pytest.raises(CLIError, match="is not a folder"):
        list_images(str(tmp_path / "missing"), (".png",))


def test_read_grey(tmp_path):
    grey = (np.arange(12 * 10) % 251).astype(np.uint8).reshape(12, 10)
    colour = np.dstack([grey] * 3)
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    cv2.imwrite(str(tmp_path / "colour.png"), colour)
    cv2.imwrite(str(tmp_path / "deep.png"), grey.astype(np.uint16) * 257)
    cv2.imwrite(str(tmp_path / "alpha.png"), np.dstack([colour, np.full_like(grey, 255)]))
    np.testing.assert_array_equal(read_grey(str(tmp_path / "grey.png")), grey)
    np.testing.assert_array_equal(read_grey(str(tmp_path / "colour.png")), grey)
    np.testing.assert_array_equal(read_grey(str(tmp_path / "alpha.png")), grey)
    deep = read_grey(str(tmp_path / "deep.png"))
    assert deep.dtype == np.uint16 and deep.shape == (12, 10)
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    assert read_grey(str(tmp_path / "bad.png")) is None
    assert read_grey(str(tmp_path / "missing.png")) is None


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "--corner-noise-px", "-1"], "--corner-noise-px must be >= 0, got -1.0"),
        (["simulate", "--square-mm", "0"], "--square-mm must be positive, got 0.0"),
        (["calibrate", "OBS.json", "--robust", "nan"], "--robust must be >= 0, got nan"),
        (
            ["detect", "IM", "--board", "7x6", "--square-mm", "inf"],
            "--square-mm must be positive, got inf",
        ),
    ],
)
def test_option_errors_are_one_line(tmp_path, capsys, argv, message):
    out = tmp_path / "out.json"
    assert main([*argv, "--out", str(out)]) == 1
    assert capsys.readouterr().err == f"scheimflux {argv[0]}: error: {message}\n"
    assert not out.exists()
