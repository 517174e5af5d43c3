"""LSD repair and matching on the synthetic town, against its ground-truth 3D edges, depth and poses."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from features_eval import (
    edge_precision_recall,
    flow_predicted_segments,
    project_visible_edges,
    read_kitti_poses,
    read_p0,
)

from plvo.config import LineConfig, MatchingConfig, OrbConfig
from plvo.features.extract import extract_features
from plvo.features.lines import detect_lsd, repair_segments, segment_lengths
from plvo.features.matching import match_lines, match_points

FRAMES = (0, 5, 10, 15)


@pytest.fixture(scope="module")
def town(synth_seq):
    seq = synth_seq / "sequences" / "00"
    K = read_p0(seq / "calib.txt")
    T = read_kitti_poses(synth_seq / "poses" / "00.txt")
    edges = np.load(seq / "gt" / "edges.npy")

    def frame(i):
        img = cv2.imread(str(seq / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        depth = np.load(seq / "gt" / "depth" / f"{i:06d}.npy")
        return img, depth

    return K, T, edges, frame


# The repaired segments' precision and recall at least, by LSD scale. Measured on FRAMES of the 20-frame seed-0
# town: at 0.5 precision 0.442 and recall 0.400, at 0.35 (the default) 0.389 and 0.369 (LSD's long segments alone:
# 0.447 / 0.351 and 0.430 / 0.350). A coarser LSD places a segment less exactly (to a fraction of its pixel, 2.9 image
# pixels at 0.35), and more of its segments then miss the 2 px the measure allows: the price of the default's speed
# (docs/results/faster_config/).
REPAIR_FLOORS = {0.5: (0.40, 0.35), 0.35: (0.37, 0.35)}


@pytest.mark.parametrize("lsd_scale", sorted(REPAIR_FLOORS))
def test_repair_against_true_edges(town, lsd_scale):
    """Precision: share of segments lying on a visible true edge; recall: share of visible true edges (>= 50 px)
    covered. Measured on 6 frames of a seed-0 town at LSD 0.5: raw LSD (>= 8 px, what enters the repair) precision
    0.19, mean length 35 px; raw LSD >= 50 px precision 0.574, recall 0.437, mean 92 px; repaired precision 0.544,
    recall 0.478, mean 100 px. The repair's new segments (chains of short pieces) include straight image
    edges the town's edge list lacks (shadows, foliage), hence the small drop against the filtered raw set."""
    assert LineConfig().lsd_scale in REPAIR_FLOORS  # the default's lines are held to a floor of their own
    K, T, edges, frame = town
    cfg = dataclasses.replace(LineConfig(), lsd_scale=lsd_scale)
    res = {"raw": [], "raw50": [], "rep": []}
    for i in FRAMES:
        img, depth = frame(i)
        visible = project_visible_edges(edges, T[i], K, depth)
        raw = detect_lsd(img, cfg)
        rep = repair_segments(raw, cfg)
        for key, seg in (("raw", raw[segment_lengths(raw) >= cfg.raw_min_length_px]),
                         ("raw50", raw[segment_lengths(raw) >= cfg.min_length_px]), ("rep", rep.segments)):
            p, r = edge_precision_recall(seg, visible)
            res[key].append((p, r, segment_lengths(seg).mean()))
    raw, raw50, rep = (np.nanmean(res[k], axis=0) for k in ("raw", "raw50", "rep"))
    assert rep[2] > raw50[2] > raw[2]  # mean segment length
    assert rep[0] >= raw[0]  # precision against what LSD returns
    assert rep[0] >= raw50[0] - 0.05  # and against LSD's long segments alone
    assert rep[1] >= raw50[1]  # recall of the long segments
    precision, recall = REPAIR_FLOORS[lsd_scale]
    assert rep[0] > precision and rep[1] > recall, (rep[0], rep[1])


def move_segments(seg: np.ndarray, depth: np.ndarray, K: np.ndarray, T10: np.ndarray) -> np.ndarray:
    """(M,4) segments of frame 0 moved into frame 1 with the exact depth: interior samples back-projected with
    the nearest depth of a 3x3 block (the edge's own, foreground side), moved, projected; NaN where a sample
    lies on the sky or the samples spread over > 5 % in depth relative to a line fit."""
    zmin = cv2.erode(np.where(np.isfinite(depth), depth, 1e9).astype(np.float32), np.ones((3, 3), np.uint8))
    t = np.linspace(0.1, 0.9, 5)
    out = np.full((len(seg), 4), np.nan)
    Ki = np.linalg.inv(K)
    for k, s in enumerate(seg):
        uv = s[:2] + t[:, None] * (s[2:] - s[:2])
        z = zmin[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
        if np.any(z > 1e8):
            continue
        X = (np.c_[uv, np.ones(5)] @ Ki.T) * z[:, None]
        X1 = X @ T10[:3, :3].T + T10[:3, 3]
        if np.any(X1[:, 2] <= 0.1):
            continue
        p = X1[:, :2] / X1[:, 2:] @ K[:2, :2].T + K[:2, 2]
        c = p.mean(axis=0)
        u = np.linalg.svd(p - c)[2][0]
        if np.max(np.abs((p - c) @ np.array([-u[1], u[0]]))) > 1.0:  # samples on different surfaces
            continue
        out[k] = np.r_[p[0], p[-1]]
    return out


def block_depths(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.where(np.isfinite(depth), depth, np.nan).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    return cv2.erode(np.nan_to_num(d, nan=1e9), k), cv2.dilate(np.nan_to_num(d, nan=-1.0), k)


def reprojection(uv0, uv1, depth, K, T10) -> np.ndarray:
    """(N,) px error of uv1 against uv0 moved with the depth map and T10; NaN where the depth is invalid."""
    z = depth[np.rint(uv0[:, 1]).astype(int), np.rint(uv0[:, 0]).astype(int)].astype(np.float64)
    z[(z <= 0) | (z > 1e8)] = np.nan
    X1 = (np.c_[uv0, np.ones(len(uv0))] @ np.linalg.inv(K).T * z[:, None]) @ T10[:3, :3].T + T10[:3, 3]
    uv = X1[:, :2] / X1[:, 2:] @ K[:2, :2].T + K[:2, 2]
    return np.linalg.norm(uv - uv1, axis=1)


def perpendicular(seg: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(M,) larger perpendicular distance of seg's endpoints from ref's infinite line, row by row."""
    d = ref[:, 2:] - ref[:, :2]
    n = np.c_[-d[:, 1], d[:, 0]] / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    return np.maximum(np.abs(np.einsum("ij,ij->i", seg[:, :2] - ref[:, :2], n)),
                      np.abs(np.einsum("ij,ij->i", seg[:, 2:] - ref[:, :2], n)))


def test_matching_on_consecutive_town_frames(town):
    """Point matches judged with the exact depth and poses (reprojection under 2 px at the point's level); line
    matches judged by the current segment lying within 2 px of the previous one moved with exact depth."""
    K, T, edges, frame = town
    cfg = MatchingConfig()
    p_ok = p_n = q_ok = q_n = l_ok = l_n = l_judged = 0
    for i in FRAMES:
        (img0, depth0), (img1, _) = frame(i), frame(i + 1)
        a = extract_features(img0, OrbConfig(), LineConfig())
        b = extract_features(img1, OrbConfig(), LineConfig())
        m = match_points(a, b, cfg)
        uv0 = a.keypoints[m.pairs[:, 0]]
        T10 = np.linalg.inv(T[i + 1]) @ T[i]
        # corners sit on depth edges: accept either side's depth of a 3x3 block
        errs = [reprojection(uv0, b.keypoints[m.pairs[:, 1]], blk, K, T10) for blk in block_depths(depth0)]
        err = np.fmin(*errs)
        finite = np.isfinite(err)
        tol = 2.0 * OrbConfig().scale_factor ** a.kp_octave[m.pairs[:, 0]]
        p_ok += np.sum(err[finite] < tol[finite])
        p_n += finite.sum()

        # with a prediction (here from the exact depth, as the tracker's from its landmarks) and the window
        zfg = block_depths(depth0)[0]
        z = zfg[np.rint(a.keypoints[:, 1]).astype(int), np.rint(a.keypoints[:, 0]).astype(int)].astype(float)
        z[z > 1e8] = np.nan
        X1 = (np.c_[a.keypoints, np.ones(a.n_points)] @ np.linalg.inv(K).T * z[:, None]) @ T10[:3, :3].T + T10[:3, 3]
        puv = X1[:, :2] / X1[:, 2:] @ K[:2, :2].T + K[:2, 2]
        mp = match_points(a, b, cfg, puv)
        e2 = np.fmin(*[reprojection(a.keypoints[mp.pairs[:, 0]], b.keypoints[mp.pairs[:, 1]], blk, K, T10)
                       for blk in block_depths(depth0)])
        f2 = np.isfinite(e2)
        tol2 = 2.0 * OrbConfig().scale_factor ** a.kp_octave[mp.pairs[:, 0]]
        q_ok, q_n = q_ok + np.sum(e2[f2] < tol2[f2]), q_n + f2.sum()

        pred = flow_predicted_segments(a.keypoints, b.keypoints, m.pairs, a.segments)
        ml = match_lines(a, b, cfg, pred)
        moved = move_segments(a.segments[ml.pairs[:, 0]], depth0, K, T10)
        s1 = b.segments[ml.pairs[:, 1]]
        judged = np.all(np.isfinite(moved), axis=1)
        ok = judged & (perpendicular(s1, moved) < 2.0)
        l_ok, l_judged, l_n = l_ok + ok.sum(), l_judged + judged.sum(), l_n + len(ml)
    # measured (seed-0 town, frames 0/5/10/15 -> +1): points 864/1003 = 0.861 unpredicted, 963/1082 = 0.890 with
    # the exact-depth prediction; lines 75/75 judged right, ~19 a pair
    assert p_n / len(FRAMES) > 150 and p_ok / p_n > 0.8
    assert q_n / len(FRAMES) > 150 and q_ok / q_n > 0.85
    assert l_n / len(FRAMES) >= 10
    assert l_judged >= 20 and l_ok / l_judged > 0.9
