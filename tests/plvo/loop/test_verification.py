"""Geometric verification: a true revisit of a textured wall is accepted with the right relative pose, a false
candidate is rejected with its reason."""

from __future__ import annotations

import numpy as np
import pytest
from loop_scenes import K, planar_keyframe, planar_view, scene_image

from plvo.config import LoopConfig
from plvo.geometry import se3
from plvo.loop.verification import match_binary, verify

DEPTH = 10.0


@pytest.fixture(scope="module")
def keyframes():
    base = scene_image(7)
    T_q_c = se3.exp(np.array([0.6, 0.05, 0.7, 0.01, -0.04, 0.005]))  # query camera 0.9 m from the candidate
    cand = planar_keyframe(3, base, DEPTH)
    query = planar_keyframe(40, planar_view(base, T_q_c, DEPTH), None)
    other = planar_keyframe(5, scene_image(8), DEPTH)
    return cand, query, other, se3.inv(T_q_c)


def test_true_revisit_is_accepted_with_the_relative_pose(keyframes):
    cand, query, _, T_c_q = keyframes
    v = verify(query, cand, K, LoopConfig(min_off_plane=0))  # the scene is one wall: no off-plane check
    assert v.accepted, v.reason
    assert v.n_point_inliers >= LoopConfig().min_inliers
    assert v.n_line_inliers > 0  # the LBD matches take part (PnL)
    dT = se3.inv(T_c_q) @ v.T_cand_query
    assert np.linalg.norm(dT[:3, 3]) < 0.05  # measured ~1 cm
    assert np.degrees(se3.rotation_angle(dT)) < 0.2
    assert not v.registered  # no scans given


def test_support_on_a_single_plane_is_rejected(keyframes):
    cand, query, _, _ = keyframes
    v = verify(query, cand, K, LoopConfig())  # default: 10 inliers must lie off the dominant plane
    assert not v.accepted and "one plane" in v.reason


def test_false_candidate_is_rejected_with_a_reason(keyframes):
    _, query, other, _ = keyframes
    v = verify(query, other, K, LoopConfig())
    assert not v.accepted
    assert "matches" in v.reason or "inliers" in v.reason
    np.testing.assert_array_equal(v.T_cand_query, np.eye(4))


def test_candidate_without_depth_is_rejected(keyframes):
    cand, query, _, _ = keyframes
    v = verify(cand, query, K, LoopConfig())  # swapped: the "candidate" now has no 3D points
    assert not v.accepted and "with depth" in v.reason


def test_match_binary_is_mutual_and_bounded():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    b = a[::-1].copy()
    pairs = match_binary(a, b, 0.8, 64)
    assert len(pairs) == 200
    np.testing.assert_array_equal(pairs[:, 1], 199 - pairs[:, 0])
    assert len(match_binary(a, rng.integers(0, 256, (200, 32), dtype=np.uint8), 0.8, 64)) == 0
