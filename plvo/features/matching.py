"""2D-2D matching between consecutive frames (paper, II-C).

Points: Hamming distance of ORB descriptors, Lowe's ratio test, mutual best check; with a prediction of where
each previous point moved, only current points within `point_window_px` of it are candidates.

Lines: Hamming distance of LBD descriptors among the pairs that pass the paper's geometric criteria: angle
difference < `line_angle_deg`, length difference ratio |l1 - l2| / max(l1, l2) < `line_length_ratio`, midpoint
distance < `line_midpoint_px`. The 5 px midpoint bound of the paper only makes sense after the motion: the
criteria compare the current segment with the *predicted* previous segment (the tracker projects the segment's
3D landmark with the constant-velocity pose). Rows without a prediction (NaN, or no prediction at all) are
compared with the previous segment as it was, within `line_midpoint_px_unpredicted` and the paper's angle and
length bounds. The best candidate by LBD distance must be under `line_max_lbd` and be the mutual best.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from plvo.config import MatchingConfig
from plvo.types import FeatureMatches, FeatureSet, Matches

_BIG = np.iinfo(np.int32).max


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,M) int32 Hamming distances between (N,32) and (M,32) uint8 binary descriptors.

    As a matrix product of +-1 bit vectors (dot = bits - 2 * hamming): this OpenCV build's Hamming norm has no
    popcount (baseline SSE3) and is ~3x slower than BLAS here.
    """
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)), np.int32)
    bits = a.shape[1] * 8
    sa = np.unpackbits(a, axis=1).astype(np.float32) * 2 - 1
    sb = np.unpackbits(b, axis=1).astype(np.float32) * 2 - 1
    return np.rint((bits - sa @ sb.T) * 0.5).astype(np.int32)


def hamming_pairs(a: np.ndarray, b: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(P,) int32 Hamming distances between rows a[i] and b[j] of (N,32) / (M,32) uint8 descriptors."""
    x = np.ascontiguousarray(a).view(np.uint64)[i] ^ np.ascontiguousarray(b).view(np.uint64)[j]
    return np.bitwise_count(x).sum(axis=1, dtype=np.int32)


def _empty() -> Matches:
    return Matches(np.zeros((0, 2), np.int64), np.zeros(0))


def _best_mutual(dist: np.ndarray, max_dist: float, ratio: float | None, mutual: bool) -> Matches:
    """Row-wise best entries of a masked (N,M) distance matrix (_BIG = not a candidate), filtered."""
    n, m = dist.shape
    if n == 0 or m == 0:
        return _empty()
    rows = np.arange(n)
    best = np.argmin(dist, axis=1)
    d1 = dist[rows, best]
    ok = d1 <= max_dist
    if ratio is not None and m > 1:
        d2 = np.partition(dist, 1, axis=1)[:, 1]
        # a lone candidate in the window passes; otherwise Lowe's test
        ok &= (d2 == _BIG) | (d1 < ratio * d2)
    if mutual:
        ok &= np.argmin(dist, axis=0)[best] == rows
    sel = np.flatnonzero(ok)
    return Matches(np.stack([sel, best[sel]], axis=1).astype(np.int64), d1[sel].astype(np.float64))


def _select_sparse(
    i: np.ndarray, j: np.ndarray, d: np.ndarray, max_dist: float, ratio: float | None, mutual: bool
) -> Matches:
    """Matches among candidate pairs (i, j) with distances d: best of its row, ratio test, best of its column."""
    if len(i) == 0:
        return _empty()
    order = np.lexsort((d, i))
    i, j, d = i[order], j[order], d[order]
    first = np.r_[True, i[1:] != i[:-1]]
    idx = np.flatnonzero(first)
    nxt = idx + 1
    has2 = np.zeros(len(idx), bool)
    has2[nxt < len(i)] = ~first[nxt[nxt < len(i)]]
    d2 = np.full(len(idx), np.inf)
    d2[has2] = d[nxt[has2]]
    ok = d[idx] <= max_dist
    if ratio is not None:
        ok &= d[idx] < ratio * d2  # a lone candidate in its window passes (d2 = inf)
    bi, bj, bd = i[idx], j[idx], d[idx]
    if mutual:
        col_order = np.lexsort((d, j))
        col_first = col_order[np.r_[True, j[col_order][1:] != j[col_order][:-1]]]
        best_row_of_col = np.full(int(j.max()) + 1, -1, dtype=np.int64)
        best_row_of_col[j[col_first]] = i[col_first]
        ok &= best_row_of_col[bj] == bi
    return Matches(np.stack([bi[ok], bj[ok]], axis=1).astype(np.int64), bd[ok].astype(np.float64))


def match_points(
    prev: FeatureSet, cur: FeatureSet, cfg: MatchingConfig, predicted_uv: np.ndarray | None = None
) -> Matches:
    """ORB matches prev -> cur; predicted_uv: (N_prev,2) where each prev point should be in cur (NaN: anywhere).

    With a prediction for every row only the current points within point_window_px are compared (a k-d tree
    gives the pairs), which keeps matching within its budget; otherwise the full distance matrix is computed and
    the window applied to the predicted rows.
    """
    if prev.n_points == 0 or cur.n_points == 0:
        return _empty()
    if predicted_uv is None:
        dist = hamming_matrix(prev.descriptors, cur.descriptors)
        return _best_mutual(dist, cfg.point_max_hamming, cfg.point_ratio, cfg.point_mutual)
    pred = np.asarray(predicted_uv, dtype=np.float64).reshape(-1, 2)
    known = np.all(np.isfinite(pred), axis=1)
    if not known.all():  # rows without a prediction search everywhere: dense, with the window on the others
        dist = hamming_matrix(prev.descriptors, cur.descriptors)
        d2 = ((pred[:, None, :] - cur.keypoints[None, :, :]) ** 2).sum(axis=2)
        dist[known[:, None] & ~(d2 <= cfg.point_window_px**2)] = _BIG
        return _best_mutual(dist, cfg.point_max_hamming, cfg.point_ratio, cfg.point_mutual)
    pairs = cKDTree(pred).query_ball_tree(cKDTree(cur.keypoints), cfg.point_window_px)
    counts = np.fromiter((len(p) for p in pairs), dtype=np.intp, count=len(pairs))
    i = np.repeat(np.arange(len(pred)), counts)
    j = np.fromiter(itertools.chain.from_iterable(pairs), dtype=np.intp, count=int(counts.sum()))
    d = hamming_pairs(prev.descriptors, cur.descriptors, i, j)
    return _select_sparse(i, j, d, cfg.point_max_hamming, cfg.point_ratio, cfg.point_mutual)


def _seg_geometry(seg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = seg[:, 2:] - seg[:, :2]
    return np.arctan2(d[:, 1], d[:, 0]), np.hypot(d[:, 0], d[:, 1]), (seg[:, :2] + seg[:, 2:]) / 2


def line_geometry(ref_seg: np.ndarray, cur_seg: np.ndarray, cfg: MatchingConfig) -> tuple[np.ndarray, np.ndarray]:
    """For (M,4) reference and (K,4) current segments: (M,K) bool angle and length-ratio test, (M,K) midpoint px."""
    ta, la, ma = _seg_geometry(ref_seg)
    tb, lb, mb = _seg_geometry(cur_seg)
    # directed: LSD orients a segment by its gradient's polarity, and LBD's band follows that orientation
    dth = np.abs(ta[:, None] - tb[None, :]) % (2 * np.pi)
    dth = np.minimum(dth, 2 * np.pi - dth)
    lr = np.abs(la[:, None] - lb[None, :]) / np.maximum(np.maximum(la[:, None], lb[None, :]), 1e-9)
    dm = np.hypot(ma[:, None, 0] - mb[None, :, 0], ma[:, None, 1] - mb[None, :, 1])
    return (dth < np.radians(cfg.line_angle_deg)) & (lr < cfg.line_length_ratio), dm


def match_lines(
    prev: FeatureSet, cur: FeatureSet, cfg: MatchingConfig, predicted_segments: np.ndarray | None = None
) -> Matches:
    """LBD matches prev -> cur under the geometric criteria; predicted_segments (M_prev,4), NaN rows = none."""
    if prev.n_lines == 0 or cur.n_lines == 0:
        return _empty()
    ref = np.array(prev.segments, dtype=np.float64, copy=True)
    bound = np.full(len(ref), cfg.line_midpoint_px_unpredicted)
    if predicted_segments is not None:
        pred = np.asarray(predicted_segments, dtype=np.float64).reshape(-1, 4)
        has = np.all(np.isfinite(pred), axis=1)
        ref[has] = pred[has]
        bound[has] = cfg.line_midpoint_px
    shape_ok, dm = line_geometry(ref, cur.segments, cfg)
    ok = shape_ok & (dm < bound[:, None])
    i, j = np.nonzero(ok)
    d = hamming_pairs(prev.line_descriptors, cur.line_descriptors, i, j)
    return _select_sparse(i, j, d, cfg.line_max_lbd, cfg.line_ratio if cfg.line_ratio < 1.0 else None, True)


def match_features(
    prev: FeatureSet,
    cur: FeatureSet,
    cfg: MatchingConfig,
    predicted_uv: np.ndarray | None = None,
    predicted_segments: np.ndarray | None = None,
) -> FeatureMatches:
    """Point and line matches prev -> cur (see match_points and match_lines)."""
    return FeatureMatches(
        points=match_points(prev, cur, cfg, predicted_uv),
        lines=match_lines(prev, cur, cfg, predicted_segments),
    )
