"""`scheimflux detect --stage-target DIR --delta-omega-deg D`: the folder layout (one image
per table step, natural name order), dropped steps keeping their numbers, and the
refusals of missing or zero steps. Rendered images with known corners (a board turned in
its plane between images, as on a table seen from above)."""

import cv2
import numpy as np
import pytest
from test_detect import SMALL, _render

import scheimflux as sf
from scheimflux.cli._main import main
from scheimflux.io._observations import read_observations
from scheimflux.simulate._render_board import render_checkerboard


@pytest.fixture(scope="module")
def cam():
    return sf.paper_thick_lens()


@pytest.fixture(scope="module")
def folders(tmp_path_factory, cam):
    root = tmp_path_factory.mktemp("stage_target")
    images, table = root / "images", root / "table"
    images.mkdir()
    table.mkdir()
    for k, rot in ((0, 3.0), (1, 183.0)):
        f, _ = _render(cam, SMALL, rot_deg=rot)
        cv2.imwrite(str(images / f"view_{k}.png"), render_checkerboard(SMALL, f, shape=(600, 800),
                    blur_sigma_px=1.0, seed=k))  # fmt: skip
    truths = {}
    # table steps 0..4 named so that only natural order is right (step_10 after step_2);
    # step 2 shows no target (blank), step 3 is not an image file that decodes
    names = ["step_1.png", "step_2.png", "step_3.png", "step_10.png", "step_11.png"]
    for k, name in enumerate(names):
        if k == 2:
            cv2.imwrite(str(table / name), np.full((600, 800), 128, np.uint8))
            continue
        if k == 3:
            (table / name).write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
            continue
        f, truth = _render(cam, SMALL, rot_deg=3.0 + 5.0 * k)
        truths[k] = truth
        cv2.imwrite(str(table / name), render_checkerboard(SMALL, f, shape=(600, 800),
                    blur_sigma_px=1.0, seed=10 + k))  # fmt: skip
    (table / "notes.txt").write_text("not an image")
    return root, images, table, truths


def _argv(images, out, *extra):
    return [
        "detect", str(images), "--board", "7x6", "--square-mm", "0.2", "--out", str(out),
        "--pixel-pitch-mm", "0.0044", "0.0044", *extra,
    ]  # fmt: skip


def test_cli_stage_target_layout(folders, capsys):
    root, images, table, truths = folders
    out = root / "obs.json"
    argv = _argv(images, out, "--stage-target", str(table), "--delta-omega-deg", "5")
    assert main(argv + ["--overwrite"]) == 0
    cap = capsys.readouterr()
    assert "table step 2 (step_3.png) dropped:" in cap.err
    assert "table step 3 (step_10.png) dropped: step_10.png cannot be read" in cap.err
    assert "table target at 3 of 5 table step(s)" in cap.out
    st = read_observations(out).stage_target
    assert st.delta_omega_deg == 5.0
    np.testing.assert_array_equal(st.table_steps, [0, 1, 4])  # numbers kept past the drops
    assert [d.view for d in st.dropped] == [2, 3]
    assert st.sources == (("step_1.png",), ("step_2.png",), ("step_11.png",))
    np.testing.assert_allclose(st.board_points_mm, SMALL.points_mm)
    assert all(len(s) == 0 for s in st.stripe_px)  # no laser in these renders: no line
    for k, step in enumerate(st.table_steps):
        # the detected corners are the rendered truth (detection accuracy: test_detect)
        err = np.linalg.norm(st.corners_px[k] - truths[int(step)], axis=1)
        assert err.max() < 0.1


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--stage-target", "TABLE"], "--stage-target needs --delta-omega-deg"),
        (["--stage-target", "TABLE", "--delta-omega-deg", "0"], "non-zero angle"),
        (["--delta-omega-deg", "5"], "--delta-omega-deg needs --scan SCAN_DIR or --stage-target"),
        (["--stage-target", "NOWHERE", "--delta-omega-deg", "5"], "is not a folder"),
        (["--stage-target-board", "7x6"], "need --stage-target"),
        (
            ["--target", "circles", "--stage-target-circle-diameter-mm", "0.1"],
            "--stage-target-circle-diameter-mm need --stage-target",
        ),
        (
            ["--stage-target", "TABLE", "--delta-omega-deg", "5",
             "--stage-target-circle-diameter-mm", "0.1"],
            "--stage-target-circle-diameter-mm is for --target circles or acircles",
        ),  # fmt: skip
    ],
)
def test_cli_stage_target_refusals(folders, capsys, extra, message):
    root, images, table, _ = folders
    out = root / "refused.json"
    extra = [str(table) if a == "TABLE" else str(root / a) if a == "NOWHERE" else a
             for a in extra]  # fmt: skip
    assert main(_argv(images, out, *extra)) == 1
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not out.exists()


def test_cli_stage_target_found_once_is_refused(folders, capsys, tmp_path):
    root, images, table, _ = folders
    one = tmp_path / "one"
    one.mkdir()
    (one / "a.png").write_bytes((table / "step_1.png").read_bytes())
    (one / "b.png").write_bytes((table / "step_3.png").read_bytes())  # blank
    out = tmp_path / "obs.json"
    assert main(_argv(images, out, "--stage-target", str(one), "--delta-omega-deg", "5")) == 1
    err = capsys.readouterr().err
    assert "found in 1 of 2 image(s)" in err and "two or more table steps" in err
    assert not out.exists()
