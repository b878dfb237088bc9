"""The shared small fits of `scheimflux.geometry` (TLS plane, perpendicular basis, unit
rows, Kabsch), checked against independent constructions: SciPy's rotation alignment,
planes and rotations made by hand, and the invariances each fit must have."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scheimflux.geometry import (
    aligned_distances,
    fit_plane_svd,
    perpendicular_basis,
    rigid_fit,
    unit_rows,
)

# float64 rounding of the sums and SVDs below, O(100 ε) on unit-size data
TIGHT = 1e-12


@pytest.mark.parametrize("shape", [(3,), (7, 3), (2, 4, 3)])
def test_unit_rows_and_perpendicular_basis(shape):
    rng = np.random.default_rng(0)
    v = rng.normal(size=shape) * 5.0
    d = unit_rows(v)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=TIGHT)
    np.testing.assert_allclose(d * np.linalg.norm(v, axis=-1, keepdims=True), v, atol=TIGHT)
    a, b = perpendicular_basis(d)
    assert a.shape == b.shape == d.shape
    for u in (a, b):
        np.testing.assert_allclose(np.linalg.norm(u, axis=-1), 1.0, atol=TIGHT)
    np.testing.assert_allclose(np.sum(a * d, axis=-1), 0.0, atol=TIGHT)
    np.testing.assert_allclose(np.sum(b * d, axis=-1), 0.0, atol=TIGHT)
    np.testing.assert_allclose(np.sum(a * b, axis=-1), 0.0, atol=TIGHT)
    np.testing.assert_allclose(np.cross(a, b), d, atol=TIGHT)  # right-handed (a, b, d)


def test_perpendicular_basis_along_the_axes():
    # the helper axis switches from x to y near ±x: both branches must stay orthonormal
    d = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.95, 0.3122499, 0]])
    d = unit_rows(d)
    a, b = perpendicular_basis(d)
    np.testing.assert_allclose(np.einsum("ni,ni->n", a, d), 0.0, atol=TIGHT)
    np.testing.assert_allclose(np.cross(a, b), d, atol=TIGHT)


def test_fit_plane_svd_recovers_a_plane():
    rng = np.random.default_rng(1)
    n_true = unit_rows(np.array([0.2, -0.5, 0.84]))
    a, b = perpendicular_basis(n_true)
    c_true = np.array([3.0, -1.0, 250.0])
    st = rng.uniform(-20, 20, size=(400, 2))
    P = c_true + st[:, :1] * a + st[:, 1:] * b
    c, n, s = fit_plane_svd(P)
    assert abs(abs(n @ n_true) - 1.0) < TIGHT
    np.testing.assert_allclose(c, P.mean(axis=0), atol=1e-9)
    assert s[2] < 1e-9 * s[0]  # exactly planar
    # noise σ along the normal: the normal's angle error is ≈ σ / (spread · √N)
    # = 1e-3 / (11.5 · 20) ≈ 4e-6 rad; 5× that as the bound
    sigma = 1e-3
    Pn = P + rng.normal(scale=sigma, size=(len(P), 1)) * n_true
    _, n2, s2 = fit_plane_svd(Pn)
    angle = np.arctan2(np.linalg.norm(np.cross(n2, n_true)), abs(n2 @ n_true))
    assert angle < 2e-5
    np.testing.assert_allclose(s2[2] / np.sqrt(len(P)), sigma, rtol=0.15)  # RMS residual
    with pytest.raises(ValueError, match="at least 3 points"):
        fit_plane_svd(P[:2])


def _random_rotation(rng):
    return Rotation.from_rotvec(rng.normal(size=3)).as_matrix()


def test_rigid_fit_recovers_the_motion_and_matches_scipy():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(50, 3)) * 10.0
    R_true, t_true = _random_rotation(rng), rng.normal(size=3) * 5.0
    B = A @ R_true.T + t_true
    R, t = rigid_fit(A, B)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-10)
    np.testing.assert_allclose(aligned_distances(A, B), 0.0, atol=1e-10)
    # with noise: the same rotation as SciPy's independent solution (centred sets)
    Bn = B + rng.normal(scale=0.1, size=B.shape)
    R, t = rigid_fit(A, Bn)
    rot, _ = Rotation.align_vectors(Bn - Bn.mean(axis=0), A - A.mean(axis=0))
    np.testing.assert_allclose(R, rot.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(t, Bn.mean(axis=0) - R @ A.mean(axis=0), atol=1e-10)


def test_rigid_fit_never_reflects():
    # B is a mirror image of A: the best proper rotation, det +1, not the reflection
    rng = np.random.default_rng(3)
    A = rng.normal(size=(30, 3))
    B = A * np.array([1.0, 1.0, -1.0])
    R, _ = rigid_fit(A, B)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=TIGHT)
    assert np.linalg.det(R) > 0
    assert aligned_distances(A, B).max() > 0.1  # a mirror is not a rigid motion


def test_aligned_distances_keep_shape_changes():
    # a scaled copy differs in shape: after alignment what remains is |s − 1| |A − Ā|
    rng = np.random.default_rng(4)
    A = rng.normal(size=(40, 3))
    B = 1.01 * (A - A.mean(axis=0)) @ _random_rotation(rng).T + 7.0
    d = aligned_distances(A, B)
    np.testing.assert_allclose(d, 0.01 * np.linalg.norm(A - A.mean(axis=0), axis=1), atol=1e-12)
    # fewer than 3 points: the plain distances
    plain = np.linalg.norm(A[:2] - B[:2], axis=1)
    np.testing.assert_allclose(aligned_distances(A[:2], B[:2]), plain)
