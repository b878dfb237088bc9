"""Geometric fits: exact recovery on noise-free points, statistics on noisy ones."""

import math

import numpy as np
import pytest

from scheimflux.metrology import fit_circle_3d, fit_cylinder, fit_plane, step_height


def _rot(axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(axis, e1), axis])


def _cylinder_points(rng, point, axis, r, n, arc=2 * math.pi, length=10.0, noise=0.0):
    R = _rot(axis)
    a = rng.uniform(0.3, 0.3 + arc, n)
    z = rng.uniform(-length / 2, length / 2, n)
    local = np.column_stack([r * np.cos(a), r * np.sin(a), z])
    local[:, :2] += (
        noise * rng.standard_normal(n)[:, None] * np.column_stack([np.cos(a), np.sin(a)])
    )
    return local @ R.T + point


def _angle(u, v):
    # atan2(|u x v|, |u . v|): accurate near 0, where acos of a rounded cosine is only good
    # to sqrt(machine epsilon) ~ 1.5e-8 rad
    return math.atan2(float(np.linalg.norm(np.cross(u, v))), abs(float(np.dot(u, v))))


def test_plane_exact_and_noisy():
    rng = np.random.default_rng(0)
    n = np.array([0.3, -0.2, 0.93])
    n /= np.linalg.norm(n)
    R = _rot(n)
    uv = rng.uniform(-5, 5, (200, 2))
    pts = np.column_stack([uv, np.zeros(200)]) @ R.T + [1.0, 2.0, 150.0]
    fit = fit_plane(pts)
    assert _angle(fit.normal, n) < 1e-12
    assert abs((fit.point - [1.0, 2.0, 150.0]) @ n) < 1e-9
    assert fit.rms < 1e-9 and fit.residuals.shape == (200,)
    sigma = 1e-3
    noisy = pts + sigma * rng.standard_normal(200)[:, None] * n
    fit = fit_plane(noisy)
    assert 0.8 * sigma < fit.rms < 1.2 * sigma
    assert _angle(fit.normal, n) < 5 * sigma / 5.0 / math.sqrt(200 / 3)


def test_circle_3d_exact():
    rng = np.random.default_rng(1)
    n = np.array([0.1, 0.5, 0.86])
    R = _rot(n)
    a = rng.uniform(0, 2.0, 50)  # a partial arc
    pts = np.column_stack([17.5 * np.cos(a), 17.5 * np.sin(a), np.zeros(50)]) @ R.T + [3, -4, 200]
    fit = fit_circle_3d(pts)
    assert abs(fit.radius - 17.5) < 1e-9
    assert np.allclose(fit.centre, [3, -4, 200], atol=1e-9)
    assert _angle(fit.normal, n) < 1e-12
    assert fit.rms < 1e-9 and fit.plane_rms < 1e-9


@pytest.mark.parametrize("radius_known", [False, True])
def test_cylinder_exact(radius_known):
    rng = np.random.default_rng(2)
    axis = np.array([0.2, 0.95, -0.1])
    axis /= np.linalg.norm(axis)
    p0 = np.array([1.0, -2.0, 160.0])
    pts = _cylinder_points(rng, p0, axis, 17.5, 300)
    fit = fit_cylinder(pts, radius=17.5 if radius_known else None)
    assert abs(fit.radius - 17.5) < 1e-9
    assert _angle(fit.direction, axis) < 1e-10
    # the reported point lies on the true axis
    d = fit.point - p0
    assert np.linalg.norm(d - (d @ axis) * axis) < 1e-9
    assert fit.rms < 1e-9


def test_cylinder_partial_arc_with_guess():
    rng = np.random.default_rng(3)
    axis = np.array([0.0, 0.0, 1.0])
    pts = _cylinder_points(rng, np.array([0.0, 0.0, 0.0]), axis, 18.646, 400, arc=math.pi / 2)
    fit = fit_cylinder(pts, axis_guess=[0.05, 0.0, 1.0])
    assert abs(fit.radius - 18.646) < 1e-9
    assert fit.direction @ axis > 0


def test_cylinder_noisy_within_sigma():
    rng = np.random.default_rng(4)
    sigma, n, r = 1e-3, 2000, 17.5
    axis = np.array([0.3, 0.1, 0.95])
    axis /= np.linalg.norm(axis)
    pts = _cylinder_points(rng, np.array([2.0, 1.0, 150.0]), axis, r, n, noise=sigma)
    fit = fit_cylinder(pts)
    # full circle: var(r) ≈ σ²/N
    assert abs(fit.radius - r) < 5 * sigma / math.sqrt(n)
    assert 0.9 * sigma < fit.rms < 1.1 * sigma
    assert _angle(fit.direction, axis) < 1e-3


def test_step_height_exact_and_noisy():
    rng = np.random.default_rng(5)
    n = np.array([0.1, -0.3, 0.95])
    n /= np.linalg.norm(n)
    R = _rot(n)
    xy = rng.uniform(-3, 3, (400, 2))
    labels = (xy[:, 0] > 0).astype(int)
    h = 1.5
    local = np.column_stack([xy, h * labels])
    pts = local @ R.T + [0, 0, 150]
    res = step_height(pts, labels)
    assert abs(res.height - h) < 1e-9
    assert res.sigma < 1e-9 and res.tilt < 1e-9
    sigma = 2e-3
    noisy = pts + sigma * rng.standard_normal(400)[:, None] * n
    res = step_height(noisy, labels)
    assert abs(res.height - h) < 5 * res.stderr
    assert 0.8 * sigma < res.sigma < 1.2 * sigma
    # the standard error matches the Monte-Carlo scatter of the height (base tilt included)
    heights = [
        step_height(pts + sigma * rng.standard_normal(400)[:, None] * n, labels).height
        for _ in range(300)
    ]
    assert 0.8 * res.stderr < np.std(heights) < 1.2 * res.stderr
    # labels swapped: the height is still positive
    assert abs(step_height(pts, 1 - labels).height - h) < 1e-9


def test_errors():
    with pytest.raises(ValueError, match="at least 3"):
        fit_plane(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="collinear"):
        fit_plane(np.outer(np.arange(5.0), [1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        fit_plane(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        fit_plane(np.array([[0, 0, 0], [1, 0, 0], [0, 1, np.nan]]))
    with pytest.raises(ValueError, match="collinear"):
        fit_circle_3d(np.outer(np.arange(4.0), [1.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="at least 5"):
        fit_cylinder(np.eye(3))
    with pytest.raises(ValueError, match="radius must be positive"):
        fit_cylinder(np.random.default_rng(0).normal(size=(10, 3)), radius=-1.0)
    with pytest.raises(ValueError, match="base points"):
        step_height(np.eye(3), [0, 0, 1])
    with pytest.raises(ValueError, match="no top points"):
        step_height(np.random.default_rng(0).normal(size=(4, 3)), [0, 0, 0, 0])
    with pytest.raises(ValueError, match="labels must have shape"):
        step_height(np.eye(3), [0, 1])
