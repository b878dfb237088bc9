"""The programs a calibration runs once: compiled with less optimisation, same numbers.

`ONE_SHOT` compiles a solve's start/end program, the residual summaries and the axis
warning with LLVM at -O0 (compile time is most of a cold calibration, their run is
milliseconds). Optimisation level must not change what they compute beyond rounding,
and the axis warning's forward-mode chain rule must be the derivative of its lengths.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.calibration.core._model import SystemParams, corner_errors_px, make_data
from scheimflux.calibration.core._solve import ONE_SHOT, free_spec, split
from scheimflux.calibration.trust._stage_warning import _gradients, reference_pixels
from scheimflux.camera import ThickLensScheimpflug
from scheimflux.geometry import LaserPlane, RotaryStage
from scheimflux.geometry._transforms import Pose
from scheimflux.simulate import paper_rig, simulate_observations
from scheimflux.targets import Checkerboard


@pytest.fixture(scope="module")
def rig():
    return paper_rig(refine=False)


def _system(rig, n_views=1):
    cam = ThickLensScheimpflug(**rig.nominal_thick_lens_params())
    plane = LaserPlane(jnp.asarray(rig.laser_plane))
    # a generic table pose (not the rig's): every parameter moves the lengths
    stage = RotaryStage(
        pose=Pose(jnp.array([0.3, -0.2, 0.1]), jnp.array([1.0, -2.0, 50.0])),
        delta_omega=math.radians(30.0),
    )
    poses = Pose(jnp.zeros((n_views, 3)), jnp.zeros((n_views, 3)))
    return SystemParams(cam, poses, plane, stage, jnp.zeros(2))


def test_axis_gradients_match_central_differences(rig):
    params = _system(rig)
    spec = free_spec(params, ("board_poses", "eccentricity", "stage.delta_omega"))
    uv = jnp.asarray(reference_pixels(*rig.sensor_size))
    L, gL, _, _, _ = (np.asarray(a) for a in _gradients(params, spec, uv, 6.0))
    assert np.all(np.isfinite(gL)) and gL.shape == (25, gL.shape[1]) and gL.shape[1] > 10
    x0, unravel, static = split(params, spec)
    x0 = np.asarray(x0)
    fd = np.empty_like(gL)
    for k in range(x0.size):
        # h ≈ ε^(1/3)·scale: central-difference truncation (h² L'''/6) and rounding
        # (ε L / h) both ~1e-11·L per unit of x_k (L ~ 100 mm here)
        h = 6e-6 * max(abs(x0[k]), 1e-2)
        Lk = []
        for s in (h, -h):
            x = x0.copy()
            x[k] += s
            p = eqx.combine(unravel(jnp.asarray(x)), static)
            Lk.append(np.asarray(_gradients(p, spec, uv, 6.0)[0]))
        fd[:, k] = (Lk[0] - Lk[1]) / (2 * h)
    # per column: the bound above (×100 margin) in units of that column's largest entry
    scale = np.maximum(np.abs(gL).max(axis=0), 1e-300)
    err = np.abs(fd - gL) / scale
    assert np.all(np.isfinite(L)) and L.max() > 1.0
    assert err.max() < 1e-5, f"worst column {int(err.max(axis=0).argmax())}: {err.max():.2e}"


@pytest.mark.slow  # simulates a scene and compiles the summary program twice (~107 s under load 15)
def test_one_shot_program_equals_default_optimisation(rig):
    obs, _ = simulate_observations(rig, Checkerboard(6, 5, 0.4), n_views=3, seed=2)
    data = make_data(obs, sigma_corner_px=0.03)
    params = _system(rig, n_views=3)
    params = eqx.tree_at(
        lambda p: p.board_poses,
        params,
        Pose(
            jnp.tile(jnp.array([0.1, -0.05, 0.02]), (3, 1)),
            jnp.tile(jnp.array([0.0, 0.0, 80.0]), (3, 1)),
        ),
    )
    a = np.asarray(eqx.filter_jit(corner_errors_px, compiler_options=ONE_SHOT)(params, data))
    b = np.asarray(eqx.filter_jit(corner_errors_px)(params, data))
    assert np.all(np.isfinite(a)) and np.abs(a).max() > 1.0
    # same operations, differently scheduled: float64 rounding of ~1e3 px errors
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9)
    with jax.disable_jit():
        c = np.asarray(corner_errors_px(params, data))
    np.testing.assert_allclose(a, c, rtol=1e-12, atol=1e-9)


def _toy_problem(V, K, seed):
    from test_linear import _Toy, _toy_residuals

    rng = np.random.default_rng(seed)
    truth = _Toy(jnp.array([0.4, 1.1, -0.2]), jnp.asarray(rng.normal(size=(V, 2))))
    a = jnp.asarray(rng.normal(size=(V, K, 3)))
    y = _toy_residuals(truth, (a, jnp.zeros((V, K)))).reshape(V, K)  # residual pred - y
    start = _Toy(truth.g + 0.1, truth.board_poses + 0.1)
    return _toy_residuals, truth, start, (a, y)


def test_least_squares_compiles_only_solver_programs_per_shape():
    """A solve of a new shape lowers the solver's programs and nothing else: the host-side
    work is NumPy (an eager jax.numpy call would be one more program per shape)."""
    from scheimflux.calibration.core._solve import _split_host, least_squares

    fn, _, start, data = _toy_problem(4, 6, 5)
    least_squares(fn, start, data, blocks="board_poses")  # shape-independent programs
    fn, truth, start, data = _toy_problem(5, 7, 6)  # shapes of no other test
    spec = free_spec(start, ())
    x_host, unravel_h, _ = _split_host(start, spec)
    x_dev, unravel_d, _ = split(start, spec)
    np.testing.assert_array_equal(x_host, np.asarray(x_dev))  # the same state vector
    assert unravel_h == unravel_d and x_host.dtype == np.float64
    names = []

    def listen(event, duration, **kw):
        # lowering: once per top-level program (compiled or read from the cache); the
        # jits nested inside a traced program are not lowered on their own
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            names.append(str(kw.get("fun_name")).removeprefix("jit(").removesuffix(")"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        fit = least_squares(fn, start, data, blocks="board_poses")
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert fit.converged and fit.rms < 1e-8  # noise-free data: the truth is recovered
    np.testing.assert_allclose(np.asarray(fit.params.g), np.asarray(truth.g), atol=1e-7)
    # the LM loop is `_solve._lm_solve` (traced: a residual function of the tests is
    # not exported)
    assert "_lm_solve" in names and "_normal_detect" in names, names
    assert set(names) <= {"_lm_solve", "_normal_detect", "_normal_at"}, names
