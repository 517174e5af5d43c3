"""3D lines: Pluecker/orthonormal round trips, transformation, projection, residuals, trimming, Jacobians.

Random lines are well conditioned: both endpoints in front of the camera, inside the image, at least 40 px
apart, and the line at least 0.5 m from the camera centre. K has fx != fy and an off-centre principal point so
that a swapped focal length or principal point in the line projection matrix would show.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from plvo.errors import PlvoError
from plvo.geometry import lines, se3
from plvo.geometry.camera import backproject, project
from plvo.geometry.line_jacobians import (
    line_residual_jacobians,
    line_residuals_and_jacobians_batch,
    orth_plucker_jacobian,
    point_line_distance_and_jacobian,
)

SETTINGS = settings(max_examples=40, deadline=None)
WIDTH, HEIGHT = 1241, 376


@st.composite
def cameras(draw) -> np.ndarray:
    fx = draw(st.floats(400.0, 900.0))
    fy = fx * draw(st.floats(0.8, 1.25))
    cx = draw(st.floats(0.4, 0.6)) * WIDTH
    cy = draw(st.floats(0.4, 0.6)) * HEIGHT
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@st.composite
def pixel_pairs(draw) -> np.ndarray:
    uv = np.array([[draw(st.floats(5.0, WIDTH - 5.0)), draw(st.floats(5.0, HEIGHT - 5.0))] for _ in range(2)])
    assume(np.linalg.norm(uv[0] - uv[1]) > 40.0)
    return uv


@st.composite
def camera_segments(draw, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 3D segment (P, Q) in the camera frame whose exact projection is well inside the image."""
    uv = draw(pixel_pairs())
    depths = np.array([draw(st.floats(3.0, 40.0)), draw(st.floats(3.0, 40.0))])
    pts = backproject(K, uv, depths)
    assume(np.linalg.norm(np.cross(pts[0], pts[1])) / np.linalg.norm(pts[1] - pts[0]) > 0.5)
    return pts[0], pts[1]


@st.composite
def poses(draw) -> np.ndarray:
    vals = [draw(st.floats(-1.0, 1.0)) for _ in range(6)]
    return se3.exp(np.array(vals) * np.array([10, 10, 10, 1.5, 1.5, 1.5]))


@st.composite
def scenes(draw):
    """K, T_cam_world, camera-frame endpoints P, Q and the same endpoints in the world frame."""
    K = draw(cameras())
    P, Q = draw(camera_segments(K))
    T_cw = draw(poses())
    T_wc = se3.inv(T_cw)
    Pw, Qw = se3.transform_points(T_wc, np.stack([P, Q]))
    return K, T_cw, P, Q, Pw, Qw


def _same_line(L1: np.ndarray, L2: np.ndarray, tol: float) -> bool:
    """Equal up to a nonzero scale (either sign)."""
    a, b = L1 / np.linalg.norm(L1), L2 / np.linalg.norm(L2)
    return min(np.abs(a - b).max(), np.abs(a + b).max()) < tol


def _segment(K: np.ndarray, P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    uv, _ = project(K, np.stack([P, Q]))
    return uv.reshape(4)


# --- representation --------------------------------------------------------------------------------------------


@SETTINGS
@given(scenes(), st.floats(-5.0, 5.0).filter(lambda s: abs(s) > 0.05))
def test_plucker_orth_round_trip(scene, scale):
    *_, Pw, Qw = scene
    L = lines.plucker_from_points(Pw, Qw) * scale
    U, W = lines.plucker_to_orth(L)
    assert np.abs(U.T @ U - np.eye(3)).max() < 1e-12 and abs(np.linalg.det(U) - 1) < 1e-12
    assert np.abs(W.T @ W - np.eye(2)).max() < 1e-12 and abs(np.linalg.det(W) - 1) < 1e-12
    back = lines.orth_to_plucker(U, W)
    # Same line, and in fact the same orientation: back = L / |L| exactly.
    np.testing.assert_allclose(back, L / np.linalg.norm(L), atol=1e-12)
    assert _same_line(back, lines.plucker_from_points(Pw, Qw), 1e-12)


def test_plucker_from_points_basics():
    L = lines.plucker_from_points(np.array([1.0, 2.0, 0.0]), np.array([1.0, 2.0, 5.0]))
    np.testing.assert_allclose(L[3:], [0, 0, 1])
    np.testing.assert_allclose(lines.closest_point_to_origin(L), [1, 2, 0], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(L[:3]), np.sqrt(5.0))
    np.testing.assert_allclose(lines.line_direction(L * -3.0), [0, 0, -1])
    with pytest.raises(PlvoError, match="coincide"):
        lines.plucker_from_points(np.ones(3), np.ones(3))
    with pytest.raises(PlvoError, match="shape"):
        lines.line_direction(np.zeros(5))


def test_line_through_origin_orth():
    L = lines.plucker_from_points(np.zeros(3), np.array([1.0, 2.0, 3.0]))
    U, W = lines.plucker_to_orth(L)
    assert abs(np.linalg.det(U) - 1) < 1e-12 and abs(W[0, 0]) < 1e-15
    np.testing.assert_allclose(lines.orth_to_plucker(U, W), L / np.linalg.norm(L), atol=1e-15)


@SETTINGS
@given(scenes(), st.lists(st.floats(-0.5, 0.5), min_size=4, max_size=4))
def test_orth_update(scene, delta):
    *_, Pw, Qw = scene
    U, W = lines.plucker_to_orth(lines.plucker_from_points(Pw, Qw))
    U0, W0 = lines.orth_update(U, W, np.zeros(4))
    np.testing.assert_allclose(U0, U, atol=1e-15)
    np.testing.assert_allclose(W0, W, atol=1e-15)
    delta = np.array(delta)
    U1, W1 = lines.orth_update(U, W, delta)
    np.testing.assert_allclose(U1, U @ se3.so3_exp(delta[:3]), atol=1e-14)
    c, s = np.cos(delta[3]), np.sin(delta[3])
    np.testing.assert_allclose(W1, W @ np.array([[c, -s], [s, c]]), atol=1e-14)
    # Batch form agrees row by row.
    Ub, Wb = lines.orth_update(np.stack([U, U]), np.stack([W, W]), np.stack([np.zeros(4), delta]))
    np.testing.assert_allclose(Ub[1], U1, atol=1e-14)
    np.testing.assert_allclose(Wb[0], W, atol=1e-15)


def test_batch_forms_match_single():
    rng = np.random.default_rng(3)
    P, Q = rng.normal(size=(5, 3)) + [0, 0, 10], rng.normal(size=(5, 3)) + [0, 0, 12]
    Lb = lines.plucker_from_points(P, Q)
    Ub, Wb = lines.plucker_to_orth(Lb)
    T = se3.exp(np.array([0.5, -0.2, 1.0, 0.1, 0.2, -0.3]))
    K = np.array([[700.0, 0, 600], [0, 650.0, 180], [0, 0, 1]])
    for i in range(5):
        Li = lines.plucker_from_points(P[i], Q[i])
        np.testing.assert_allclose(Lb[i], Li)
        np.testing.assert_allclose(lines.orth_to_plucker(Ub, Wb)[i], lines.orth_to_plucker(*lines.plucker_to_orth(Li)))
        np.testing.assert_allclose(lines.transform_line(T, Lb)[i], lines.transform_line(T, Li))
        np.testing.assert_allclose(lines.project_line(K, Lb)[i], lines.project_line(K, Li))
    # A stack of poses applied to one line.
    Ts = np.stack([T, np.eye(4)])
    np.testing.assert_allclose(lines.transform_line(Ts, Lb[0])[1], Lb[0])


# --- transformation and projection ------------------------------------------------------------------------------


@SETTINGS
@given(scenes())
def test_transform_line_matches_transformed_points(scene):
    K, T_cw, P, Q, Pw, Qw = scene
    L_c = lines.transform_line(T_cw, lines.plucker_from_points(Pw, Qw))
    # Rigid motions keep |d|, so even the scale agrees.
    np.testing.assert_allclose(L_c, lines.plucker_from_points(P, Q), atol=1e-9 * (1 + np.abs(L_c).max()))
    back = lines.transform_line(se3.inv(T_cw), L_c)
    np.testing.assert_allclose(back, lines.plucker_from_points(Pw, Qw), atol=1e-9 * (1 + np.abs(back).max()))


@SETTINGS
@given(scenes())
def test_projected_line_passes_through_projected_endpoints(scene):
    K, T_cw, P, Q, Pw, Qw = scene
    l = lines.project_line(K, lines.transform_line(T_cw, lines.plucker_from_points(Pw, Qw)))
    uv, _ = project(K, np.stack([P, Q]))
    through = np.cross(np.append(uv[0], 1.0), np.append(uv[1], 1.0))
    assert _same_line(l, through, 1e-9)
    # Equivalently fx fy K^-T m.
    m = lines.plucker_from_points(P, Q)[:3]
    assert _same_line(l, np.linalg.inv(K).T @ m, 1e-12)


@SETTINGS
@given(scenes(), st.floats(-20.0, 20.0), st.floats(-0.5, 1.5), st.floats(-0.5, 1.5))
def test_residual_zero_on_projection_and_offset_otherwise(scene, offset, a, b):
    K, T_cw, P, Q, Pw, Qw = scene
    l = lines.project_line(K, lines.transform_line(T_cw, lines.plucker_from_points(Pw, Qw)))
    seg = _segment(K, P, Q)
    np.testing.assert_allclose(lines.line_reprojection_residual(l, seg), [0, 0], atol=1e-7)
    # Any two points of the image line, shifted by `offset` px along its normal, are at +-offset.
    e1, e2 = seg[:2], seg[2:]
    n = l[:2] / np.linalg.norm(l[:2])
    moved = np.concatenate([e1 + a * (e2 - e1) + offset * n, e1 + b * (e2 - e1) + offset * n])
    np.testing.assert_allclose(lines.line_reprojection_residual(l, moved), [offset, offset], atol=1e-7)
    np.testing.assert_allclose(lines.line_reprojection_residual(-3.0 * l, moved), [-offset, -offset], atol=1e-7)
    batch = lines.line_reprojection_residual(np.stack([l, l]), np.stack([seg, moved]))
    np.testing.assert_allclose(batch, [[0, 0], [offset, offset]], atol=1e-7)


# --- distances and trimming ---------------------------------------------------------------------------------------


@SETTINGS
@given(scenes(), st.floats(-3.0, 3.0), st.floats(0.0, 5.0), st.floats(0.0, 2 * np.pi))
def test_point_line_distance(scene, t, offset, angle):
    *_, Pw, Qw = scene
    L = lines.plucker_from_points(Pw, Qw) * 2.5  # homogeneous: the scale must not matter
    d = lines.line_direction(L)
    on_line = Pw + t * (Qw - Pw)
    n1 = np.cross(d, [1.0, 0, 0] if abs(d[0]) < 0.9 else [0, 1.0, 0])
    n1 /= np.linalg.norm(n1)
    n2 = np.cross(d, n1)
    off = on_line + offset * (np.cos(angle) * n1 + np.sin(angle) * n2)
    dist = lines.point_line_distance(np.stack([Pw, Qw, on_line, off]), L)
    np.testing.assert_allclose(dist, [0, 0, 0, offset], atol=1e-9)


@SETTINGS
@given(scenes())
def test_trim_endpoints_recovers_true_endpoints(scene):
    K, T_cw, P, Q, Pw, Qw = scene
    L_c = lines.transform_line(T_cw, lines.plucker_from_points(Pw, Qw))
    ends = lines.trim_endpoints(K, L_c, _segment(K, P, Q))
    np.testing.assert_allclose(ends, np.stack([P, Q]), atol=1e-6 * max(np.abs(P).max(), np.abs(Q).max()))


@SETTINGS
@given(scenes(), st.floats(0.1, 0.9), st.floats(-3.0, 3.0))
def test_trim_endpoints_of_subsegment(scene, a, offset):
    """A sub-segment of the projection trims to the 3D points projecting onto its ends; moved off the image
    line by `offset` px, the trimmed points still lie on the 3D line, in front of the camera."""
    K, T_cw, P, Q, *_ = scene
    L_c = lines.plucker_from_points(P, Q)
    l = lines.project_line(K, L_c)
    seg = _segment(K, P, Q)
    sub = np.concatenate([seg[:2], seg[:2] + a * (seg[2:] - seg[:2])])
    ends = lines.trim_endpoints(K, L_c, sub)
    np.testing.assert_allclose(lines.point_line_distance(ends, L_c), [0, 0], atol=1e-9)
    np.testing.assert_allclose(project(K, ends)[0], sub.reshape(2, 2), atol=1e-6)
    n = l[:2] / np.linalg.norm(l[:2])
    moved = sub + np.tile(offset * n, 2)
    ends = lines.trim_endpoints(K, L_c, moved)
    np.testing.assert_allclose(lines.point_line_distance(ends, L_c), [0, 0], atol=1e-9)
    assert np.all(ends[:, 2] > 0)


def test_trim_endpoints_ray_parallel_to_line_is_nan():
    K = np.array([[700.0, 0, 600], [0, 650.0, 180], [0, 0, 1]])
    d = np.array([0.2, -0.1, 1.0])
    p = np.array([1.0, 0.5, 2.0])
    L = lines.plucker_from_points(p, p + d)
    vanishing = K @ d / d[2]
    seg = np.concatenate([vanishing[:2], project(K, p[None])[0][0]])
    ends = lines.trim_endpoints(K, L, seg)
    assert np.all(np.isnan(ends[0]))
    np.testing.assert_allclose(ends[1], p, atol=1e-9)


# --- Jacobians -----------------------------------------------------------------------------------------------------


def _random_observations(seed: int, n: int):
    """n world lines, n poses, and segments = exact projections perturbed by a few pixels."""
    rng = np.random.default_rng(seed)
    K = np.array([[718.0, 0, 607.0], [0, 690.0, 185.0], [0, 0, 1]])
    Ts, Us, Ws, segs = [], [], [], []
    while len(Ts) < n:
        uv = rng.uniform([20, 20], [WIDTH - 20, HEIGHT - 20], size=(2, 2))
        if np.linalg.norm(uv[0] - uv[1]) < 40:
            continue
        P, Q = backproject(K, uv, rng.uniform(3, 40, size=2))
        T_cw = se3.exp(rng.normal(size=6) * [5, 5, 5, 0.5, 0.5, 0.5])
        Pw, Qw = se3.transform_points(se3.inv(T_cw), np.stack([P, Q]))
        U, W = lines.plucker_to_orth(lines.plucker_from_points(Pw, Qw) * rng.choice([-1.0, 1.0]))
        Ts.append(T_cw), Us.append(U), Ws.append(W), segs.append(uv.reshape(4) + rng.normal(scale=3.0, size=4))
    return K, np.array(Ts), np.array(Us), np.array(Ws), np.array(segs)


def _numeric(f, x0: np.ndarray, h: float) -> np.ndarray:
    cols = []
    for i in range(x0.size):
        e = np.zeros_like(x0)
        e[i] = h
        cols.append((f(x0 + e) - f(x0 - e)) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_line_residual_jacobians_match_central_differences(seed):
    K, T, U, W, seg = _random_observations(seed, 25)
    r, J_pose, J_line = line_residuals_and_jacobians_batch(K, T, U, W, seg)
    assert r.shape == (25, 2) and J_pose.shape == (25, 2, 6) and J_line.shape == (25, 2, 4)
    for i in range(25):
        l = lines.project_line(K, lines.transform_line(T[i], lines.orth_to_plucker(U[i], W[i])))
        np.testing.assert_allclose(r[i], lines.line_reprojection_residual(l, seg[i]), atol=1e-9)

        def res_pose(xi, i=i):
            return line_residual_jacobians(K, se3.exp(xi) @ T[i], U[i], W[i], seg[i])[0]

        def res_line(delta, i=i):
            return line_residual_jacobians(K, T[i], *lines.orth_update(U[i], W[i], delta), seg[i])[0]

        num_pose = _numeric(res_pose, np.zeros(6), 1e-6)
        num_line = _numeric(res_line, np.zeros(4), 1e-6)
        scale_p, scale_l = 1 + np.abs(num_pose).max(), 1 + np.abs(num_line).max()
        np.testing.assert_allclose(J_pose[i], num_pose, atol=1e-6 * scale_p)
        np.testing.assert_allclose(J_line[i], num_line, atol=1e-6 * scale_l)
        r1, jp1, jl1 = line_residual_jacobians(K, T[i], U[i], W[i], seg[i])
        np.testing.assert_allclose(np.concatenate([jp1, jl1], axis=1), np.concatenate([J_pose[i], J_line[i]], axis=1))


def test_batch_residuals_accept_one_shared_pose():
    K, T, U, W, seg = _random_observations(7, 4)
    shared = line_residuals_and_jacobians_batch(K, T[0], U, W, seg)
    stacked = line_residuals_and_jacobians_batch(K, np.repeat(T[:1], 4, axis=0), U, W, seg)
    for a, b in zip(shared, stacked):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(PlvoError, match="segments"):
        line_residuals_and_jacobians_batch(K, T, U, W, seg[:, :3])


@pytest.mark.parametrize("seed", [0, 1])
def test_orth_plucker_jacobian_matches_central_differences(seed):
    _, _, U, W, _ = _random_observations(seed, 10)
    J = orth_plucker_jacobian(U, W)
    for i in range(10):
        num = _numeric(lambda dl, i=i: lines.orth_to_plucker(*lines.orth_update(U[i], W[i], dl)), np.zeros(4), 1e-6)
        np.testing.assert_allclose(J[i], num, atol=1e-8)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_point_line_distance_jacobian_matches_central_differences(seed):
    rng = np.random.default_rng(seed)
    _, _, U, W, _ = _random_observations(seed, 1)
    L = lines.orth_to_plucker(U[0], W[0])
    base = lines.closest_point_to_origin(L)
    pts = base + rng.normal(scale=3.0, size=(30, 3))
    dist, J = point_line_distance_and_jacobian(pts, U[0], W[0])
    np.testing.assert_allclose(dist, lines.point_line_distance(pts, L), atol=1e-12)

    def f(delta):
        return lines.point_line_distance(pts, lines.orth_to_plucker(*lines.orth_update(U[0], W[0], delta)))

    # Far lines make w2 small and the distance steep in delta[3]; h = 1e-7 keeps the truncation error low.
    np.testing.assert_allclose(J, _numeric(f, np.zeros(4), 1e-7), atol=1e-7 * (1 + np.abs(J).max()))
    on_line = point_line_distance_and_jacobian(base[None], U[0], W[0])
    assert on_line[0][0] < 1e-9 and np.all(np.isfinite(on_line[1]))

