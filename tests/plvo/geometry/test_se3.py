"""SE(3)/SO(3) maps: exp/log round trips (including near 0 and near pi), inverse, composition, adjoint, gtsam."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plvo.geometry import se3

SETTINGS = settings(max_examples=60, deadline=None)

unit = st.tuples(*[st.floats(-1.0, 1.0)] * 3).map(np.array).filter(lambda v: np.linalg.norm(v) > 0.1)
unit = unit.map(lambda v: v / np.linalg.norm(v))
angles = st.floats(0.0, np.pi - 1e-3)
translations = st.tuples(*[st.floats(-50.0, 50.0)] * 3).map(np.array)


@st.composite
def tangents(draw, max_angle: float = np.pi - 1e-3) -> np.ndarray:
    axis = draw(unit)
    return np.concatenate([draw(translations), draw(st.floats(0.0, max_angle)) * axis])


@st.composite
def poses(draw) -> np.ndarray:
    return se3.exp(draw(tangents()))


def _is_rotation(R: np.ndarray, tol: float = 1e-12) -> bool:
    return np.abs(R.T @ R - np.eye(3)).max() < tol and abs(np.linalg.det(R) - 1.0) < tol


@SETTINGS
@given(tangents())
def test_log_exp_round_trip(xi):
    T = se3.exp(xi)
    assert _is_rotation(T[:3, :3], 1e-12)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(se3.log(T), xi, atol=1e-9 * (1 + np.abs(xi).max()))


@SETTINGS
@given(poses())
def test_exp_log_round_trip(T):
    xi = se3.log(T)
    assert np.linalg.norm(xi[3:]) <= np.pi + 1e-12
    np.testing.assert_allclose(se3.exp(xi), T, atol=1e-11)


@SETTINGS
@given(unit, st.floats(0.0, 1e-2), st.sampled_from([1e-12, 1e-9, 1e-6, 1e-4, 1e-3, 1e-2, 0.0]))
def test_so3_log_near_pi(axis, frac, eps):
    """Rotations within 1e-2 rad of pi (the old code lost ~eps of accuracy there): exact to 1e-13."""
    theta = np.pi - eps * (1.0 - frac)
    R = se3.so3_exp(theta * axis)
    phi = se3.so3_log(R)
    np.testing.assert_allclose(se3.so3_exp(phi), R, atol=1e-13)
    assert abs(np.linalg.norm(phi) - theta) < 1e-12
    # Away from exactly pi the axis sign is determined; at pi both signs are the same rotation.
    if eps > 1e-9:
        np.testing.assert_allclose(phi, theta * axis, atol=1e-10)


@pytest.mark.parametrize("diag", [(1, -1, -1), (-1, 1, -1), (-1, -1, 1)])
def test_so3_log_exactly_pi(diag):
    R = np.diag(np.array(diag, dtype=float))
    phi = se3.so3_log(R)
    assert abs(np.linalg.norm(phi) - np.pi) < 1e-14
    np.testing.assert_allclose(se3.so3_exp(phi), R, atol=1e-15)


@SETTINGS
@given(unit, st.sampled_from([0.0, 1e-12, 1e-9, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 2e-3]), translations)
def test_small_angle_round_trip(axis, theta, rho):
    """Near identity the closed forms cancel; the series keep log(exp(xi)) exact to ~1e-13 relative."""
    xi = np.concatenate([rho, theta * axis])
    back = se3.log(se3.exp(xi))
    np.testing.assert_allclose(back[:3], rho, atol=1e-12 * (1 + np.abs(rho).max()))
    np.testing.assert_allclose(back[3:], theta * axis, atol=1e-15 + 1e-12 * theta)
    assert abs(se3.rotation_angle(se3.exp(xi)) - theta) < 1e-15 + 1e-12 * theta


@SETTINGS
@given(poses())
def test_inv(T):
    np.testing.assert_allclose(T @ se3.inv(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(se3.inv(T), np.linalg.inv(T), atol=1e-10)
    np.testing.assert_allclose(se3.inv(se3.inv(T)), T, atol=1e-12)


@SETTINGS
@given(poses(), poses(), poses())
def test_compose_and_transform_points(A, B, C):
    np.testing.assert_allclose(se3.compose(A, B, C), A @ B @ C, atol=1e-12)
    np.testing.assert_array_equal(se3.compose(), np.eye(4))
    pts = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 10.0]])
    via = se3.transform_points(A, se3.transform_points(B, pts))
    np.testing.assert_allclose(se3.transform_points(se3.compose(A, B), pts), via, atol=1e-10)
    np.testing.assert_allclose(se3.transform_points(se3.inv(A), se3.transform_points(A, pts)), pts, atol=1e-10)


@SETTINGS
@given(poses(), tangents(max_angle=2.0))
def test_adjoint_property(T, xi):
    lhs = se3.exp(se3.adjoint(T) @ xi)
    rhs = T @ se3.exp(xi) @ se3.inv(T)
    np.testing.assert_allclose(lhs, rhs, atol=1e-9)


@SETTINGS
@given(tangents())
def test_matches_gtsam(xi):
    """Our (rho, phi) exp and adjoint agree with gtsam's Pose3 (phi, rho) after reordering."""
    T = se3.exp(xi)
    np.testing.assert_allclose(gtsam.Pose3.Expmap(se3.to_gtsam_tangent(xi)).matrix(), T, atol=1e-10)
    perm = np.zeros((6, 6))
    perm[:3, 3:] = np.eye(3)
    perm[3:, :3] = np.eye(3)
    np.testing.assert_allclose(perm @ gtsam.Pose3(T).AdjointMap() @ perm, se3.adjoint(T), atol=1e-10)


@SETTINGS
@given(tangents())
def test_rotation_angle_and_from_rt(xi):
    T = se3.exp(xi)
    assert abs(se3.rotation_angle(T) - np.linalg.norm(xi[3:])) < 1e-12
    assert abs(se3.rotation_angle(T[:3, :3]) - np.linalg.norm(xi[3:])) < 1e-12
    np.testing.assert_array_equal(se3.from_rt(T[:3, :3], T[:3, 3]), T)


@SETTINGS
@given(poses(), st.integers(0, 2**31 - 1))
def test_orthonormalize(T, seed):
    noisy = T.copy()
    noisy[:3, :3] += np.random.default_rng(seed).normal(scale=1e-6, size=(3, 3))
    fixed = se3.orthonormalize(noisy)
    assert _is_rotation(fixed[:3, :3], 1e-12)
    np.testing.assert_allclose(fixed, T, atol=1e-5)
    np.testing.assert_array_equal(fixed[:3, 3], T[:3, 3])


def test_orthonormalize_reflection_gives_rotation():
    reflected = np.diag([1.0, 1.0, -1.0, 1.0])
    assert _is_rotation(se3.orthonormalize(reflected)[:3, :3])


def test_hat_is_cross_product():
    w, v = np.array([0.3, -1.2, 2.0]), np.array([4.0, 0.5, -1.0])
    np.testing.assert_allclose(se3.hat(w) @ v, np.cross(w, v), atol=1e-15)
