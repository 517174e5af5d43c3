"""LSD segments and the paper's repair of them (II-A): chain broken collinear pieces, merge double edges.

The repair works on groups of raw LSD segments. Each pass finds, among the current segments, the pairs that may
be combined, keeps the pairs that are each other's best partner (so the chosen pairs are disjoint and the pass is
one vectorised step), joins them, and refits every group's segment from all its raw members. Passes repeat until
no pair is left or `max_iterations` is reached.

A pair (A longer, B shorter, angle between them under the threshold) may be combined when
- chaining: both endpoints of B lie within `chain_offset_px` of A's supporting line and the gap between them
  along that line is under `chain_endpoint_px` (one endpoint near the other's), or
- merging: both endpoints of B lie within `merge_distance_px` of A's line and B overlaps A along the line by at
  least `merge_overlap` of B's length (both endpoints near the other's: a double edge of a thin structure).
The three distances are image pixels for LSD at 0.5 or finer; below that they grow with LSD's pixel
(`repair_tolerances`).
A group's segment is the total-least-squares line through its members' endpoints, each weighted by its member's
length, spanning the members' extent, oriented like its longest member (LSD's orientation follows the gradient's
polarity, which LBD needs).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from dataclasses import dataclass

import cv2
import numpy as np

from plvo.config import LineConfig
from plvo.errors import PlvoError

log = logging.getLogger(__name__)
_local = threading.local()


@dataclass(frozen=True)
class LineSegments:
    """raw: (R,4) LSD segments; segments: (M,4) repaired, longest first; sources: M arrays of raw indices."""

    raw: np.ndarray
    segments: np.ndarray
    sources: tuple[np.ndarray, ...]
    iterations: int


def _detector(refine: bool, scale: float) -> cv2.LineSegmentDetector:
    """This thread's LSD for (refine, scale). OpenCV's detector keeps per-image buffers, so one per thread; kept
    between images because a reused one is ~1.5 ms of a frame's 13 cheaper (its buffers are not allocated and
    faulted in again) and finds the same segments (tests/plvo/features/test_lines.py)."""
    cache = getattr(_local, "lsd", None)
    if cache is None:
        cache = _local.lsd = {}
    key = (bool(refine), float(scale))
    if key not in cache:
        cache[key] = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD if refine else cv2.LSD_REFINE_NONE, scale)
    return cache[key]


def detect_lsd(image: np.ndarray, cfg: LineConfig) -> np.ndarray:
    """(R,4) LSD segments x1,y1,x2,y2 of a (H,W) uint8 image, pixel centres at integer coordinates."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise PlvoError(f"LSD: image must be (H,W) uint8, got shape {image.shape} dtype {image.dtype}")
    lines = _detector(cfg.lsd_refine, cfg.lsd_scale).detect(image)[0]
    if lines is None:
        return np.zeros((0, 4))
    # OpenCV maps a coarse pixel's centre to the fine grid as if both had corners at 0: shift to centres
    shift = 0.5 * (1.0 / cfg.lsd_scale - 1.0)
    return lines.reshape(-1, 4).astype(np.float64) + shift


def segment_lengths(seg: np.ndarray) -> np.ndarray:
    """(N,) lengths of (N,4) segments."""
    return np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])


def _candidate_pairs(seg: np.ndarray, max_angle: float, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j), i != j, whose undirected angles differ by < max_angle and whose boxes, grown by reach, meet.

    Sorting by angle and taking a window per segment keeps this near O(n log n + pairs), not O(n^2).
    """
    n = len(seg)
    theta = np.arctan2(seg[:, 3] - seg[:, 1], seg[:, 2] - seg[:, 0]) % np.pi
    order = np.argsort(theta)
    ts = theta[order]
    ext = np.r_[ts, ts + np.pi]  # wrap-around: angle 179 deg is near 1 deg
    hi = np.searchsorted(ext, ts + max_angle, side="left")
    counts = np.minimum(hi - np.arange(n) - 1, n - 1)
    counts = np.maximum(counts, 0)
    a = np.repeat(np.arange(n), counts)
    offs = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    b = (a + 1 + offs) % n
    i, j = order[a], order[b]
    # separate x and y arrays: numpy reductions over a length-2 axis are slow
    x_lo = np.minimum(seg[:, 0], seg[:, 2]) - reach
    x_up = np.maximum(seg[:, 0], seg[:, 2]) + reach
    y_lo = np.minimum(seg[:, 1], seg[:, 3]) - reach
    y_up = np.maximum(seg[:, 1], seg[:, 3]) + reach
    meet = (x_lo[i] <= x_up[j]) & (x_lo[j] <= x_up[i]) & (y_lo[i] <= y_up[j]) & (y_lo[j] <= y_up[i])
    return i[meet], j[meet]


def _pair_costs(seg: np.ndarray, i: np.ndarray, j: np.ndarray, cfg: LineConfig) -> tuple[np.ndarray, np.ndarray]:
    """For pairs (i, j): may they be combined (chain or merge), and at what cost (px, lower is better)."""
    length = segment_lengths(seg)
    swap = length[j] > length[i]
    a, b = np.where(swap, j, i), np.where(swap, i, j)  # a: the longer
    pa, qa = seg[a, :2], seg[a, 2:]
    la = np.maximum(length[a], 1e-9)
    lb = np.maximum(length[b], 1e-9)
    u = (qa - pa) / la[:, None]
    rel0, rel1 = seg[b, :2] - pa, seg[b, 2:] - pa
    perp = np.maximum(
        np.abs(u[:, 0] * rel0[:, 1] - u[:, 1] * rel0[:, 0]), np.abs(u[:, 0] * rel1[:, 1] - u[:, 1] * rel1[:, 0])
    )
    t0 = np.einsum("ij,ij->i", rel0, u)
    t1 = np.einsum("ij,ij->i", rel1, u)
    tmin, tmax = np.minimum(t0, t1), np.maximum(t0, t1)
    gap = np.maximum(tmin - la, -tmax)  # > 0: disjoint along A's line
    overlap = np.clip(np.minimum(tmax, la) - np.maximum(tmin, 0.0), 0.0, None) / lb
    cosang = np.abs(np.einsum("ij,ij->i", u, (seg[b, 2:] - seg[b, :2]) / lb[:, None]))
    ang = np.degrees(np.arccos(np.clip(cosang, 0.0, 1.0)))
    chain = (ang < cfg.chain_angle_deg) & (perp < cfg.chain_offset_px) & (gap < cfg.chain_endpoint_px)
    merge = (ang < cfg.merge_angle_deg) & (perp < cfg.merge_distance_px) & (overlap >= cfg.merge_overlap)
    return chain | merge, perp + np.maximum(gap, 0.0)


def _mutual_best(n: int, i: np.ndarray, j: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Mask of the pairs that are the cheapest pair of both their segments (disjoint by construction)."""
    cost = cost + 1e-9 * np.arange(len(cost))  # unique costs: one best pair per segment
    best = np.full(n, np.inf)
    np.minimum.at(best, i, cost)
    np.minimum.at(best, j, cost)
    return (cost == best[i]) & (cost == best[j])


def fit_groups(raw: np.ndarray, label: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups,4) segments fitted to the raw (R,4) segments grouped by label (R,) in [0, n_groups)."""
    pts = np.concatenate([raw[:, :2], raw[:, 2:]])
    w = np.tile(np.maximum(segment_lengths(raw), 1e-6), 2)
    lab = np.tile(label, 2)
    sw = np.bincount(lab, w, n_groups)
    cx = np.bincount(lab, w * pts[:, 0], n_groups) / sw
    cy = np.bincount(lab, w * pts[:, 1], n_groups) / sw
    dx, dy = pts[:, 0] - cx[lab], pts[:, 1] - cy[lab]
    sxx = np.bincount(lab, w * dx * dx, n_groups)
    syy = np.bincount(lab, w * dy * dy, n_groups)
    sxy = np.bincount(lab, w * dx * dy, n_groups)
    phi = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # principal direction of the weighted endpoints
    ux, uy = np.cos(phi), np.sin(phi)
    # orient like the longest member: LSD orientation carries the edge polarity
    length = segment_lengths(raw)
    longest = np.zeros(n_groups, dtype=np.intp)
    order = np.lexsort((-length, label))
    first = np.r_[True, np.diff(label[order]) != 0]
    longest[label[order][first]] = order[first]
    ref = raw[longest, 2:] - raw[longest, :2]
    flip = np.where(ux * ref[:, 0] + uy * ref[:, 1] < 0, -1.0, 1.0)
    ux, uy = ux * flip, uy * flip
    t = dx * ux[lab] + dy * uy[lab]
    tmin = np.full(n_groups, np.inf)
    tmax = np.full(n_groups, -np.inf)
    np.minimum.at(tmin, lab, t)
    np.maximum.at(tmax, lab, t)
    return np.stack([cx + tmin * ux, cy + tmin * uy, cx + tmax * ux, cy + tmax * uy], axis=1)


# The repair's distances are set for LSD at this scale or finer (KITTI at 0.5, the drawings of the tests at 0.5 and 1).
_TOLERANCE_SCALE = 0.5


def repair_tolerances(cfg: LineConfig) -> LineConfig:
    """cfg with the repair's distances (chain_offset_px, chain_endpoint_px, merge_distance_px) for its LSD scale:
    as given at lsd_scale 0.5 and finer, grown by 0.5 / lsd_scale below it. LSD places a segment to a fraction of its
    own pixel, which spans 1 / lsd_scale of the image's: at 0.35 the pieces of an edge broken by occluders lie up to
    ~2 px off each other's line, beyond chain_offset_px, and the edge stays in pieces
    (tests/plvo/features/test_lines.py)."""
    if cfg.lsd_scale >= _TOLERANCE_SCALE:
        return cfg
    grow = _TOLERANCE_SCALE / cfg.lsd_scale
    return dataclasses.replace(cfg, chain_offset_px=cfg.chain_offset_px * grow,
                               chain_endpoint_px=cfg.chain_endpoint_px * grow,
                               merge_distance_px=cfg.merge_distance_px * grow)


def repair_segments(raw: np.ndarray, cfg: LineConfig) -> LineSegments:
    """Chain and merge raw (R,4) LSD segments until stable; keep those >= min_length_px, longest first. The
    distances are cfg's for its LSD scale (repair_tolerances)."""
    raw = np.asarray(raw, dtype=np.float64).reshape(-1, 4)
    cfg = repair_tolerances(cfg)
    kept = np.flatnonzero(segment_lengths(raw) >= cfg.raw_min_length_px)
    sub = raw[kept]
    label = np.arange(len(sub))
    seg = sub.copy()
    max_angle = np.radians(max(cfg.chain_angle_deg, cfg.merge_angle_deg))
    reach = max(cfg.chain_endpoint_px, cfg.merge_distance_px)
    iterations = 0
    while iterations < cfg.max_iterations and len(seg) > 1:
        i, j = _candidate_pairs(seg, max_angle, reach)
        ok, cost = _pair_costs(seg, i, j, cfg)
        i, j, cost = i[ok], j[ok], cost[ok]
        if len(i) == 0:
            break
        iterations += 1
        sel = _mutual_best(len(seg), i, j, cost)
        target = np.arange(len(seg))
        target[j[sel]] = i[sel]
        _, label = np.unique(target[label], return_inverse=True)
        seg = fit_groups(sub, label, int(label.max()) + 1)
    else:
        if len(seg) > 1 and iterations >= cfg.max_iterations:
            log.debug("line repair stopped after %d passes with pairs left", iterations)
    return _finish(raw, kept, seg, label, cfg, iterations)


def _finish(
    raw: np.ndarray, kept: np.ndarray, seg: np.ndarray, label: np.ndarray, cfg: LineConfig, iterations: int
) -> LineSegments:
    length = segment_lengths(seg)
    # a segment needs one raw member of some length: chains of short pieces are mostly texture, not structure
    anchor = np.zeros(len(seg))
    np.maximum.at(anchor, label, segment_lengths(raw[kept]))
    order = np.argsort(-length, kind="stable")
    good = (length[order] >= cfg.min_length_px) & (anchor[order] >= cfg.min_anchor_px)
    order = order[good][: cfg.max_lines]
    by_group = np.argsort(label, kind="stable")
    bounds = np.searchsorted(label[by_group], np.arange(len(seg) + 1))
    members = [kept[by_group[bounds[g] : bounds[g + 1]]] for g in order]
    return LineSegments(raw, seg[order].reshape(-1, 4), tuple(members), iterations)


def detect_lines(image: np.ndarray, cfg: LineConfig) -> LineSegments:
    """LSD on a (H,W) uint8 image, then the repair: raw (R,4) and repaired (M,4) segments in pixels."""
    return repair_segments(detect_lsd(image, cfg), cfg)
