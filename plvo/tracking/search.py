"""Where landmarks should appear: the motion prediction for the 2D-2D matching, and re-finding line landmarks by
projection (the line counterpart of map.search_by_projection).

Why: the paper's 2D-2D line criteria (midpoint within 5 px of the predicted segment, length ratio < 0.1) assume
LSD finds the same extent of an edge in consecutive frames. It does not: on the real KITTI frames the true
correspondences (both endpoints within 2 px of the projected 3D line) have a median midpoint offset of ~18 px and a
length ratio of ~0.17, so only a quarter of them pass and ~5 line landmarks a frame are tracked. Here a landmark's
3D segment is projected with the solved pose and a current segment matches it when it lies *on* the projected
line (both endpoints close to it, same direction), overlaps the projected extent, and has the smallest LBD
distance; the extent of the detection does not matter.
"""

from __future__ import annotations

import numpy as np

from plvo.geometry import se3
from plvo.geometry.camera import pixel_rays, project
from plvo.tracking.association import hamming
from plvo.tracking.keyframes import closest_points_on_lines
from plvo.tracking.map import LandmarkMap

NEAR_M = 0.5  # 3D segments are clipped to this depth before projection


def _rotation_homography(K: np.ndarray, T_world_prev: np.ndarray, T_world_cur: np.ndarray) -> np.ndarray:
    R = (se3.inv(T_world_cur) @ T_world_prev)[:3, :3]
    return K @ R @ np.linalg.inv(K)


def predict_points(K: np.ndarray, lmap: LandmarkMap, T_world_prev: np.ndarray, keypoints: np.ndarray,
                   landmark: np.ndarray, T_pred: np.ndarray) -> np.ndarray:
    """Previous keypoints (N,2) with their landmark ids (N,) (-1 none), poses (4,4) -> (N,2) predicted pixels:
    landmarks projected with the predicted pose, the rest moved by the predicted rotation alone (at infinity)."""
    uv = np.asarray(keypoints, dtype=float).reshape(-1, 2)
    H = _rotation_homography(K, T_world_prev, T_pred)
    hom = np.c_[uv, np.ones(len(uv))] @ H.T
    pred = hom[:, :2] / hom[:, 2:3]
    has = landmark >= 0
    if has.any():
        pw = lmap.point_positions(landmark[has])
        puv, z = project(K, se3.transform_points(se3.inv(T_pred), pw))
        ok = np.isfinite(puv).all(axis=1) & (z > 0)
        pred[np.flatnonzero(has)[ok]] = puv[ok]
    return pred


def predict_segments(K: np.ndarray, lmap: LandmarkMap, T_world_prev: np.ndarray, segments: np.ndarray,
                     landmark: np.ndarray, T_pred: np.ndarray) -> np.ndarray:
    """Previous segments (M,4) with their landmark ids (M,), poses (4,4) -> (M,4) predicted segments: the ends
    lifted onto their 3D line landmark (closest points to the end rays) and projected with the predicted pose; by
    rotation alone without a landmark."""
    seg = np.asarray(segments, dtype=float).reshape(-1, 4)
    H = _rotation_homography(K, T_world_prev, T_pred)
    ends = np.c_[seg.reshape(-1, 2), np.ones(2 * len(seg))] @ H.T
    pred = (ends[:, :2] / ends[:, 2:3]).reshape(-1, 4)
    has = landmark >= 0
    if has.any():
        Lw = lmap.line_endpoints(landmark[has])
        T_prev_world = se3.inv(T_world_prev)
        lifted = closest_points_on_lines(
            se3.transform_points(T_prev_world, Lw[:, 0]), se3.transform_points(T_prev_world, Lw[:, 1]),
            pixel_rays(K, seg[has].reshape(-1, 2)).reshape(-1, 2, 3))
        puv, z = project(K, se3.transform_points(se3.inv(T_pred) @ T_world_prev, lifted.reshape(-1, 3)))
        puv = puv.reshape(-1, 4)
        ok = np.isfinite(puv).all(axis=1) & (z.reshape(-1, 2) > 0).all(axis=1)
        pred[np.flatnonzero(has)[ok]] = puv[ok]
    return pred


def project_segments(K: np.ndarray, T_world_cam: np.ndarray, endpoints: np.ndarray, width: int, height: int
                     ) -> np.ndarray:
    """(L,2,3) world endpoints, camera pose (4,4) -> (L,4) projected segments px; NaN rows when the segment is
    behind the camera, degenerate, or misses the image."""
    out = np.full((len(endpoints), 4), np.nan)
    if len(endpoints) == 0:
        return out
    T_cw = se3.inv(T_world_cam)
    A = se3.transform_points(T_cw, endpoints[:, 0])
    B = se3.transform_points(T_cw, endpoints[:, 1])
    za, zb = A[:, 2], B[:, 2]
    ok = np.isfinite(A).all(axis=1) & np.isfinite(B).all(axis=1) & ((za > NEAR_M) | (zb > NEAR_M))
    # Clip the part behind the near plane (a segment passing beside the camera).
    with np.errstate(divide="ignore", invalid="ignore"):
        A_c = np.where((za < NEAR_M)[:, None], A + ((NEAR_M - za) / (zb - za))[:, None] * (B - A), A)
        B_c = np.where((zb < NEAR_M)[:, None], B + ((NEAR_M - zb) / (za - zb))[:, None] * (A - B), B)
        f = np.diag(K)[:2]
        ua = A_c[:, :2] / A_c[:, 2:3] * f + K[:2, 2]
        ub = B_c[:, :2] / B_c[:, 2:3] * f + K[:2, 2]
    seg = np.c_[ua, ub]
    ok &= np.isfinite(seg).all(axis=1) & (np.linalg.norm(ub - ua, axis=1) > 1.0)
    lo = np.minimum(ua, ub)
    hi = np.maximum(ua, ub)
    ok &= (hi[:, 0] >= 0) & (lo[:, 0] < width) & (hi[:, 1] >= 0) & (lo[:, 1] < height)
    out[ok] = seg[ok]
    return out


def search_lines_by_projection(proj: np.ndarray, desc_landmarks: np.ndarray, segments: np.ndarray,
                               descriptors: np.ndarray, free: np.ndarray, max_dist_px: float, max_angle_deg: float,
                               min_overlap: float, max_lbd: int) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks projected to (L,4) segments (NaN rows skipped) with (L,32) LBD, a frame's (M,4) segments, (M,32)
    LBD and (M,) bool free -> (k,) landmark rows and (k,) segment indices, one-to-one.

    A pair is a candidate when the segment's endpoints are both within max_dist_px of the projected infinite
    line, its direction within max_angle_deg of the projection's (directed: LSD orients by gradient polarity),
    and its extent along the line overlaps the projected extent by min_overlap of the shorter of the two.
    Each landmark takes the candidate with the smallest LBD distance (<= max_lbd); conflicts go to the smaller.
    """
    rows_ok = np.flatnonzero(np.isfinite(proj).all(axis=1))
    cols = np.flatnonzero(free)
    empty = np.zeros(0, np.int64)
    if len(rows_ok) == 0 or len(cols) == 0:
        return empty, empty
    P, S = proj[rows_ok], segments[cols]
    d = P[:, 2:] - P[:, :2]
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    n = np.c_[-u[:, 1], u[:, 0]]
    rel1 = S[None, :, :2] - P[:, None, :2]  # (R,C,2)
    rel2 = S[None, :, 2:] - P[:, None, :2]
    dist = np.maximum(np.abs(np.einsum("rcx,rx->rc", rel1, n)), np.abs(np.einsum("rcx,rx->rc", rel2, n)))
    sd = S[:, 2:] - S[:, :2]
    s_len = np.linalg.norm(sd, axis=1)
    cos = (u @ sd.T) / np.maximum(s_len[None, :], 1e-9)
    t1, t2 = np.einsum("rcx,rx->rc", rel1, u), np.einsum("rcx,rx->rc", rel2, u)
    overlap = np.minimum(np.maximum(t1, t2), length[:, None]) - np.maximum(np.minimum(t1, t2), 0.0)
    shorter = np.minimum(length[:, None], s_len[None, :])
    cand = (dist < max_dist_px) & (cos > np.cos(np.radians(max_angle_deg))) & (overlap > min_overlap * shorter)
    r, c = np.nonzero(cand)
    if len(r) == 0:
        return empty, empty
    rows, segs = rows_ok[r], cols[c]
    lbd = hamming(desc_landmarks[rows], descriptors[segs])
    keep = lbd <= max_lbd
    rows, segs, lbd = rows[keep], segs[keep], lbd[keep]
    return _one_to_one(rows, segs, lbd)


def _one_to_one(rows: np.ndarray, cols: np.ndarray, cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Greedy by increasing cost: each row and each column used once."""
    order = np.argsort(cost, kind="stable")
    rows, cols = rows[order], cols[order]
    _, first = np.unique(rows, return_index=True)
    rows, cols = rows[np.sort(first)], cols[np.sort(first)]
    _, first = np.unique(cols, return_index=True)
    first = np.sort(first)
    return rows[first], cols[first]
