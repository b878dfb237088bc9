"""The calibration's compiled programs: how many there are, and that nothing is traced
again for a second calibration of the same shape (a retrace costs seconds of Python)."""

import collections
import contextlib
import dataclasses

import jax
import numpy as np
import pytest

from scheimflux.calibrate import calibrate
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard

_TRACE = "/jax/core/compile/jaxpr_trace_duration"
_counts: collections.Counter | None = None


def _listen(event, duration, **kw):
    del duration
    if event == _TRACE and _counts is not None:
        _counts[str(kw.get("fun_name", "?"))] += 1


jax.monitoring.register_event_duration_secs_listener(_listen)


@contextlib.contextmanager
def _traces():
    """Count the jit traces (by function name) inside the block."""
    global _counts
    _counts = collections.Counter()
    try:
        yield _counts
    finally:
        _counts = None


# the solver's programs: the LM loops and the programs at a solve's start and end
_SOLVER = ("least_squares", "_normal_detect", "_normal_at")


@pytest.fixture(scope="module")
def scenes():
    rig = paper_rig(refine=False)
    board = Checkerboard(6, 5, 0.4)
    kw = dict(n_views=4, n_frames=6, delta_omega_deg=45.0)
    a, _ = simulate_observations(rig, board, seed=1, **kw)
    # the same scene with fresh corner and stripe noise (0.03 px): same array shapes
    rng = np.random.default_rng(7)
    views = [
        dataclasses.replace(
            v,
            corners_px=v.corners_px + rng.normal(0, 0.03, v.corners_px.shape),
            stripe_px=v.stripe_px + rng.normal(0, 0.03, v.stripe_px.shape),
        )
        for v in a.views
    ]
    return a, dataclasses.replace(a, views=views)


@pytest.mark.slow  # two calibrations of a 4-view scene: compile-bound
def test_calibration_programs_traced_once_and_not_again(scenes):
    a, b = scenes
    with _traces() as first:
        cal_a = calibrate(a, throw=False)
    assert set(cal_a.fits) == {"camera", "stage", "joint"}
    # the LM loop: ideal camera + camera with distortion share one program (the
    # distortion held at run time), the stage solve one, the joint solve (and the
    # rejection passes) one
    lm = sum(n for name, n in first.items() if "least_squares" in name)
    assert lm == 3, dict(first)
    with _traces() as second:
        cal_b = calibrate(b, throw=False)
    # same shapes (views, padded points, model): the solver's programs are reused
    solver = {k: n for k, n in second.items() if any(p in k for p in _SOLVER)}
    assert not solver, dict(second)
    assert not np.allclose(cal_a.camera.x0, cal_b.camera.x0)  # a different solve
