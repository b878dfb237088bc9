"""The calibration's compiled programs: how many there are, and that nothing is traced
again for a second calibration of the same shape (a retrace costs seconds of Python)."""

import collections
import contextlib
import dataclasses

import jax
import numpy as np
import pytest

from scheimflux.calibration import calibrate
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
_SOLVER = ("_lm_solve", "least_squares", "_normal_detect", "_normal_at")


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
def test_calibration_programs_traced_once_and_not_again(scenes, tmp_path, monkeypatch):
    from scheimflux import _export

    a, b = scenes
    # no exported programs from earlier tests: a fresh export folder (JAX's compilation
    # cache folder was set at import and stays), this process's programs forgotten
    monkeypatch.setenv("SCHEIMFLUX_CACHE_DIR", str(tmp_path))
    _export.clear()
    with _traces() as first:
        cal_a = calibrate(a, throw=False)
    assert set(cal_a.fits) == {"camera", "stage", "joint"}
    # the LM loop: ideal camera + camera with distortion share one program (the
    # distortion held at run time), the stage solve one, the joint solve (and the
    # rejection passes) one
    lm = sum(n for name, n in first.items() if name == "_lm_solve")
    assert lm == 3, dict(first)
    with _traces() as second:
        cal_b = calibrate(b, throw=False)
    # same shapes (views, padded points, model): the solver's programs are reused
    solver = {k: n for k, n in second.items() if any(p in k for p in _SOLVER)}
    assert not solver, dict(second)
    assert not np.allclose(cal_a.camera.x0, cal_b.camera.x0)  # a different solve


# ---------------------------------------------------------------- program size (fast)


def _count(jaxpr, name: str) -> int:
    """Equations of primitive `name` in a jaxpr, sub-jaxprs (loops, jits) included."""
    n = 0
    for eqn in jaxpr.eqns:
        n += eqn.primitive.name == name
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                inner = getattr(sub, "jaxpr", None)
                if inner is not None:
                    n += _count(getattr(inner, "jaxpr", inner), name)
    return n


def test_radial_tangential_is_the_rational_form():
    # RadialTangential leaves out the rational denominator and the thin-prism terms at
    # zero (×1 and +0 are exact in IEEE arithmetic): value and derivatives are those of
    # OpenCV's rational form with those coefficients at zero, to the last bit but for
    # XLA's fused multiply-adds, which pair the operations differently (1 ulp)
    import jax.numpy as jnp

    from scheimflux.camera._distortion import RadialTangential, _rational_prism

    rng = np.random.default_rng(3)
    k = rng.normal(0, [0.5, 5.0, 50.0, 1e-3, 1e-3])
    dist = RadialTangential(*k)
    z = jnp.zeros(())

    def rational(d, xy):
        return _rational_prism(xy[0], xy[1], d.k1, d.k2, d.k3, z, z, z, d.p1, d.p2, z, z, z, z)

    xy = jnp.asarray(rng.uniform(-0.03, 0.03, (200, 2)))
    a = jax.jit(jax.vmap(lambda p: dist.distort(p)))(xy)
    b = jax.jit(jax.vmap(lambda p: rational(dist, p)))(xy)
    np.testing.assert_allclose(a, b, rtol=4e-16, atol=1e-19)
    ja = jax.jit(jax.vmap(jax.jacfwd(lambda p: dist.distort(p))))(xy)
    jb = jax.jit(jax.vmap(jax.jacfwd(lambda p: rational(dist, p))))(xy)
    np.testing.assert_allclose(ja, jb, rtol=4e-16, atol=1e-19)


def test_joint_residuals_back_project_once():
    # the stripe and gauge pixels go through ONE back-projection (one undistortion loop
    # in the program), and the residuals are those of the separate blocks
    import jax.numpy as jnp

    from scheimflux.calibration.core._blocks import _laser_points_safe
    from scheimflux.calibration.core._model import (
        CalibrationData,
        SystemParams,
        corner_residuals,
        gauge_residuals,
        joint_residuals,
    )
    from scheimflux.camera import ThickLensScheimpflug
    from scheimflux.camera._distortion import RadialTangential
    from scheimflux.geometry import LaserPlane, RotaryStage
    from scheimflux.geometry._transforms import Pose

    rig = paper_rig(refine=False)
    cam = ThickLensScheimpflug(
        **{**rig.nominal_thick_lens_params(), "distortion": RadialTangential(0.3, -2.0)}
    )
    rng = np.random.default_rng(0)
    V, M, K, F, L = 3, 12, 20, 4, 16
    poses = Pose(jnp.asarray(rng.normal(0, 0.1, (V, 3))), jnp.asarray([[0.0, 0.0, 60.0]] * V))
    stage = RotaryStage(pose=Pose(jnp.array([0.3, -0.2, 0.1]), jnp.array([1.0, -2.0, 50.0])))
    params = SystemParams(cam, poses, LaserPlane(jnp.asarray(rig.laser_plane)), stage,
                          jnp.array([0.01, 0.02]))  # fmt: skip

    def px(*shape):
        return jnp.asarray(rng.uniform([300, 200], [1300, 1000], (*shape, 2)))

    data = CalibrationData(
        board=jnp.asarray(rng.uniform(-2, 2, (M, 3)) * [1, 1, 0]),
        corners=px(V, M),
        corner_w=jnp.ones((V, M)),
        stripe=px(V, K),
        stripe_w=jnp.asarray(rng.integers(0, 2, (V, K)), float),
        gauge=px(F, L),
        gauge_w=jnp.ones((F, L)),
        frame_index=jnp.arange(F, dtype=float),
        gauge_radius=jnp.asarray(17.5),
        sigma_corner_px=jnp.asarray(0.03),
        sigma_stripe_mm=jnp.asarray(1e-3),
        stripe_scale=jnp.asarray([1.0, 2.5, 1.0]),  # view 1: its own (speckled) sigma
        stripe_gain=jnp.asarray([0.2, 0.4, 0.3]),  # the gates' only: not in the residuals
    )
    jaxpr = jax.make_jaxpr(joint_residuals)(params, data).jaxpr
    assert _count(jaxpr, "scan") == 1  # the undistortion's fixed point, once

    def stripe_blockwise(p, d):  # the definition: each view's pixels on their own
        def one_view(pose, uv, w, scale):
            X = _laser_points_safe(p.camera, p.plane, uv)
            n_b = pose.R[:, 2]
            return (X @ n_b - jnp.dot(n_b, pose.translation)) * w / (scale * d.sigma_stripe_mm)

        return jax.vmap(one_view)(p.board_poses, d.stripe, d.stripe_w, d.stripe_scale).ravel()

    r = np.asarray(jax.jit(joint_residuals)(params, data))
    blocks = (corner_residuals, stripe_blockwise, gauge_residuals)
    ref = np.asarray(jax.jit(lambda p, d: jnp.concatenate([f(p, d) for f in blocks]))(params, data))
    assert np.all(np.isfinite(r)) and r.shape == ref.shape
    # the same arithmetic per point; batching may round differently (points agree to
    # ~1e-13 mm, i.e. 1e-10 of σ = 1 µm)
    np.testing.assert_allclose(r, ref, rtol=1e-9, atol=1e-9)

    # with a target on the rotary table its laser-line pixels join the same one
    # back-projection, and its block is the one computed on its own
    import dataclasses

    from scheimflux.calibration.core._table_block import TableTargetData, table_target_residuals

    table = TableTargetData(
        board=data.board, corners=px(F, M), w=jnp.ones((F, M)),
        steps=jnp.arange(F, dtype=float), stripe=px(F, K),
        stripe_w=jnp.asarray(rng.integers(0, 2, (F, K)), float),
    )  # fmt: skip
    params_t = dataclasses.replace(
        params, table_pose=Pose(jnp.array([0.1, 0.0, 0.2]), jnp.array([0.5, 0.0, -3.0]))
    )
    data_t = dataclasses.replace(data, table=table)
    assert _count(jax.make_jaxpr(joint_residuals)(params_t, data_t).jaxpr, "scan") == 1
    r_t = np.asarray(jax.jit(joint_residuals)(params_t, data_t))
    alone = np.asarray(jax.jit(table_target_residuals)(params_t, data_t))
    assert np.all(np.isfinite(r_t)) and len(r_t) == len(r) + len(alone)
    np.testing.assert_allclose(r_t[: len(r)], r, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r_t[len(r) :], alone, rtol=1e-9, atol=1e-9)
