"""Pupil-integrated imaging: spot centroids of stop-filling ray bundles (simulate._pupil).

Every check compares the bundle's centroid with the chief ray traced by the same Snell's
law tracer (`Rig.project`), or with itself at other apertures and sampling densities: no
camera model is involved. One rig (the 8 mm f/4.5 Tessar at ×0.5 on the benchmark's
2448 × 2048, 3.45 µm sensor, unrefined focus) and one array shape serve all tests, so
they share a single compilation; stop sizes and sensor tilts are pytree leaves.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scheimflux.simulate import build_rig, load_lens
from scheimflux.simulate._pupil import (
    _image_flat,
    _straight_edge_share,
    pupil_grid,
    pupil_image,
    pupil_points,
)

_N = pupil_grid(16).size  # every sampling is padded to this many nodes: one compilation
# Fractions of the way from the principal pixel to the sensor corner.
_FIELD = np.array([0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 0.97])


@pytest.fixture(scope="module")
def world():
    lens = load_lens("tessar")
    rig = build_rig(lens, 0.5, sensor=(2448, 2048), pixel_pitch_mm=(0.00345, 0.00345), refine=False)
    w, h = rig.sensor_size
    c = np.array([float(rig.x0), float(rig.y0)])
    uv = c + _FIELD[:, None] * (np.array([w - 1.0, h - 1.0]) - c)
    X = rig.laser_points(jnp.asarray(uv))
    chief, ok = rig.project(X)
    assert bool(np.all(ok))
    return rig, X, np.asarray(chief)


def _image(rig, X, rings=8, stop_scale=1.0):
    if stop_scale != 1.0:
        sd = rig.lens.semi_diameters[rig.lens.stop] * stop_scale
        rig = eqx.tree_at(lambda r: r.lens, rig, rig.lens.with_stop_semi_diameter(float(sd)))
    return pupil_image(rig, X, pupil_grid(rings).padded(_N))


def test_pupil_grid_is_an_area_quadrature():
    g = pupil_grid(5)
    p, w = np.asarray(g.points), np.asarray(g.weights)
    assert g.size == 5 * 11 and np.all(w > 0) and abs(w.sum() - 1.0) < 1e-14
    assert np.all(np.hypot(p[:, 0], p[:, 1]) < 1.0)
    # Mean of x^a y^b over the unit disk: 0 for odd a or b; E[r²] = 1/2, E[x²y²] = 1/24,
    # E[x⁴] = 1/8 (polar integrals of r^(a+b+1) cos^a sin^b); exact up to degree 9.
    x, y = p[:, 0], p[:, 1]
    r2 = x**2 + y**2
    moments = ((x, 0.0), (x * y, 0.0), (x**3 * y, 0.0), (r2, 0.5), (x**2 * y**2, 1 / 24),
               (x**4, 1 / 8), (r2**4, 1 / 5))  # fmt: skip
    for val, want in moments:
        assert abs(np.sum(w * val) - want) < 1e-13
    padded = g.padded(80)
    assert padded.size == 80 and float(jnp.sum(padded.weights)) == pytest.approx(1.0, abs=1e-14)
    with pytest.raises(ValueError, match="rings >= 1"):
        pupil_grid(0)


def test_on_axis_centroid_equals_chief_ray(world):
    rig, X, chief = world
    # Untilted sensor: the bundle of an on-axis point is rotationally symmetric about the
    # axis, so its centroid is the chief ray's hit exactly (rounding: ~1e-12 px).
    flat = eqx.tree_at(lambda r: (r.phi, r.theta), rig, (jnp.zeros(()), jnp.zeros(())))
    img = _image(flat, X)
    chief_flat = np.asarray(flat.project(X)[0])
    np.testing.assert_allclose(np.asarray(img.uv)[0], chief_flat[0], atol=1e-9)
    # Tilted about y only (φ = 0): the mirror symmetry y → −y survives, so v is exact;
    # u is not (the cone meets the tilted plane at different depths across the pupil).
    assert float(rig.phi) == 0.0
    img = _image(rig, X)
    assert abs(float(img.uv[0, 1]) - chief[0, 1]) < 1e-9
    assert abs(float(img.uv[0, 0]) - chief[0, 0]) < 0.05
    assert bool(img.valid[0]) and float(img.fraction[0]) == pytest.approx(1.0, abs=1e-14)


def test_small_aperture_limit_is_the_chief_ray(world):
    """Linear pupil terms integrate to zero (the quadrature is exact for them), so the
    centroid offset from the chief ray is quadratic in the stop radius a: coma ∝ a² h plus
    defocus on the tilted sensor ∝ a². Halving a must divide it by 4 (up to the a⁴ terms),
    and at a/1000 it must be below the a² extrapolation of the a/4 offset (× 1.5)."""
    rig, X, chief = world
    shift = {s: np.linalg.norm(np.asarray(_image(rig, X, stop_scale=s).uv) - chief, axis=1)
             for s in (0.5, 0.25, 1e-3)}  # fmt: skip
    mid = slice(1, 6)  # unvignetted points (fraction 1 at these stops)
    ratio = shift[0.5][mid] / shift[0.25][mid]
    assert np.all((ratio > 3.6) & (ratio < 4.4)), ratio
    bound = 1.5 * shift[0.25] * (1e-3 / 0.25) ** 2 + 1e-9
    assert np.all(shift[1e-3] < bound), (shift[1e-3], bound)


def test_shift_grows_with_aperture_and_field(world):
    rig, X, chief = world
    shifts = [
        np.linalg.norm(np.asarray(_image(rig, X, stop_scale=s).uv) - chief, axis=1)
        for s in (0.35, 0.7, 1.0)  # ≈ f/12.9, f/6.4, f/4.5
    ]
    # Aperture: larger stops move the centroid further at every off-axis point that is not
    # vignetted (where a clear aperture cuts the bundle the cut, not coma, dominates).
    m = slice(1, 6)
    assert np.all(shifts[1][m] > shifts[0][m]) and np.all(shifts[2][m] > shifts[1][m])
    # Field: at small heights coma is linear in the image height h (third order), so the
    # shift grows with h; 5 → 10 → 20 % of the half-diagonal.
    s = shifts[2]
    assert s[1] < s[2] < s[3]
    assert s[2] / s[1] == pytest.approx(2.0, rel=0.25)
    # The effect is real at f/4.5: ≥ 0.3 px (1 µm) in mid-field.
    assert s[4] > 0.3


def test_sampling_density_converges(world):
    rig, X, _ = world
    ref = _image(rig, X, rings=16)
    err6 = np.linalg.norm(np.asarray(_image(rig, X, rings=6).uv - ref.uv), axis=1)
    frac = np.asarray(ref.fraction)
    clear = frac > 1.0 - 1e-12
    assert clear[:6].all() and not clear[-1]  # the corner is vignetted at f/4.5
    # Unvignetted: the centroid is smooth over the stop, Gauss convergence is spectral.
    assert np.all(err6[clear] < 1e-5)


def test_vignetted_centroid_converges_at_second_order(world):
    """Where a clear aperture cuts the bundle each cell is split along the linearised
    edge, so the quadrature error falls with the square of the node spacing: doubling
    the rings (8 → 16) must divide the error against a 48-ring reference by about 4
    (> 3 asserted; a pass/fail test per node, first order, gives ~2 and here 1.1–2.2)."""
    rig, X, _ = world
    ref = pupil_image(rig, X, pupil_grid(48))
    vig = np.asarray(ref.fraction) < 1.0 - 1e-12
    assert vig.sum() == 2  # the 80 % and 97 % field points
    err = {r: np.linalg.norm(np.asarray(_image(rig, X, rings=r).uv - ref.uv), axis=1)
           for r in (8, 16)}  # fmt: skip
    assert np.all(err[16][vig] < err[8][vig] / 3.0), (err[8][vig], err[16][vig])
    # Measured: 0.003 / 0.010 px at 8 rings, 0.0007 / 0.0022 px at 16 (4.1×, 4.4×).
    assert np.all(err[16][vig] < 0.005)
    frac8 = np.asarray(_image(rig, X, rings=8).fraction)
    np.testing.assert_allclose(frac8, np.asarray(ref.fraction), atol=1e-3)


def test_cells_tile_the_disk():
    g = pupil_grid(7)
    p, w, cell = (np.asarray(a) for a in (g.points, g.weights, g.cells))
    area = 0.5 * (cell[:, 1] ** 2 - cell[:, 0] ** 2) * cell[:, 2]
    np.testing.assert_allclose(area, np.pi * w, rtol=1e-12)  # each node's share of the disk
    rho = np.hypot(p[:, 0], p[:, 1])
    assert np.all((cell[:, 0] < rho) & (rho < cell[:, 1]))  # Gauss nodes interlace the sums
    assert cell[:, 0].min() == 0.0 and cell[:, 1].max() == 1.0
    assert np.all(np.asarray(g.padded(g.size + 3).cells)[-3:] == 0.0)


def _clipped_area(half_w, half_h, normal, x):
    """Area of the rectangle |u| <= half_w, |v| <= half_h on the side normal·(u, v) <= x
    (Sutherland–Hodgman clipping of its polygon by the half-plane), independent of the
    distribution-function formula under test."""
    poly = [(-half_w, -half_h), (half_w, -half_h), (half_w, half_h), (-half_w, half_h)]
    out = []
    for i, a in enumerate(poly):
        b = poly[(i + 1) % 4]
        fa, fb = normal @ a - x, normal @ b - x
        if fa <= 0:
            out.append(a)
        if fa * fb < 0:
            t = fa / (fa - fb)
            out.append((a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])))
    if len(out) < 3:
        return 0.0
    u, v = np.array(out).T
    return 0.5 * abs(np.dot(u, np.roll(v, -1)) - np.dot(v, np.roll(u, -1)))


def test_straight_edge_share_is_the_clipped_area():
    rng = np.random.default_rng(4)
    for _ in range(200):
        hw, hh = rng.uniform(0.01, 1.0, 2)
        a = rng.uniform(0, 2 * np.pi)
        n = np.array([np.cos(a), np.sin(a)])
        wr, wa = 2 * hw * abs(n[0]), 2 * hh * abs(n[1])
        x = rng.uniform(-1.2, 1.2) * 0.5 * (wr + wa)
        got = float(_straight_edge_share(x, max(wr, wa), min(wr, wa)))
        assert got == pytest.approx(_clipped_area(hw, hh, n, x) / (4 * hw * hh), abs=1e-12)
    # An edge along a side (b = 0): the share is linear across the cell.
    assert float(_straight_edge_share(0.25, 1.0, 0.0)) == pytest.approx(0.75, abs=1e-15)


def test_vignetting_is_counted(world):
    rig, X, _ = world
    img = _image(rig, X)
    frac = np.asarray(img.fraction)
    assert frac[0] == pytest.approx(1.0, abs=1e-14)
    assert 0.3 < frac[-1] < 0.95  # the corner at 25° loses light on the clear apertures
    assert frac[-1] < frac[-2] <= 1.0  # vignetting grows towards the corner
    # With every clear aperture but the stop's opened, the light returns: all of it up to
    # 80 % of the field; at the corner only rays missing a steep surface or totally
    # reflected are still lost.
    sd = rig.lens.semi_diameters
    opened = jnp.full_like(sd, jnp.inf).at[rig.lens.stop].set(sd[rig.lens.stop])
    wide = np.asarray(_image(eqx.tree_at(lambda r: r.lens.semi_diameters, rig, opened), X).fraction)
    np.testing.assert_allclose(wide[:7], 1.0, atol=1e-12)
    assert wide[-1] > frac[-1] + 0.05
    # A point far outside the field: every ray vignetted → invalid, finite, never NaN.
    far = X.at[-1].set(X[-1] * jnp.asarray([40.0, 40.0, 1.0]))
    img = _image(rig, far)
    assert not bool(img.valid[-1]) and float(img.fraction[-1]) == 0.0
    assert bool(jnp.all(jnp.isfinite(img.uv))) and bool(jnp.all(jnp.isfinite(img.cov_px2)))
    # The host-side batch marks it NaN (the observations' "not seen").
    uv, ok, fr, _ = pupil_points(rig, np.asarray(far), pupil_grid(16), chunk=len(_FIELD))
    assert not ok[-1] and np.all(np.isnan(uv[-1])) and ok[:-1].all()
    np.testing.assert_allclose(uv[:-1], np.asarray(_image(rig, far, rings=16).uv)[:-1], atol=1e-9)


@pytest.mark.slow  # the eager trace takes minutes on a loaded 2-core machine
def test_jit_equals_eager(world):
    rig, X, _ = world
    sampling = pupil_grid(8).padded(_N)
    jitted = pupil_image(rig, X, sampling)
    with jax.disable_jit():
        uv, cov, frac, ok = _image_flat(rig, X, sampling)
    np.testing.assert_allclose(np.asarray(uv), np.asarray(jitted.uv), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(cov), np.asarray(jitted.cov_px2), atol=1e-9)
    np.testing.assert_allclose(np.asarray(frac), np.asarray(jitted.fraction), atol=1e-14)
    np.testing.assert_array_equal(np.asarray(ok), np.asarray(jitted.valid))


@pytest.mark.slow
def test_centroid_gradient_matches_central_differences(world):
    rig, X, _ = world
    x = X[3]
    sampling = pupil_grid(2)
    fn = lambda p: pupil_image(rig, p[None], sampling).uv[0]  # noqa: E731
    jac = np.asarray(jax.jacfwd(fn)(x))
    h = 1e-4  # mm; the centroid is smooth here (no vignetting), truncation ~h² ≪ 1e-4 px
    for k in range(3):
        e = jnp.zeros(3).at[k].set(h)
        fd = (np.asarray(fn(x + e)) - np.asarray(fn(x - e))) / (2 * h)
        np.testing.assert_allclose(jac[:, k], fd, rtol=1e-5, atol=1e-4)


def test_f_number_parameter(world):
    rig, X, _ = world
    closed = pupil_image(rig, X, pupil_grid(16).padded(_N), f_number=9.0)
    half = _image(rig, X, stop_scale=0.5)  # f/4.5 → f/9: the stop radius halves
    np.testing.assert_allclose(np.asarray(closed.uv), np.asarray(half.uv), atol=1e-6)


@pytest.mark.slow
def test_observations_with_centroid_imaging(world):
    """`simulate_observations(imaging="centroid")`: same poses and noise draws as the
    chief-ray data, pixels moved to the pupil centroids of the same 3-D points."""
    from scheimflux.simulate import simulate_observations
    from scheimflux.targets import Checkerboard

    rig, _, _ = world
    board = Checkerboard(11, 8, 0.9)
    kw = dict(n_views=2, stage_scan=False, seed=3, corner_noise_px=0.03)
    obs_c, truth_c = simulate_observations(rig, board, **kw)
    sampling = pupil_grid(16)
    obs_p, truth_p = simulate_observations(rig, board, imaging="centroid", pupil=sampling, **kw)
    assert truth_p.rig["imaging"] == "centroid" and truth_c.rig["imaging"] == "chief"
    np.testing.assert_allclose(truth_p.corners_c, truth_c.corners_c)  # same poses
    both = np.isfinite(truth_p.corners_px[..., 0]) & np.isfinite(truth_c.corners_px[..., 0])
    assert both.sum() > 100
    noise_c = np.stack([v.corners_px for v in obs_c.views]) - truth_c.corners_px
    noise_p = np.stack([v.corners_px for v in obs_p.views]) - truth_p.corners_px
    np.testing.assert_allclose(noise_p[both], noise_c[both], atol=1e-9)  # same draws
    uv, ok, _, _ = pupil_points(rig, truth_p.corners_c.reshape(-1, 3), sampling)
    np.testing.assert_allclose(truth_p.corners_px[both], uv.reshape(-1, 88, 2)[both], atol=1e-9)
    shift = np.linalg.norm(truth_p.corners_px[both] - truth_c.corners_px[both], axis=1)
    assert shift.max() > 0.1  # f/4.5 Tessar: the centroid is not the chief ray
    for s_p in truth_p.stripe_px:
        assert np.all(np.isfinite(s_p))
    with pytest.raises(ValueError, match="imaging must be 'chief' or 'centroid'"):
        simulate_observations(rig, board, imaging="marginal", **kw)


@pytest.mark.slow
def test_rig_board_maps_for_the_renderer(world):
    from scheimflux.geometry._transforms import Pose
    from scheimflux.simulate import rig_board_maps

    rig, X, chief = world
    T = Pose(np.zeros(3), np.asarray(X[3]))  # board plane through a mid-field point
    xy = np.array([[0.0, 0.0], [0.5, -0.3], [1.0, 1.0]])
    to_px, sigma = rig_board_maps(rig, T, imaging="centroid", sampling=pupil_grid(16))
    pts = np.concatenate([xy, np.zeros((3, 1))], axis=1) + np.asarray(X[3])
    uv, ok, _, sig = pupil_points(rig, pts, pupil_grid(16), on_sensor=False)
    np.testing.assert_allclose(to_px(xy), uv, atol=1e-9)
    np.testing.assert_allclose(sigma(xy), sig, atol=1e-12)
    assert np.all(sig > 0.1)  # f/4.5: the spot is more than a tenth of a pixel
    to_px, blur = rig_board_maps(rig, T)
    assert blur == 0.0
    np.testing.assert_allclose(to_px(xy)[0], chief[3], atol=1e-9)
    with pytest.raises(ValueError, match="imaging must be"):
        rig_board_maps(rig, T, imaging="splat")
