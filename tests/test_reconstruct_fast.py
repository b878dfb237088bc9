"""The fused reconstruction kernel (`reconstruct/_kernel.py`) against the reference path
(`intersect_ray_plane` on each pixel's ray under vmap)."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.reconstruct._kernel import has_fast_path
from scheimflux.reconstruct._reconstruct import (
    _cast_floats,
    reference_stripe_to_camera,
    reference_stripe_to_measurement,
)

SENSOR = (1600, 1200)


def _pixels(n=400, seed=0):
    """Pixels over and beyond the sensor, with NaN gaps (every status but the plane's)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([-200.0, -150.0], [1800.0, 1350.0], (n, 2))
    uv[::17, 0] = np.nan
    uv[5::23, 1] = np.inf
    return uv


def _cameras():
    thick = sf.paper_thick_lens("scheimpflug-1.5")
    distorted = eqx.tree_at(
        lambda c: c.distortion, thick, sf.camera.RadialTangential(k1=-0.8, p1=1e-3)
    )
    folded = eqx.tree_at(lambda c: c.distortion, thick, sf.camera.RadialTangential(k1=-2000.0))
    pinhole = sf.Pinhole(3000.0, 3010.0, 1.5, 800.0, 600.0)
    return {"thick": thick, "distorted": distorted, "folded": folded, "pinhole": pinhole}


def _reference(cam, plane, uv, sensor_size):
    uv = jnp.asarray(uv)
    cam, plane = _cast_floats((cam, plane), uv.dtype)
    sensor = None if sensor_size is None else jnp.asarray(sensor_size, uv.dtype)
    return reference_stripe_to_camera(cam, plane, uv, sensor)


@pytest.mark.parametrize(
    "name, sensor_size",
    [("thick", None), ("thick", SENSOR), ("distorted", SENSOR), ("folded", None),
     ("pinhole", SENSOR)],
)
def test_fast_equals_reference(name, sensor_size):
    cam = _cameras()[name]
    assert has_fast_path(cam)
    plane = sf.paper_laser_plane()
    uv = _pixels()
    fast = sf.stripe_to_camera(cam, plane, uv, sensor_size=sensor_size)
    ref = _reference(cam, plane, uv, sensor_size)
    np.testing.assert_array_equal(np.asarray(fast.status), np.asarray(ref.status))
    # X = h / (n·h) against origin + t·d with t = 1/(n·d), d = P/|P|: a dozen roundings of
    # unit size on points ~150 mm from the camera, i.e. a few 1e-14 relative; 1e-12 leaves
    # room for the undistortion's own rounding (its residual tolerance is 1e-13).
    np.testing.assert_allclose(fast.points, ref.points, rtol=1e-12, atol=0)
    assert np.isnan(np.asarray(fast.points)[np.asarray(fast.status) != 0]).all()
    if name == "folded":  # the fold gives failed undistortions: the status must say so
        assert int(np.sum(np.asarray(fast.status) == sf.Status.INVALID_PIXEL)) > 30


def test_every_status_equals_reference():
    cam = _cameras()["thick"]
    d = cam.backproject(jnp.array([800.0, 600.0])).direction
    planes = {
        "parallel": sf.LaserPlane.from_normal_distance(jnp.cross(d, jnp.array([0.0, 1, 0])), 50),
        "behind": sf.LaserPlane.from_normal_distance(-d, 100.0),
        "degenerate": sf.LaserPlane.from_normal_distance([-0.15, 0.03, 0.99], 1.5e-4),
        "nan": jax.jit(lambda s: sf.LaserPlane(jnp.array([s, 0.0, 1.0])))(jnp.nan),
    }
    uv = np.array([[800.0, 600.0], [np.nan, 3.0], [-10.0, 600.0], [800.0, 1300.0]])
    seen = set()
    for plane in planes.values():
        fast = sf.stripe_to_camera(cam, plane, uv, sensor_size=SENSOR)
        ref = _reference(cam, plane, uv, SENSOR)
        np.testing.assert_array_equal(np.asarray(fast.status), np.asarray(ref.status))
        seen |= set(np.asarray(fast.status).tolist())
    assert seen == {1, 2, 3, 4, 5}


@pytest.mark.parametrize("name", ["thick", "distorted"])
def test_fast_jit_equals_eager(name):
    cam, plane = _cameras()[name], sf.paper_laser_plane()
    uv = _pixels(60)
    jit = sf.stripe_to_camera(cam, plane, uv, sensor_size=SENSOR)
    with jax.disable_jit():
        eager = sf.stripe_to_camera(cam, plane, uv, sensor_size=SENSOR)
    np.testing.assert_array_equal(np.asarray(jit.status), np.asarray(eager.status))
    # XLA may contract a*b+c into an FMA under jit: one rounding per product, ~1e-15.
    np.testing.assert_allclose(jit.points, eager.points, rtol=1e-13)


def test_float32_within_derived_tolerance():
    cam, plane = _cameras()["thick"], sf.paper_laser_plane()
    uv = _pixels()
    r64 = sf.stripe_to_camera(cam, plane, uv, sensor_size=SENSOR)
    r32 = sf.stripe_to_camera(cam, plane, uv.astype(np.float32), sensor_size=SENSOR)
    assert r32.points.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(r32.status), np.asarray(r64.status))
    # float32: the camera parameters (|K_f| entries up to ~1e5 times pixel values ~1e3)
    # and each of ~12 operations round at 2^-24 ≈ 6e-8; n·h sums terms of one sign (the
    # plane faces the camera), so no cancellation: |ΔX|/|X| ≲ 12 · 6e-8 ≈ 7e-7 per
    # coordinate of the largest magnitude; 3e-6 of the point's norm bounds it.
    p64, p32 = np.asarray(r64.points), np.asarray(r32.points, np.float64)
    ok = np.asarray(r64.status) == 0
    err = np.linalg.norm(p32[ok] - p64[ok], axis=1) / np.linalg.norm(p64[ok], axis=1)
    assert err.max() < 3e-6


def test_fast_gradients_equal_reference():
    cam, plane = _cameras()["distorted"], sf.paper_laser_plane()
    uv = jnp.array([[300.0, 200.0], [1300.0, 1000.0], [np.nan, 5.0]])

    def loss(path):
        def f(c, p):
            rec = path(c, p)
            return jnp.sum(jnp.where(rec.status[:, None] == 0, rec.points, 0.0) ** 2)

        return jax.grad(f, argnums=(0, 1))(cam, plane)

    g_fast = jax.tree.leaves(loss(lambda c, p: sf.stripe_to_camera(c, p, uv)))
    g_ref = jax.tree.leaves(loss(lambda c, p: reference_stripe_to_camera(c, p, uv)))
    for a, b in zip(g_fast, g_ref):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.abs(np.asarray(b)).max())


@pytest.mark.parametrize("name", ["thick", "distorted"])  # two programs / one program
def test_measurement_fast_equals_reference(name):
    cam, plane = _cameras()[name], sf.paper_laser_plane()
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(0.5))
    uv = _pixels(5 * 80).reshape(5, 80, 2)
    fi = np.arange(5)[:, None]
    fast = sf.stripe_to_measurement(cam, plane, stage, uv, fi, sensor_size=SENSOR)
    c, p, s = _cast_floats((cam, plane, stage), jnp.float64)
    ref = reference_stripe_to_measurement(
        c, p, s, jnp.asarray(uv), jnp.broadcast_to(fi, (5, 80)), jnp.asarray(SENSOR, float)
    )
    np.testing.assert_array_equal(np.asarray(fast.status), np.asarray(ref.status))
    np.testing.assert_allclose(fast.points, ref.points, rtol=1e-12)


@pytest.mark.parametrize("name", ["thick", "distorted", "pinhole"])
def test_out_buffers_are_reused(name):
    # `out=`: the result is written into the previous result's buffers (no fresh
    # allocation, docs/throughput.md) and equals a fresh call bit for bit, also where
    # the reused buffer held other points (different pixels first: stale values would
    # show) and NaN/status codes change between the calls.
    cam, plane = _cameras()[name], sf.paper_laser_plane()
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(0.5))
    uv0 = jnp.asarray(_pixels(300, seed=1).reshape(3, 100, 2))
    uv1 = jnp.asarray(_pixels(300, seed=2).reshape(3, 100, 2))
    fi = jnp.arange(3)[:, None]
    calls = {
        "camera": lambda uv, **kw: sf.stripe_to_camera(cam, plane, uv, sensor_size=SENSOR, **kw),
        "measurement": lambda uv, **kw: sf.stripe_to_measurement(
            cam, plane, stage, uv, fi, sensor_size=SENSOR, **kw
        ),
    }
    for call in calls.values():
        fresh = call(uv1)
        old = call(uv0)
        ptr = old.points.unsafe_buffer_pointer(), old.status.unsafe_buffer_pointer()
        new = call(uv1, out=old)
        assert old.points.is_deleted() and old.status.is_deleted()
        assert (new.points.unsafe_buffer_pointer(), new.status.unsafe_buffer_pointer()) == ptr
        np.testing.assert_array_equal(np.asarray(new.status), np.asarray(fresh.status))
        np.testing.assert_array_equal(np.asarray(new.points), np.asarray(fresh.points))
        assert np.any(np.asarray(fresh.status) != np.asarray(call(uv0).status))
        with pytest.raises(ValueError, match="out does not match"):
            call(uv1[:, :50], out=new)
        with pytest.raises(ValueError, match="out does not match"):
            call(uv1.astype(jnp.float32), out=new)
        with pytest.raises(TypeError):  # the type check or `_out_buffers`
            call(uv1, out=(new.points, new.status))



def test_out_buffer_viewed_from_numpy_is_not_overwritten():
    # A previous result still viewed from NumPy (`np.asarray` shares the buffer on CPU)
    # must keep its values: XLA then does not reuse that buffer, and the call still
    # returns the right result.
    cam, plane = _cameras()["thick"], sf.paper_laser_plane()
    uv0, uv1 = jnp.asarray(_pixels(200, seed=3)), jnp.asarray(_pixels(200, seed=4))
    old = sf.stripe_to_camera(cam, plane, uv0)
    view = np.asarray(old.points)
    kept = view.copy()
    new = sf.stripe_to_camera(cam, plane, uv1, out=old)
    np.testing.assert_array_equal(view, kept)
    np.testing.assert_array_equal(
        np.asarray(new.points), np.asarray(sf.stripe_to_camera(cam, plane, uv1).points)
    )


def _batch_loops(compiled_text: str, n: int) -> list[str]:
    """The top-level instructions of the entry computation that loop over the `n` pixels
    (fusions or unfused element-wise ops whose result has a dimension `n`)."""
    entry = compiled_text[compiled_text.index("ENTRY") :]
    lines = [ln for ln in entry.splitlines()[1:] if " = " in ln and "parameter(" not in ln]
    return [ln.split(" = ")[0].strip() for ln in lines if f"[{n}" in ln.split("(")[0]]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_undistorted_kernel_is_one_pass_per_output(dtype):
    # Issue 14: each output of the undistorted kernel (status, points) is written by one
    # loop over the pixels that reads only the pixels (the points loop also the status),
    # with no intermediate per-pixel array (q, 1/q, a stacked copy) in memory: two
    # batch-sized loops per program (main's kernel had three). The size is odd so that
    # no other shape matches.
    from scheimflux.reconstruct import _kernel as k

    n = 1237
    cam, plane = _cameras()["thick"], sf.paper_laser_plane()
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(0.5))
    uv = jnp.zeros((n, 2), dtype)
    sensor = jnp.asarray(SENSOR, dtype)
    programs = {
        "camera": k.fast_stripe_to_camera.lower(cam, plane, uv, sensor),
        "measurement": k.fast_stripe_to_measurement_cs.lower(
            cam, plane, stage, uv, *k.frame_cos_sin(stage, jnp.arange(n), dtype), sensor
        ),
    }
    for name, lowered in programs.items():
        loops = _batch_loops(lowered.compile().as_text(), n)
        # at most one loop per output (a future XLA merging both would be fine), and at
        # least one (the filter finds the loops: not vacuous)
        assert 1 <= len(loops) <= 2, (name, loops)


def test_measurement_gradients_equal_reference():
    # The measurement points fold the stage into the pixel's affine map (one 3x3 matrix
    # per frame): its derivatives with respect to camera, plane and stage must be the
    # reference's (ray, intersection, then eq. 13). A NaN pixel must leave them finite
    # and equal to those with that pixel left out (the reference itself gives NaN there:
    # its eq. 13 multiplies the NaN point by a zero cotangent, so it is compared with the
    # pixel finite and weighted 0).
    cam, plane = _cameras()["thick"], sf.paper_laser_plane()
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(0.5))
    uv = np.array([[[300.0, 200.0], [1300.0, 1000.0]], [[700.0, 500.0], [800.0, 600.0]]])
    fi = jnp.array([[0.0], [7.0]])
    weight = jnp.array([[1.0, 1.0], [0.0, 1.0]])[..., None]
    uv_nan = uv.copy()
    uv_nan[1, 0] = np.nan

    def grads(path, pixels, w):
        def f(c, p, s):
            rec = path(c, p, s, jnp.asarray(pixels))
            return jnp.sum(w * jnp.where(rec.status[..., None] == 0, rec.points, 0.0) ** 2)

        return jax.tree.leaves(jax.grad(f, argnums=(0, 1, 2))(cam, plane, stage))

    def ref(c, p, s, pixels):
        return reference_stripe_to_measurement(c, p, s, pixels, jnp.broadcast_to(fi, (2, 2)))

    def fast(c, p, s, pixels):
        return sf.stripe_to_measurement(c, p, s, pixels, fi)

    g_ref = grads(ref, uv, weight)
    # rtol as the camera-frame gradients (a few dozen roundings); atol a noise floor of
    # 1e-12 of the largest derivative: some leaves' true derivative is ~0 (e.g. δω
    # through frame 0 alone) and both paths give rounding noise there, ~1e-15.
    floor = 1e-12 * max(float(np.abs(np.asarray(b)).max()) for b in g_ref)
    for g_fast in (grads(fast, uv, weight), grads(fast, uv_nan, 1.0)):
        for a, b in zip(g_fast, g_ref):
            assert np.all(np.isfinite(np.asarray(a)))
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=floor)


# The points loop is vectorised by XLA:CPU's LLVM only for batches of a few thousand
# pixels and up (the 400 pixels above run its scalar form): 4096 pixels, the size at
# which both loops were seen vectorised in the compiled code.
_N_VEC = 4096


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_vectorised_batch_equals_reference(dtype):
    cam, plane = _cameras()["thick"], sf.paper_laser_plane()
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(0.5))
    uv64 = _pixels(_N_VEC, seed=1)
    ref = _reference(cam, plane, uv64, SENSOR)
    uv = uv64.astype(dtype)
    fast = sf.stripe_to_camera(cam, plane, uv, sensor_size=SENSOR)
    status, ok = np.asarray(fast.status), np.asarray(ref.status) == 0
    np.testing.assert_array_equal(status, np.asarray(ref.status))
    assert ok.sum() > _N_VEC // 2 and set(status.tolist()) == {0, 1, 5}
    p, p_ref = np.asarray(fast.points, np.float64), np.asarray(ref.points)
    assert np.isnan(p[~ok]).all()
    err = np.linalg.norm(p[ok] - p_ref[ok], axis=1) / np.linalg.norm(p_ref[ok], axis=1)
    # float64: a dozen roundings of 1.1e-16 (test_fast_equals_reference: 1e-12); float32:
    # the 3e-6 of the point's norm derived in test_float32_within_derived_tolerance (the
    # float32 pixels are the float64 ones rounded, 6e-8 relative, inside that bound).
    assert err.max() < (3e-6 if dtype == np.float32 else 1e-12)
    # jit == eager: op-by-op execution has no fused loop (and no vectorised one); the
    # same roundings up to an FMA contraction per product under jit, within one rounding
    # of the float type per operation of the dozen above.
    with jax.disable_jit():
        eager = sf.stripe_to_camera(cam, plane, uv, sensor_size=SENSOR)
    np.testing.assert_array_equal(np.asarray(eager.status), status)
    e = np.asarray(eager.points, np.float64)
    assert np.isnan(e[~ok]).all()
    tol = 12 * np.finfo(dtype).eps
    assert (np.linalg.norm(p[ok] - e[ok], axis=1) / np.linalg.norm(e[ok], axis=1)).max() < tol
    # measurement frame, the same pixels as 4 frames
    fi = np.arange(4)[:, None]
    m = sf.stripe_to_measurement(cam, plane, stage, uv.reshape(4, -1, 2), fi, sensor_size=SENSOR)
    c, pl, s = _cast_floats((cam, plane, stage), jnp.float64)
    m_ref = reference_stripe_to_measurement(
        c, pl, s, jnp.asarray(uv64.reshape(4, -1, 2)), jnp.broadcast_to(fi, (4, _N_VEC // 4)),
        jnp.asarray(SENSOR, float),
    )
    np.testing.assert_array_equal(np.asarray(m.status), np.asarray(m_ref.status))
    pm = np.asarray(m.points, np.float64).reshape(-1, 3)
    pm_ref = np.asarray(m_ref.points).reshape(-1, 3)
    assert np.isnan(pm[~ok]).all()
    err = np.linalg.norm(pm[ok] - pm_ref[ok], axis=1) / np.linalg.norm(pm_ref[ok], axis=1)
    assert err.max() < (3e-6 if dtype == np.float32 else 1e-12)


@pytest.mark.parametrize("leaf", ["f", "x0"])
def test_nan_camera_gives_invalid_camera_and_nan_points(leaf):
    # The points loop's mask is `status + isnan(H[:3, 0]) == 0` per coordinate (so that
    # LLVM vectorises the loop, `_kernel._ok_per_coordinate`): equal to `status == OK`
    # because a NaN in H makes every status INVALID_CAMERA. A NaN focal length puts NaN
    # in every entry of H (the mask's extra term is 1), a NaN x0 in its last column only
    # (the term is 0); both must give the reference's statuses (all invalid) and NaN.
    cam = eqx.tree_at(lambda c: getattr(c, leaf), _cameras()["thick"], jnp.asarray(np.nan))
    plane = sf.paper_laser_plane()
    uv = _pixels(_N_VEC, seed=2)
    fast = sf.stripe_to_camera(cam, plane, uv)
    ref = _reference(cam, plane, uv, None)
    np.testing.assert_array_equal(np.asarray(fast.status), np.asarray(ref.status))
    assert (np.asarray(fast.status) == sf.Status.INVALID_CAMERA).all()
    assert np.isnan(np.asarray(fast.points)).all()
    stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(0.5))
    m = sf.stripe_to_measurement(cam, plane, stage, uv, 3)
    assert (np.asarray(m.status) == sf.Status.INVALID_CAMERA).all()
    assert np.isnan(np.asarray(m.points)).all()


_VECTOR_CHILD = r"""
import math, sys
import jax.numpy as jnp, numpy as np
import scheimflux as sf
from scheimflux.reconstruct import _kernel as k
n = int(sys.argv[1])
cam, plane = sf.paper_thick_lens("scheimpflug-1.5"), sf.paper_laser_plane()
stage = sf.RotaryStage(np.eye(3), [1.0, 2.0, 3.0], math.radians(0.5))
uv = jnp.zeros((n, 2), jnp.float32)
k.fast_stripe_to_camera.lower(cam, plane, uv).compile()
cs = k.frame_cos_sin(stage, jnp.arange(n), uv.dtype)
k.fast_stripe_to_measurement_cs.lower(cam, plane, stage, uv, *cs).compile()
"""


@pytest.mark.slow
def test_both_loops_are_vectorised(tmp_path):
    # Issue 14: the status and points loops of the compiled kernel are SIMD code (LLVM
    # vector types in XLA's optimised IR of each loop), for the camera and the
    # measurement frame. The points loop was scalar before its mask was made
    # per-coordinate (LLVM unswitched its inner loop on the status).
    import glob
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, XLA_FLAGS=f"--xla_dump_to={tmp_path}", SCHEIMFLUX_CACHE_DIR="off")
    subprocess.run(
        [sys.executable, "-c", _VECTOR_CHILD, str(_N_VEC)], env=env, check=True, timeout=600
    )
    seen = {}
    for hlo in glob.glob(str(tmp_path / "*fast_stripe_to_*.cpu_after_optimizations.txt")):
        text = Path(hlo).read_text()
        prefix = hlo[: -len("cpu_after_optimizations.txt")]
        program = "measurement" if "measurement" in hlo else "camera"
        loops = re.findall(rf"^\s*(?:ROOT )?%(\S+) = \w+\[{_N_VEC}(?:,3)?\]\S* fusion\(",
                           text[text.index("ENTRY"):], re.M)
        for name in loops:
            (ir,) = glob.glob(f"{prefix}{name}_kernel_module.ir-with-opt.ll")
            vectors = re.findall(r"<(\d+) x float>", Path(ir).read_text())
            seen[(program, name)] = max((int(v) for v in vectors), default=0)
    assert len(seen) == 4, seen  # status and points loop of each program
    assert all(width >= 4 for width in seen.values()), seen
