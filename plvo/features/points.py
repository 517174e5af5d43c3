"""ORB points spread evenly over the image, as ORB-SLAM2 does it (paper, II-A).

Per pyramid level: FAST corners with a per-cell threshold (a cell keeps its corners scoring >= `fast_threshold`
when it has any, else those scoring >= `fast_threshold_min`), then an even spread by bucketing (each bucket's
best corner first, then each bucket's second best, ...), then the intensity-centroid orientation and the
rotated-BRIEF descriptor of cv2.ORB, computed on the level's own image.

OpenCV's FAST response is the highest threshold at which the point is still a corner, and non-maximum
suppression compares those responses, so the corners found at the high threshold are exactly the low-threshold
corners whose response reaches it (checked on KITTI 04 frame 0): the low threshold is only needed in the cells
where the high one found nothing, and it runs on those cells alone.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from plvo.config import OrbConfig
from plvo.errors import PlvoError

log = logging.getLogger(__name__)

PATCH_SIZE = 31
HALF_PATCH = PATCH_SIZE // 2


@dataclass(frozen=True)
class OrbPoints:
    """ORB features of one image. xy: (N,2) level-0 pixels; octave, angle (deg), response: (N,); desc: (N,32)."""

    xy: np.ndarray
    octave: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    descriptors: np.ndarray


def _disc_weights() -> np.ndarray:
    """(31*31, 2) float32 weights (dx, dy) of a 31x31 patch, zero outside ORB's circle (its umax)."""
    d = np.arange(-HALF_PATCH, HALF_PATCH + 1)
    dx, dy = np.meshgrid(d, d)
    inside = dx**2 + dy**2 <= HALF_PATCH**2 + HALF_PATCH  # ORB's rounded circle
    return np.stack([(dx * inside).ravel(), (dy * inside).ravel()], axis=1).astype(np.float32)


_DISC_WEIGHTS = _disc_weights()


def features_per_level(cfg: OrbConfig) -> np.ndarray:
    """(n_levels,) int: ORB-SLAM2's geometric split of n_features over the pyramid levels."""
    f = 1.0 / cfg.scale_factor
    n0 = cfg.n_features * (1 - f) / (1 - f**cfg.n_levels)
    per = np.round(n0 * f ** np.arange(cfg.n_levels)).astype(int)
    per[-1] = max(cfg.n_features - int(per[:-1].sum()), 0)
    return per


def build_pyramid(image: np.ndarray, cfg: OrbConfig) -> list[np.ndarray]:
    """Images of the levels, sized like cv2.ORB's pyramid (round(W / s^l), round(H / s^l))."""
    h, w = image.shape
    levels = [image]
    for lvl in range(1, cfg.n_levels):
        s = cfg.scale_factor**lvl
        size = (int(round(w / s)), int(round(h / s)))
        levels.append(cv2.resize(image, size, interpolation=cv2.INTER_LINEAR))
    return levels


def _kp_arrays(kps: Sequence[cv2.KeyPoint], offset: int) -> tuple[np.ndarray, np.ndarray]:
    if not kps:
        return np.zeros((0, 2)), np.zeros(0)
    xy = np.asarray(cv2.KeyPoint.convert(kps), np.float64).reshape(-1, 2) + offset
    return xy, np.fromiter((k.response for k in kps), dtype=np.float64, count=len(kps))


def _fast_corners(img: np.ndarray, cfg: OrbConfig) -> tuple[np.ndarray, np.ndarray]:
    """FAST corners with ORB-SLAM2's per-cell threshold: (K,2) level pixels, (K,) responses.

    The low-threshold pass runs only on the runs of cells (along a cell row) where the high threshold found
    nothing: textured cells have tens of thousands of weak corners that would cost time to detect and convert.
    The runs' crops are packed into one image and searched in one FAST call (per-call overhead was a third of the
    cost); each crop has a MARGIN px border so its own pixels' scores and their non-maximum suppression see only
    the crop's pixels, as on the whole image.
    """
    b = cfg.edge_threshold - 3  # FAST itself needs 3 px, as in ORB-SLAM2
    h, w = img.shape
    if h - 2 * b < 8 or w - 2 * b < 8:
        return np.zeros((0, 2)), np.zeros(0)
    xy, resp = _kp_arrays(cv2.FastFeatureDetector.create(cfg.fast_threshold, True).detect(img[b : h - b, b : w - b]), b)
    if cfg.fast_threshold_min < cfg.fast_threshold:
        cell = cfg.grid_cell_px
        ncols, nrows = int(np.ceil(w / cell)), int(np.ceil(h / cell))
        strong = np.zeros(nrows * ncols, dtype=bool)
        strong[_cell_index(xy, cell, w)] = True
        weak = np.pad(~strong.reshape(nrows, ncols), ((0, 0), (1, 1))).astype(np.int8)
        r, c0 = np.nonzero(np.diff(weak, axis=1) == 1)
        c1 = np.nonzero(np.diff(weak, axis=1) == -1)[1]
        own = np.stack([c0 * cell, r * cell, np.minimum(c1 * cell, w), np.minimum((r + 1) * cell, h)], axis=1)
        wxy, wresp = _weak_corners(img, own, b, cfg.fast_threshold_min)
        xy, resp = np.vstack([xy, wxy]), np.concatenate([resp, wresp])
    return _inside(xy, resp, w, h, cfg.edge_threshold)


MARGIN = 4  # crop border: a pixel's FAST circle has radius 3, and its NMS neighbours' circles reach 4


def _weak_corners(img: np.ndarray, own: np.ndarray, b: int, threshold: int) -> tuple[np.ndarray, np.ndarray]:
    """FAST corners at `threshold` inside the (R,4) x0,y0,x1,y1 pixel rectangles `own`, via one packed image."""
    h, w = img.shape
    x0, y0 = np.maximum(own[:, 0] - MARGIN, b), np.maximum(own[:, 1] - MARGIN, b)
    x1, y1 = np.minimum(own[:, 2] + MARGIN, w - b), np.minimum(own[:, 3] + MARGIN, h - b)
    ok = (x1 - x0 >= 7) & (y1 - y0 >= 7)
    if not ok.any():
        return np.zeros((0, 2)), np.zeros(0)
    own, x0, y0, x1, y1 = own[ok], x0[ok], y0[ok], x1[ok], y1[ok]
    cw, ch = (x1 - x0).tolist(), (y1 - y0).tolist()
    width, shelf = max(w, max(cw)), max(ch)
    px, py, x, y = [], [], 0, 0
    for k in cw:  # shelf packing: left to right, a new shelf when the row is full
        if x + k > width:
            x, y = 0, y + shelf
        px.append(x)
        py.append(y)
        x += k
    packed = np.zeros((y + shelf, width), np.uint8)
    owner = np.full(packed.shape, -1, np.int32)
    for k, (a, c, wk, hk) in enumerate(zip(px, py, cw, ch)):
        packed[c : c + hk, a : a + wk] = img[y0[k] : y0[k] + hk, x0[k] : x0[k] + wk]
        owner[c : c + hk, a : a + wk] = k
    sxy, sresp = _kp_arrays(cv2.FastFeatureDetector.create(threshold, True).detect(packed), 0)
    ij = sxy.astype(np.intp)
    k = owner[ij[:, 1], ij[:, 0]]
    shift = np.stack([x0 - np.asarray(px), y0 - np.asarray(py)], axis=1)
    sxy += shift[k]
    o = own[k]
    keep = (k >= 0) & (sxy[:, 0] >= o[:, 0]) & (sxy[:, 1] >= o[:, 1]) & (sxy[:, 0] < o[:, 2]) & (sxy[:, 1] < o[:, 3])
    return sxy[keep], sresp[keep]


def _inside(xy: np.ndarray, resp: np.ndarray, w: int, h: int, e: int) -> tuple[np.ndarray, np.ndarray]:
    inside = (xy[:, 0] >= e) & (xy[:, 1] >= e) & (xy[:, 0] < w - e) & (xy[:, 1] < h - e)
    return xy[inside], resp[inside]


def _cell_index(xy: np.ndarray, cell: float, width: int) -> np.ndarray:
    """(K,) row-major cell ids of (K,2) non-negative pixels; a product, not //, which is slow on floats."""
    ncols = int(np.ceil(width / cell))
    inv = 1.0 / cell
    return (xy[:, 1] * inv).astype(np.int64) * ncols + (xy[:, 0] * inv).astype(np.int64)


def spread_select(xy: np.ndarray, resp: np.ndarray, n: int, width: int, height: int) -> np.ndarray:
    """Indices of n corners spread evenly: about n buckets, the best of each first, then the second best..."""
    m = len(xy)
    if m <= n:
        return np.arange(m)
    cell = max(np.sqrt(width * height / max(n, 1)), 1.0)
    cells = _cell_index(xy, cell, width)
    # Rank the responses once (best 0, ties by index): the integer keys below are then unique, so a plain sort
    # gives the order of a stable sort by (cell, -response) and then by (rank in cell, -response).
    rrank = np.empty(m, np.int64)
    rrank[np.argsort(-resp, kind="stable")] = np.arange(m)
    order = np.argsort(cells * m + rrank)
    sorted_cells = cells[order]
    first = np.ones(m, dtype=bool)
    first[1:] = sorted_cells[1:] != sorted_cells[:-1]
    run_start = np.flatnonzero(first)[np.cumsum(first) - 1]
    rank = np.empty(m, dtype=np.int64)
    rank[order] = np.arange(m) - run_start
    return np.sort(np.argpartition(rank * m + rrank, n - 1)[:n])


def ic_angles(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(K,) ORB orientation in degrees [0, 360) by the intensity centroid of a radius-15 disc; xy in this level."""
    if len(xy) == 0:
        return np.zeros(0)
    pad = cv2.copyMakeBorder(img, HALF_PATCH, HALF_PATCH, HALF_PATCH, HALF_PATCH, cv2.BORDER_REFLECT_101)
    # (K,31,31) patches by indexing a window view with K pairs: no (K,709) index array to build
    windows = sliding_window_view(pad, (PATCH_SIZE, PATCH_SIZE))
    patches = windows[np.rint(xy[:, 1]).astype(np.intp), np.rint(xy[:, 0]).astype(np.intp)]
    m = patches.reshape(len(xy), -1).astype(np.float32) @ _DISC_WEIGHTS
    return np.degrees(np.arctan2(m[:, 1], m[:, 0]).astype(np.float64)) % 360.0


def detect_orb(image: np.ndarray, cfg: OrbConfig) -> OrbPoints:
    """ORB features evenly spread over a (H,W) uint8 image; positions in level-0 pixels."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise PlvoError(f"ORB: image must be (H,W) uint8, got shape {image.shape} dtype {image.dtype}")
    pyramid = build_pyramid(image, cfg)
    wanted = features_per_level(cfg)
    parts = []
    for lvl, (img, n) in enumerate(zip(pyramid, wanted)):
        xy, resp = _fast_corners(img, cfg)
        if len(xy) == 0 or n <= 0:
            continue
        sel = spread_select(xy, resp, int(n), img.shape[1], img.shape[0])
        xy, resp = xy[sel], resp[sel]
        part = _describe_level(img, xy, ic_angles(img, xy), resp, cfg)
        if part is not None:
            parts.append((lvl, part))
    if not parts:
        return _empty()
    s = np.concatenate([np.full(len(p[0]), cfg.scale_factor**lvl) for lvl, p in parts])
    return OrbPoints(
        xy=np.vstack([p[0] for _, p in parts]) * s[:, None],
        octave=np.concatenate([np.full(len(p[0]), lvl, np.int32) for lvl, p in parts]),
        angle=np.concatenate([p[1] for _, p in parts]),
        response=np.concatenate([p[2] for _, p in parts]),
        descriptors=np.vstack([p[3] for _, p in parts]),
    )


def _describe_level(
    img: np.ndarray, xy: np.ndarray, angle: np.ndarray, resp: np.ndarray, cfg: OrbConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """rBRIEF of corners (K,2) in one level's pixels, on that level's image -> (xy, angle, response, desc) or None.

    One single-level cv2.ORB per level of our pyramid: cv2.ORB's multi-level compute would rebuild and blur its
    own pyramid (5 of its 7 ms) and describe the corners in images resampled differently from those they were
    detected in.
    """
    orb = cv2.ORB.create(
        nfeatures=cfg.n_features, scaleFactor=cfg.scale_factor, nlevels=1, edgeThreshold=cfg.edge_threshold,
        patchSize=PATCH_SIZE,
    )
    given = [cv2.KeyPoint(x, y, PATCH_SIZE, a, r, 0)
             for (x, y), a, r in zip(xy.tolist(), angle.tolist(), resp.tolist())]
    kps, desc = orb.compute(img, given)
    if desc is None or not kps:
        return None
    n = len(kps)
    if n == len(xy):  # nothing dropped: ORB keeps the order
        return xy, angle, resp, desc
    out_xy = np.asarray(cv2.KeyPoint.convert(kps), np.float64).reshape(n, 2)
    out_angle = np.fromiter((k.angle for k in kps), dtype=np.float64, count=n)
    return out_xy, out_angle, np.fromiter((k.response for k in kps), dtype=np.float64, count=n), desc


def _empty() -> OrbPoints:
    return OrbPoints(
        np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0), np.zeros(0), np.zeros((0, 32), np.uint8)
    )
