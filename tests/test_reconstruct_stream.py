"""Streaming reconstruction: chunked == one batch bit for bit, streamed files == in-memory
files byte for byte, the incremental STRIPES.json reader == the whole-file reader, and bad
input (cut-short files, failures midway) leaves no output; sharding over 4 host devices
== one device."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import scheimflux as sf
from scheimflux.cli import main
from scheimflux.io._calibration import FORMAT, camera_to_dict, plane_to_dict
from scheimflux.io._pointcloud import open_points_writer, write_points
from scheimflux.io._stripes import iter_stripes, read_stripes, write_stripes
from scheimflux.reconstruct import iter_reconstruct, reconstruct_frames

SENSOR = (1600, 1200)


def _frames(n_frames=11, seed=0):
    """Frames of varying length (0 to 150 points), some pixels off the sensor or NaN."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n_frames):
        n = int(rng.integers(0, 150)) if i != 3 else 0
        f = rng.uniform([-50.0, -50.0], [1650.0, 1250.0], (n, 2))
        if n > 4:
            f[2] = np.nan
        frames.append(f)
    return frames


@pytest.fixture(scope="module")
def system():
    return sf.paper_thick_lens("scheimpflug-1.5"), sf.paper_laser_plane(), sf.paper_stage(0.5)


@pytest.mark.parametrize("measurement", [False, True])
def test_chunked_equals_one_batch_bit_for_bit(system, measurement):
    cam, plane, stage = system
    stage = stage if measurement else None
    frames = _frames()
    pts, st = reconstruct_frames(cam, plane, frames, stage=stage, sensor_size=SENSOR)
    got_p, got_s = [], []
    for p, s in iter_reconstruct(
        cam, plane, iter(frames), stage=stage, sensor_size=SENSOR, chunk_frames=4
    ):
        got_p += p
        got_s += s
    assert len(got_p) == len(frames)
    for a, b, sa, sb, f in zip(got_p, pts, got_s, st, frames):
        assert a.shape == (len(f), 3)
        np.testing.assert_array_equal(a, b)  # NaN at the same places, the rest identical
        np.testing.assert_array_equal(sa, sb)
    codes = np.concatenate(got_s)
    assert {0, 1, 5} <= set(codes.tolist())  # valid, NaN pixel, off the sensor
    # and the batch agrees with the public per-frame function
    for i in (0, 5):
        if measurement:
            one = sf.stripe_to_measurement(cam, plane, stage, frames[i], i, sensor_size=SENSOR)
        else:
            one = sf.stripe_to_camera(cam, plane, frames[i], sensor_size=SENSOR)
        np.testing.assert_array_equal(np.asarray(one.points), pts[i])


def test_iter_stripes_equals_read_stripes(tmp_path):
    frames = [f[~np.isnan(f).any(axis=1)] for f in _frames(6)]
    path = tmp_path / "s.json"
    write_stripes(path, frames, confidence=[np.full(len(f), 0.5) for f in frames])
    whole = read_stripes(path)
    for block in (7, 64, 1 << 20):  # buffer boundaries inside numbers, pairs, frames
        got = list(iter_stripes(path, block_size=block))
        assert len(got) == len(whole)
        for a, b in zip(got, whole):
            np.testing.assert_array_equal(a, b)
    # keys in another order, blanks between tokens
    doc = {"frames": [f.tolist() for f in frames], "format": "scheimflux.stripes/1"}
    (tmp_path / "t.json").write_text(json.dumps(doc, indent=2))
    for a, b in zip(iter_stripes(tmp_path / "t.json", block_size=5), whole):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    "text, message",
    [
        ('{"format": "scheimflux.stripes/1", "frames": [[[1.0, 2.0]], [[3.0, 4', "ends early"),
        ('{"format": "scheimflux.stripes/1", "frames": [[[1.0, 2.0]]', "ends early"),
        ('{"format": "other/1", "frames": []}', "unsupported format"),
        ('{"frames": [[[1.0, 2.0, 3.0]]]}', "frame 0 must be a list of"),
        ('{"frames": [[[1.0, 2.0]]]} x', "extra data"),
        ('{"format": "scheimflux.stripes/1"}', "missing key 'frames'"),
        ("[1, 2]", "expected a JSON object"),
    ],
)
def test_iter_stripes_bad_files(tmp_path, text, message):
    path = tmp_path / "s.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        list(iter_stripes(path, block_size=8))


@pytest.mark.parametrize("ext", [".ply", ".npy", ".json"])
def test_streamed_file_equals_in_memory_file(tmp_path, system, ext):
    cam, plane, _ = system
    frames = _frames()
    pts, _ = reconstruct_frames(cam, plane, frames, sensor_size=SENSOR)
    write_points(tmp_path / f"mem{ext}", pts)
    width = max(len(f) for f in frames)
    with open_points_writer(tmp_path / f"str{ext}", width=width) as w:
        for p, _ in iter_reconstruct(cam, plane, frames, sensor_size=SENSOR, chunk_frames=3):
            w.add(p)
    assert (tmp_path / f"str{ext}").read_bytes() == (tmp_path / f"mem{ext}").read_bytes()
    if ext == ".ply":
        valid = np.concatenate([p[~np.isnan(p).any(axis=1)] for p in pts])
        np.testing.assert_array_equal(sf.io.read_ply(tmp_path / f"str{ext}"), valid)
    if ext == ".npy":
        a = np.load(tmp_path / f"str{ext}")
        assert a.shape == (len(frames), width, 3)
        np.testing.assert_array_equal(a[5, : len(pts[5])], pts[5])


def test_failure_midway_leaves_no_file(tmp_path, system):
    cam, plane, _ = system

    def frames():
        yield from _frames(5)
        raise OSError("camera unplugged")

    out = tmp_path / "p.ply"
    with pytest.raises(OSError, match="unplugged"):
        with open_points_writer(out) as w:
            for p, _ in iter_reconstruct(cam, plane, frames(), chunk_frames=2):
                w.add(p)
    assert os.listdir(tmp_path) == []


def _cal(tmp_path, coverage=None):
    """A calibration file of the paper's x1.5 rig with its sensor size, written by hand
    (with `coverage`, a `Coverage`, when given)."""
    doc = {
        "format": FORMAT,
        "model": "thick-lens",
        "camera": camera_to_dict(sf.paper_thick_lens("scheimpflug-1.5")),
        "laser_plane": plane_to_dict(sf.paper_laser_plane()),
        "sensor": {"width": SENSOR[0], "height": SENSOR[1]},
    }
    if coverage is not None:
        doc["coverage"] = coverage.to_dict()
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    return str(path)


def test_cli_streamed_chunks_equal_one_chunk_and_truncated_input(tmp_path, capsys):
    cal = _cal(tmp_path)
    frames = [f[~np.isnan(f).any(axis=1)] for f in _frames()]
    write_stripes(tmp_path / "s.json", frames)
    for chunk in ("2", "1000"):
        argv = ["reconstruct", cal, str(tmp_path / "s.json"), "--out"]
        assert main([*argv, str(tmp_path / f"p{chunk}.ply"), "--chunk-frames", chunk]) == 0
    assert (tmp_path / "p2.ply").read_bytes() == (tmp_path / "p1000.ply").read_bytes()
    text = capsys.readouterr().out
    assert f"reconstructed {len(frames)} frames" in text and "outside the sensor" in text
    # a file cut short after some frames: exit 1, reported, no output and no temporary
    data = (tmp_path / "s.json").read_text()
    (tmp_path / "cut.json").write_text(data[: int(len(data) * 0.7)])
    before = sorted(os.listdir(tmp_path))
    argv = ["reconstruct", cal, str(tmp_path / "cut.json"), "--out", str(tmp_path / "c.ply")]
    assert main([*argv, "--chunk-frames", "2"]) == 1
    assert "ends early" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == before
    # NaN pixels in a STRIPES file (written by hand; write_stripes drops them) are refused
    # with the frame number, after earlier frames were reconstructed: no output either
    doc = json.loads(data)
    k = next(i for i in range(4, len(frames)) if len(frames[i]))
    doc["frames"][k][0] = [float("nan"), 3.0]
    (tmp_path / "nan.json").write_text(json.dumps(doc))
    before = sorted(os.listdir(tmp_path))
    argv = ["reconstruct", cal, str(tmp_path / "nan.json"), "--out", str(tmp_path / "n.ply")]
    assert main([*argv, "--chunk-frames", "2"]) == 1
    assert f"frame {k} contains non-finite numbers" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == before


def test_sharded_over_four_host_devices_equals_one_device(tmp_path):
    # A fresh interpreter: the device count is fixed when JAX starts.
    script = textwrap.dedent(
        """
        import numpy as np, jax, scheimflux as sf
        from scheimflux.reconstruct import iter_reconstruct
        assert len(jax.local_devices()) == 4, jax.local_devices()
        cam, plane, stage = sf.paper_thick_lens(), sf.paper_laser_plane(), sf.paper_stage(1.0)
        rng = np.random.default_rng(1)
        frames = [rng.uniform(0, 1200, (int(rng.integers(1, 90)), 2)) for _ in range(10)]
        out = {}
        for shard in (True, False):
            chunks = list(iter_reconstruct(cam, plane, frames, stage=stage, chunk_frames=8,
                                           shard=shard))
            out[shard] = [p for c in chunks for p in c[0]]
        sharding = sf.reconstruct._stream.local_devices_sharding(8)
        assert sharding is not None and len(sharding.device_set) == 4
        for a, b in zip(out[True], out[False]):
            np.testing.assert_array_equal(a, b)
        print("OK", len(out[True]))
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    r = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "OK 10" in r.stdout


def test_streamed_parquet_equals_in_memory_points(tmp_path, system):
    pytest.importorskip("pyarrow")
    from scheimflux.io import read_points_parquet

    cam, plane, _ = system
    frames = _frames()
    pts, _ = reconstruct_frames(cam, plane, frames, sensor_size=SENSOR)
    with open_points_writer(tmp_path / "str.parquet") as w:
        for p, _ in iter_reconstruct(cam, plane, frames, sensor_size=SENSOR, chunk_frames=3):
            w.add(p)
    frame, pixel, xyz = read_points_parquet(tmp_path / "str.parquet")
    # every valid point of the in-memory batch, once, at its (frame, pixel), bit for bit
    want = [(i, k) for i, p in enumerate(pts) for k in np.flatnonzero(np.isfinite(p).all(1))]
    assert list(zip(frame.tolist(), pixel.tolist())) == want
    np.testing.assert_array_equal(xyz, np.stack([pts[i][k] for i, k in want]))
    # write_points (one call) gives the same table
    write_points(tmp_path / "mem.parquet", pts)
    for a, b in zip(read_points_parquet(tmp_path / "mem.parquet"), (frame, pixel, xyz)):
        np.testing.assert_array_equal(a, b)
    # a failure midway leaves neither the file nor a temporary
    def failing():
        yield from frames[:5]
        raise OSError("camera unplugged")

    with pytest.raises(OSError, match="unplugged"):
        with open_points_writer(tmp_path / "f.parquet") as w:
            for p, _ in iter_reconstruct(cam, plane, failing(), chunk_frames=2):
                w.add(p)
    assert sorted(os.listdir(tmp_path)) == ["mem.parquet", "str.parquet"]


def test_parquet_without_pyarrow_is_refused_up_front(tmp_path, monkeypatch, capsys):
    # pyarrow made unimportable: a one-line message naming the file and the extra, before
    # any work, and nothing written
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    cal = _cal(tmp_path)
    write_stripes(tmp_path / "s.json", [np.array([[800.0, 600.0]])])
    argv = ["reconstruct", cal, str(tmp_path / "s.json"), "--out", str(tmp_path / "p.parquet")]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "p.parquet" in err and "scheimflux[parquet]" in err
    assert not (tmp_path / "p.parquet").exists()


def test_cli_reconstruct_from_a_folder_of_frames(tmp_path, capsys):
    # images -> stripes -> points in one pass == `extract` then `reconstruct`, byte for
    # byte; an unreadable image and a blank one stay in place as empty frames
    import cv2

    from scheimflux.simulate._render_stripe import render_stripe

    cal = _cal(tmp_path)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(5):
        img, _ = render_stripe((240, 320), lambda u, i=i: 100.0 + 0.1 * u + 9 * i, seed=i)
        cv2.imwrite(str(folder / f"f{i}.png"), img)
    (folder / "f5.png").write_bytes(b"not an image")
    cv2.imwrite(str(folder / "f6.png"), np.zeros((240, 320), np.uint8))
    cv2.imwrite(str(folder / "f10.png"), img)  # natural order: after f6
    assert main(["extract", str(folder), "--out", str(tmp_path / "s.json")]) == 0
    stripes = str(tmp_path / "s.json")
    assert main(["reconstruct", cal, stripes, "--out", str(tmp_path / "a.ply")]) == 0
    capsys.readouterr()
    argv = ["reconstruct", cal, str(folder), "--chunk-frames", "3", "--workers", "2", "--out"]
    assert main([*argv, str(tmp_path / "b.ply")]) == 0
    text = capsys.readouterr()
    assert (tmp_path / "b.ply").read_bytes() == (tmp_path / "a.ply").read_bytes()
    assert "reconstructed 8 frames" in text.out and "1 unusable, 1 without a line" in text.out
    assert "f5.png" in text.err and "f6.png" in text.err
    # .npy rows: the larger image side; frame i is the i-th image
    assert main([*argv, str(tmp_path / "b.npy")]) == 0
    a = np.load(tmp_path / "b.npy")
    assert a.shape == (8, 320, 3)
    assert np.isnan(a[5]).all() and np.isnan(a[6]).all() and np.isfinite(a[7, :300]).all()
    # a folder without images: one line, exit 1, nothing written
    (tmp_path / "none").mkdir()
    argv = ["reconstruct", cal, str(tmp_path / "none"), "--out", str(tmp_path / "c.ply")]
    assert main(argv) == 1
    assert "no image files" in capsys.readouterr().err and not (tmp_path / "c.ply").exists()


def test_cli_refuses_a_gap_in_the_frame_numbers_in_the_measurement_frame(tmp_path, capsys):
    # Frame i is the i-th image and is turned by i x delta omega. A scan folder with
    # f3.png lost (or a stray copy f0_copy.png) put every later frame at the wrong table
    # angle, silently: exit 0 and points 15 deg off. Now: one line naming the problem,
    # exit 1, nothing written; the camera frame (no angles) warns and goes on.
    import cv2

    from scheimflux.io._calibration import stage_to_dict
    from scheimflux.simulate._render_stripe import render_stripe

    _cal(tmp_path)
    cal = json.loads((tmp_path / "cal.json").read_text())
    cal["stage"] = stage_to_dict(sf.paper_stage(0.5))
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    cal = str(tmp_path / "cal.json")
    whole, gap, stray = (tmp_path / n for n in ("whole", "gap", "stray"))
    for folder in (whole, gap, stray):
        folder.mkdir()
        for i in range(6):
            img, _ = render_stripe((240, 320), lambda u, i=i: 100.0 + 0.1 * u + 9 * i, seed=i)
            cv2.imwrite(str(folder / f"f{i}.png"), img)
    (gap / "f3.png").unlink()
    (stray / "f0_copy.png").write_bytes((stray / "f0.png").read_bytes())
    (stray / "notes.txt").write_text("not an image: ignored")
    (whole / "notes.txt").write_text("not an image: ignored")
    argv = ["reconstruct", cal, "--frame", "measurement", "--out"]
    assert main([*argv, str(tmp_path / "w.npy"), str(whole)]) == 0
    assert np.load(tmp_path / "w.npy").shape[0] == 6
    capsys.readouterr()
    for folder, said in ((gap, "missing between f0.png and f5.png: 3"), (stray, "f0_copy.png")):
        before = sorted(os.listdir(tmp_path))
        assert main([*argv, str(tmp_path / "p.npy"), str(folder)]) == 1
        err = capsys.readouterr().err
        assert said in err and "wrong table angle" in err and len(err.strip().splitlines()) == 1
        assert sorted(os.listdir(tmp_path)) == before
    argv = ["reconstruct", cal, str(gap), "--out", str(tmp_path / "c.npy")]
    assert main(argv) == 0
    assert "missing between f0.png and f5.png: 3" in capsys.readouterr().err
    # detect --scan: refused before any board image is read
    argv = ["detect", str(tmp_path / "whole"), "--board", "9x6", "--square-mm", "1",
            "--scan", str(gap), "--delta-omega-deg", "15", "--gauge-radius-mm", "12"]
    assert main([*argv, "--out", str(tmp_path / "obs.json")]) == 1
    err = capsys.readouterr().err
    assert "missing between f0.png and f5.png: 3" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "obs.json").exists()


def test_frame_numbering_problem():
    from scheimflux.stripe._folder import numbering_problem

    assert numbering_problem([f"frame_{i}.tif" for i in range(24)]) is None
    assert numbering_problem([f"frame_{i:03d}.tif" for i in range(1, 25)]) is None
    assert numbering_problem(["a.png", "b.png", "c.png"]) is None
    stamps = [f"img_{t}.png" for t in (224401, 224403, 224406, 224410)]  # time stamps
    assert numbering_problem(stamps) is None
    said = numbering_problem([f"f{i:03d}.png" for i in (1, 2, 5, 6, 7, 8, 9)] + ["f005.tif"])
    assert "missing between f001.png and f009.png: 3, 4" in said
    assert "f005.png and f005.tif" in said


def test_cli_counts_pixels_outside_coverage_in_its_one_pass(tmp_path, capsys):
    # The count of stripe pixels outside the calibration's coverage comes from the
    # reconstruction's own pass, for a stripes file and a folder of frames alike (a folder
    # is no stripes file to read a second time). Truth: the grid covers the columns of
    # the first 20 cells of 8 px, i.e. u < 159.5, a plain threshold on the pixels.
    import cv2

    from scheimflux.geometry._coverage import Coverage
    from scheimflux.simulate._render_stripe import render_stripe

    grid = np.zeros((SENSOR[1] // 8, SENSOR[0] // 8), bool)
    grid[:, :20] = True
    cal = _cal(tmp_path, Coverage(grid, 8, 0.0, SENSOR))
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        img, _ = render_stripe((240, 320), lambda u, i=i: 100.0 + 0.1 * u + 9 * i, seed=i)
        cv2.imwrite(str(folder / f"f{i}.png"), img)
    stripes = tmp_path / "s.json"
    assert main(["extract", str(folder), "--out", str(stripes)]) == 0
    px = np.concatenate(read_stripes(stripes))
    n_out = int(np.sum(px[:, 0] >= 159.5))
    assert 0 < n_out < len(px)
    want = f"{n_out} of {len(px)} stripe pixels on the sensor"
    for i, source in enumerate((stripes, folder)):
        capsys.readouterr()
        assert main(["reconstruct", cal, str(source), "--out", str(tmp_path / f"{i}.ply")]) == 0
        assert want in capsys.readouterr().out


def test_import_stays_light():
    # `import scheimflux` (issue 14: import time) loads neither SciPy nor matplotlib nor
    # the renderer/capture/metrology subpackages; they load on first use, and
    # `sf.calibrate` is still the function
    script = textwrap.dedent(
        """
        import sys
        import scheimflux as sf
        heavy = ["scipy", "matplotlib", "scheimflux.simulate", "scheimflux.capture",
                 "scheimflux.metrology", "scheimflux.export"]
        print(sorted(m for m in heavy if m in sys.modules))
        fit = sf.fit_plane
        print(callable(sf.calibrate), fit.__module__, "scheimflux.metrology" in sys.modules)
        """
    )
    env = {**os.environ, "SCHEIMFLUX_CACHE_DIR": "off"}
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True
    ).stdout.split("\n")
    assert out[0] == "[]"
    calibrate_is_function, module, loaded = out[1].split()
    assert calibrate_is_function == "True" and loaded == "True"
    assert module.startswith("scheimflux.metrology")
