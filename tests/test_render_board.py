"""Checkerboard rendering: the numerical inverse of the board → pixel map, exact
anti-aliasing, blur, bit depths."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scheimflux as sf
from scheimflux.simulate._render_board import board_map, render_checkerboard
from scheimflux.targets._board import Checkerboard


def _focus_pose(cam, board, rot_deg=0.0, tilt_deg=(0.0, 0.0)):
    """Board pose on the camera's plane of sharp focus, centred on the optical axis."""
    from scipy.spatial.transform import Rotation

    centre = np.asarray(cam.object_point(jnp.array([float(cam.x0), float(cam.y0)])))
    n = np.asarray(cam.focus_plane().normal)  # +z of the board: away from the camera
    ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
    ex /= np.linalg.norm(ex)
    R0 = np.stack([ex, np.cross(n, ex), n], axis=1)
    R = R0 @ Rotation.from_euler("xyz", [*tilt_deg, rot_deg], degrees=True).as_matrix()
    return sf.Pose.from_matrix(R, centre - R @ board.centre_mm)


@jax.jit
def _project_board(cam, pose, xy):
    X = jnp.concatenate([xy, jnp.zeros_like(xy[:, :1])], axis=1)
    return cam.project(pose.apply(X))


def _projector(cam, pose, offset=(0.0, 0.0)):
    """`board_to_pixel`: board points (N, 2) mm → pixels, minus `offset` (a sensor crop)."""

    def board_to_pixel(xy):
        xy = jnp.asarray(np.asarray(xy, dtype=np.float64))
        return np.asarray(_project_board(cam, pose, xy)) - np.asarray(offset)

    return board_to_pixel


def test_inverse_map_reprojects_to_the_pixel():
    cam = sf.paper_thick_lens()
    board = Checkerboard(11, 8, 0.3)
    f = _projector(cam, _focus_pose(cam, board, rot_deg=20.0, tilt_deg=(25.0, -15.0)))
    bmap = board_map(f, (1200, 1600), (-0.6, 3.6, -0.6, 2.7), grid_step_px=16)
    xy = bmap.xy()
    rng = np.random.default_rng(0)
    v, u = rng.integers(0, 1200, 3000), rng.integers(0, 1600, 3000)
    back = f(xy[v, u])
    err = np.hypot(back[:, 0] - u, back[:, 1] - v)
    assert np.all(np.isfinite(err))
    assert err.max() < 1e-4  # far below 0.01 px
    # the derivatives used for the box filter agree with the map's Jacobian
    r = bmap.rows(600, 601)
    J = np.linalg.inv(
        np.stack(
            [
                (f(xy[600, 800][None] + [1e-6, 0]) - f(xy[600, 800][None])) / 1e-6,
                (f(xy[600, 800][None] + [0, 1e-6]) - f(xy[600, 800][None])) / 1e-6,
            ],
            axis=-1,
        )[0]
    )
    np.testing.assert_allclose(
        [[r["x_u"][0, 800], r["x_v"][0, 800]], [r["y_u"][0, 800], r["y_v"][0, 800]]],
        J,
        rtol=1e-5,
    )


def _affine(k, u0, v0, angle_deg=0.0):
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    return lambda xy: (np.asarray(xy) @ np.array([[c, -s], [s, c]]).T) * k + [u0, v0]


def test_box_filter_is_exact_for_straight_edges():
    board = Checkerboard(5, 4, 1.0)
    k, u0, v0 = 23.37, 300.3, 200.71
    img = render_checkerboard(
        board, _affine(k, u0, v0), shape=(400, 600), bit_depth=16, black=0.0, white=1.0
    )
    dark = 1.0 - img.astype(np.float64) / 65535
    row = dark[int(round(v0 + 0.5 * k))]  # through squares y ∈ [0, 1]: black on x ∈ [0, 1]
    lo, hi = int(u0 - 0.5 * k), int(u0 + 1.5 * k)
    u = np.arange(lo, hi)
    assert row[lo:hi].sum() == pytest.approx(k, abs=2e-3)  # width of a black square
    centroid = (u * row[lo:hi]).sum() / row[lo:hi].sum()
    assert centroid == pytest.approx(u0 + 0.5 * k, abs=2e-3)


def test_colours_quiet_zone_and_background():
    board = Checkerboard(5, 4, 1.0)
    k, u0, v0 = 20.0, 200.0, 150.0
    img = render_checkerboard(
        board, _affine(k, u0, v0), shape=(300, 400), black=0.1, white=0.9, background=0.5
    )
    level = lambda x, y: img[int(round(v0 + k * y)), int(round(u0 + k * x))] / 255  # noqa: E731
    assert level(-0.5, -0.5) == pytest.approx(0.1, abs=0.01)  # black outside corner 0
    assert level(0.5, -0.5) == pytest.approx(0.9, abs=0.01)
    assert level(0.5, 0.5) == pytest.approx(0.1, abs=0.01)
    assert level(-1.5, 1.5) == pytest.approx(0.9, abs=0.01)  # quiet zone
    assert level(-2.5, 1.5) == pytest.approx(0.5, abs=0.01)  # background
    assert level(5.5, 4.5) == pytest.approx(0.9, abs=0.01)  # 5 + 4 odd: white corner square


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_bit_depths(bits):
    board = Checkerboard(5, 4, 1.0)
    img = render_checkerboard(
        board,
        _affine(20.0, 200.0, 150.0, 10.0),
        shape=(300, 400),
        bit_depth=bits,
        noise_sigma=0.01,
        seed=0,
    )
    assert img.dtype == (np.uint8 if bits == 8 else np.uint16)
    assert img.max() <= 2**bits - 1
    assert img.max() > 0.8 * 2**bits  # full scale used


def test_blur_vignetting_and_noise():
    board = Checkerboard(5, 4, 1.0)
    f = _affine(20.0, 200.0, 150.0, 10.0)
    kw = dict(shape=(300, 400), bit_depth=16)
    sharp = render_checkerboard(board, f, **kw).astype(float)
    blurred = render_checkerboard(board, f, blur_sigma_px=2.0, **kw).astype(float)
    varying = render_checkerboard(
        board, f, blur_sigma_px=lambda xy: 0.5 * np.clip(xy[:, 0], 0, None), **kw
    ).astype(float)
    # blur smooths the edges: smaller gradients; the varying blur is sharp on the left
    grad = lambda im: np.abs(np.diff(im, axis=1))  # noqa: E731
    assert grad(blurred).max() < 0.5 * grad(sharp).max()
    left = (slice(140, 160), slice(170, 215))  # x < 0.5 square: sigma < 0.25 px
    right = (slice(140, 160), slice(270, 310))  # x ≈ 4: sigma ≈ 2 px
    assert grad(varying[left]).max() > 0.8 * grad(sharp[left]).max()
    assert grad(varying[right]).max() < 0.5 * grad(sharp[right]).max()
    vign = render_checkerboard(board, f, vignetting=0.3, **kw).astype(float)
    assert vign[0, 0] == pytest.approx(0.7 * sharp[0, 0], rel=0.01)
    a = render_checkerboard(board, f, noise_sigma=0.02, seed=3, **kw)
    b = render_checkerboard(board, f, noise_sigma=0.02, seed=3, **kw)
    np.testing.assert_array_equal(a, b)
    assert np.std(a.astype(float) - sharp) == pytest.approx(0.02 * 65535, rel=0.1)


def test_map_with_invalid_region_renders_background():
    board = Checkerboard(5, 4, 1.0)
    g = _affine(20.0, 200.0, 150.0)

    def f(xy):  # a lens whose field ends at x = 7 mm: no pixel there
        uv = g(xy)
        uv[np.asarray(xy)[:, 0] > 7.0] = np.nan
        return uv

    img = render_checkerboard(board, f, shape=(300, 400), background=0.5, black=0.1)
    assert img[150, 390] == pytest.approx(0.5 * 255, abs=1)
    assert img[int(150 - 10), int(200 - 10)] == pytest.approx(0.1 * 255, abs=1)


def test_rejects_bad_arguments():
    board = Checkerboard(5, 4, 1.0)
    f = _affine(20.0, 200.0, 150.0)
    with pytest.raises(ValueError, match="bit_depth"):
        render_checkerboard(board, f, shape=(300, 400), bit_depth=10)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        render_checkerboard(board, lambda xy: np.zeros(3), shape=(300, 400))
