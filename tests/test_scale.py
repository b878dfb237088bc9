"""Scale-out on Dask: a LocalCluster of worker processes reconstructs several scans, each
output equal byte for byte to the single-process one; a bad scan is reported without
stopping the others; a worker killed mid-scan is replaced and its scan still completes,
with no partial output (slow: starts a cluster)."""

import os
import signal
import threading
import time

import numpy as np
import pytest

import scheimflux as sf
from scheimflux.io._stripes import write_stripes
from scheimflux.reconstruct._scan import reconstruct_scan

distributed = pytest.importorskip("distributed")


def _scan(path, n_frames, seed):
    rng = np.random.default_rng(seed)
    u = np.linspace(100.0, 1500.0, 120)
    v = rng.uniform(200.0, 1000.0, n_frames)
    frames = [np.stack([u, np.full_like(u, vi)], 1) for vi in v]
    write_stripes(path, frames)


@pytest.mark.slow
def test_local_cluster_scans_equal_single_process_and_survive_a_killed_worker(tmp_path):
    from test_reconstruct_stream import _cal

    from scheimflux.scale import reconstruct_scans

    cal = _cal(tmp_path)
    scans = tmp_path / "scans"
    scans.mkdir()
    for i, n in enumerate((40, 3000, 60)):
        _scan(scans / f"scan{i}.json", n, i)
    (scans / "cut.json").write_text('{"format": "scheimflux.stripes/1", "frames": [[[1.0, 2')
    ref = tmp_path / "ref"
    ref.mkdir()
    for i in range(3):
        reconstruct_scan(cal, scans / f"scan{i}.json", ref / f"scan{i}.ply", chunk_frames=64)
    out = tmp_path / "out"
    out.mkdir()
    names = [scans / f"scan{i}.json" for i in range(3)] + [scans / "cut.json"]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:  # fmt: skip
        with distributed.Client(cluster) as client:
            killed = []

            def kill_mid_scan():
                # once the long scan's output is being written (its temporary file
                # exists), kill the worker running it
                deadline = time.time() + 300
                while time.time() < deadline and not killed:
                    if any(n.startswith(".tmp-scan1.ply") for n in os.listdir(out)):
                        for w, keys in client.processing().items():
                            if any("scan1" in str(k) for k in keys):
                                pid = client.run(os.getpid, workers=[w])[w]
                                os.kill(pid, signal.SIGKILL)
                                killed.append(w)
                    time.sleep(0.05)

            t = threading.Thread(target=kill_mid_scan)
            t.start()
            results = reconstruct_scans(cal, names, out, client=client, chunk_frames=64)
            t.join()
    assert killed, "the long scan finished before a worker could be killed"
    assert [r.ok for r in results] == [True, True, True, False]
    assert "ends early" in results[3].error
    for i in range(3):
        got = (out / f"scan{i}.ply").read_bytes()
        assert got == (ref / f"scan{i}.ply").read_bytes()
        assert results[i].summary.frames == (40, 3000, 60)[i]
    assert not (out / "cut.ply").exists()
    # the killed attempt may leave its hidden temporary file, never a partial scan1.ply
    assert sorted(n for n in os.listdir(out) if not n.startswith(".tmp-")) == [
        "scan0.ply", "scan1.ply", "scan2.ply"
    ]
    assert sf.io.read_ply(out / "scan1.ply").shape == (3000 * 120, 3)
