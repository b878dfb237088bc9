"""Many calibrations in one process (a notebook, a server) must not exhaust it.

Every compiled XLA program keeps thousands of memory mappings for as long as it is
cached, and the caches are never released: when each data set compiled its own solver
(its exact number of stripe points was an array shape), a process doing calibrations
grew by ~3,500 mappings per calibration until `vm.max_map_count` (65,530) was reached
and LLVM failed (a segfault). Padded shapes recur, so the compiled solvers are reused.
"""

import dataclasses

import numpy as np
import pytest

from scheimflux.calibration import calibrate, calibrate_camera
from scheimflux.io import View
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard


def _maps() -> int:
    with open("/proc/self/maps") as f:
        return sum(1 for _ in f)


@pytest.fixture(scope="module")
def base():
    rig = paper_rig(refine=False)
    obs, _ = simulate_observations(
        rig, Checkerboard(6, 5, 0.4), n_views=4, stage_scan=False, seed=0
    )
    return obs


def _variant(obs, k: int):
    """The same scene with k stripe pixels fewer per view and fresh corner noise: a new
    data set of a new size, as repeated captures give."""
    rng = np.random.default_rng(k)
    views = [
        View(
            np.asarray(v.corners_px) + 0.03 * rng.standard_normal(np.shape(v.corners_px)),
            np.asarray(v.stripe_px)[: len(v.stripe_px) - k],
        )
        for v in obs.views
    ]
    return dataclasses.replace(obs, views=views)


def _grow(obs, n: int, fn) -> list[int]:
    fn(_variant(obs, 0))  # compile
    counts = [_maps()]
    for k in range(1, n):
        fn(_variant(obs, k))
        counts.append(_maps())
    return counts


def test_camera_calibrations_do_not_grow_the_process(base):
    counts = _grow(base, 6, lambda o: calibrate_camera(o, distortion="none"))
    # one compiled variant per padded size at most (sizes change every 32 points here):
    # a few hundred mappings of slack, far below one compilation's ~3,500
    assert counts[-1] - counts[0] < 1000, counts


@pytest.mark.slow
def test_fifty_calibrations_in_one_process(base):
    counts = _grow(base, 50, lambda o: calibrate(o, distortion="none"))
    assert counts[-1] - counts[0] < 4000, counts
