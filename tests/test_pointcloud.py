"""Point-cloud files: PLY (binary and ASCII), .npy and .json."""

import json

import numpy as np
import pytest

from scheimflux.io._pointcloud import read_ply, write_ply, write_points


@pytest.fixture
def points():
    rng = np.random.default_rng(0)
    return rng.normal(size=(50, 3)) * [10.0, 20.0, 200.0] + [0.0, 0.0, 150.0]


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip_is_exact(tmp_path, points, binary):
    path = tmp_path / "p.ply"
    write_ply(path, points, binary=binary, comments=("made by a test", "frame: camera"))
    np.testing.assert_array_equal(read_ply(path), points)  # float64, bit for bit
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii")
    fmt = "binary_little_endian" if binary else "ascii"
    assert header == (
        "ply\n"
        f"format {fmt} 1.0\n"
        "comment made by a test\n"
        "comment frame: camera\n"
        "element vertex 50\n"
        "property double x\n"
        "property double y\n"
        "property double z\n"
        "end_header\n"
    )
    if binary:
        assert len(data) - end == 50 * 3 * 8
        np.testing.assert_array_equal(np.frombuffer(data[end:], "<f8").reshape(-1, 3), points)
    else:
        rows = data[end:].decode().splitlines()
        assert len(rows) == 50
        np.testing.assert_array_equal(np.array([r.split() for r in rows], float), points)


def test_ply_leaves_out_nan_rows_and_rejects_inf(tmp_path, points):
    pts = points.copy()
    pts[3] = np.nan
    write_ply(tmp_path / "a.ply", pts)
    np.testing.assert_array_equal(read_ply(tmp_path / "a.ply"), np.delete(points, 3, axis=0))
    pts[4, 1] = np.inf
    with pytest.raises(ValueError, match="infinite"):
        write_ply(tmp_path / "b.ply", pts)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        write_ply(tmp_path / "c.ply", points[:, :2])
    with pytest.raises(ValueError, match="single lines"):
        write_ply(tmp_path / "d.ply", points, comments=("two\nlines",))
    assert not any((tmp_path / n).exists() for n in ("b.ply", "c.ply", "d.ply"))


def test_empty_ply(tmp_path):
    write_ply(tmp_path / "e.ply", np.zeros((0, 3)), binary=False)
    assert read_ply(tmp_path / "e.ply").shape == (0, 3)


def test_ply_no_clobber(tmp_path, points):
    path = tmp_path / "p.ply"
    write_ply(path, points)
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        write_ply(path, points[:3])
    assert path.read_bytes() == before
    write_ply(path, points[:3], overwrite=True)
    np.testing.assert_array_equal(read_ply(path), points[:3])
    assert [p.name for p in tmp_path.iterdir()] == ["p.ply"]  # no temporary file left


def test_read_ply_other_writers(tmp_path):
    # float32 big-endian with an extra property and a face element after the vertices
    pts = np.array([[1.5, 2.0, 3.25], [4.0, -5.0, 6.0]])
    dt = np.dtype([("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("intensity", ">u1")])
    rec = np.zeros(2, dt)
    rec["x"], rec["y"], rec["z"], rec["intensity"] = pts[:, 0], pts[:, 1], pts[:, 2], 7
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n"
        "property float y\nproperty float z\nproperty uchar intensity\n"
        "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    (tmp_path / "o.ply").write_bytes(header.encode() + rec.tobytes())
    np.testing.assert_array_equal(read_ply(tmp_path / "o.ply"), pts)
    (tmp_path / "bad.ply").write_bytes(b"solid stl\n")
    with pytest.raises(ValueError, match="not a PLY file"):
        read_ply(tmp_path / "bad.ply")
    (tmp_path / "short.ply").write_bytes(header.encode() + rec.tobytes()[:5])
    with pytest.raises(ValueError, match="ends before"):
        read_ply(tmp_path / "short.ply")


def _frames():
    a = np.array([[1.0, 2.0, 3.0], [np.nan, np.nan, np.nan], [4.0, 5.0, 6.0]])
    b = np.array([[7.0, 8.0, 9.0]])
    c = np.zeros((0, 3))
    return [a, b, c]


def test_write_points_json(tmp_path):
    write_points(tmp_path / "p.json", _frames(), "measurement")
    doc = json.loads((tmp_path / "p.json").read_text())
    assert doc["format"] == "scheimflux.points/1"
    assert doc["frame"] == "measurement" and doc["unit"] == "mm"
    assert doc["frames"] == [[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], [[7.0, 8.0, 9.0]], []]


def test_write_points_ply(tmp_path):
    write_points(tmp_path / "p.ply", _frames())
    np.testing.assert_array_equal(
        read_ply(tmp_path / "p.ply"), [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]
    )
    assert b"comment scheimflux camera frame, mm" in (tmp_path / "p.ply").read_bytes()


def test_write_points_npy(tmp_path):
    write_points(tmp_path / "p.npy", _frames())
    a = np.load(tmp_path / "p.npy")
    assert a.dtype == np.float64 and a.shape == (3, 3, 3)
    np.testing.assert_array_equal(a[0], _frames()[0])  # invalid rows kept in place
    np.testing.assert_array_equal(a[1, 0], [7.0, 8.0, 9.0])
    assert np.isnan(a[1, 1:]).all() and np.isnan(a[2]).all()  # padding
    # one frame as an (N, 3) array stays (N, 3)
    write_points(tmp_path / "one.npy", _frames()[0])
    np.testing.assert_array_equal(np.load(tmp_path / "one.npy"), _frames()[0])


def test_write_points_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown point-cloud format '.xyz'"):
        write_points(tmp_path / "p.xyz", _frames())
    with pytest.raises(ValueError, match="frame must be one of"):
        write_points(tmp_path / "p.json", _frames(), "world")
    with pytest.raises(ValueError, match=r"frame 1 points must have shape \(N, 3\)"):
        write_points(tmp_path / "p.json", [np.zeros((2, 3)), np.zeros((2, 2))])
    (tmp_path / "old.npy").write_bytes(b"old")
    with pytest.raises(FileExistsError):
        write_points(tmp_path / "old.npy", _frames())
    assert (tmp_path / "old.npy").read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.npy"]
