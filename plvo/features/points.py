"""ORB points spread evenly over the image, as ORB-SLAM2 does it (paper, II-A).

Per pyramid level: FAST corners with a per-cell threshold (a cell keeps its corners scoring >= `fast_threshold`
when it has any, else those scoring >= `fast_threshold_min`), then an even spread by bucketing (each bucket's
best corner first, then each bucket's second best, ...), then the intensity-centroid orientation and the
rotated-BRIEF descriptor of cv2.ORB.

One FAST pass at the low threshold is enough: OpenCV's FAST response is the highest threshold at which the
point is still a corner, and non-maximum suppression compares those responses, so the corners found at the high
threshold are exactly the low-threshold corners whose response reaches it (checked on KITTI 04 frame 0).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

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


def _circle_offsets() -> tuple[np.ndarray, np.ndarray]:
    """Offsets (dx, dy) of the circular patch used for the intensity centroid (ORB's umax)."""
    d = np.arange(-HALF_PATCH, HALF_PATCH + 1)
    dx, dy = np.meshgrid(d, d)
    inside = dx**2 + dy**2 <= HALF_PATCH**2 + HALF_PATCH  # ORB's rounded circle
    return dx[inside].astype(np.intp), dy[inside].astype(np.intp)


_DX, _DY = _circle_offsets()


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


def _kp_arrays(kps: tuple, offset: int) -> tuple[np.ndarray, np.ndarray]:
    if not kps:
        return np.zeros((0, 2)), np.zeros(0)
    xy = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2) + offset
    return xy, np.fromiter((k.response for k in kps), dtype=np.float64, count=len(kps))


def _fast_corners(img: np.ndarray, cfg: OrbConfig) -> tuple[np.ndarray, np.ndarray]:
    """FAST corners with ORB-SLAM2's per-cell threshold: (K,2) level pixels, (K,) responses.

    The low-threshold pass runs only on horizontal runs of the cells where the high threshold found nothing:
    textured cells have tens of thousands of weak corners that would otherwise cost time to detect and convert.
    """
    b = cfg.edge_threshold - 3  # FAST itself needs 3 px, as in ORB-SLAM2
    h, w = img.shape
    if h - 2 * b < 8 or w - 2 * b < 8:
        return np.zeros((0, 2)), np.zeros(0)
    xy, resp = _kp_arrays(cv2.FastFeatureDetector_create(cfg.fast_threshold, True).detect(img[b : h - b, b : w - b]), b)
    if cfg.fast_threshold_min >= cfg.fast_threshold:
        return _inside(xy, resp, w, h, cfg.edge_threshold)
    cell = cfg.grid_cell_px
    ncols, nrows = int(np.ceil(w / cell)), int(np.ceil(h / cell))
    strong = np.zeros(nrows * ncols, dtype=bool)
    strong[_cell_index(xy, cell, w)] = True
    weak = ~strong.reshape(nrows, ncols)
    edges = np.diff(np.pad(weak, ((0, 0), (1, 1))).astype(np.int8), axis=1)
    det = cv2.FastFeatureDetector_create(cfg.fast_threshold_min, True)
    parts_xy, parts_resp = [xy], [resp]
    for r, c0, c1 in zip(*np.nonzero(edges == 1), np.nonzero(edges == -1)[1]):
        y0, y1 = max(r * cell - 3, b), min((r + 1) * cell + 3, h - b)
        x0, x1 = max(c0 * cell - 3, b), min(c1 * cell + 3, w - b)
        if y1 - y0 < 7 or x1 - x0 < 7:
            continue
        sxy, sresp = _kp_arrays(det.detect(img[y0:y1, x0:x1]), 0)
        sxy += (x0, y0)
        own = weak.ravel()[_cell_index(np.clip(sxy, 0, [w - 1, h - 1]), cell, w)]
        parts_xy.append(sxy[own])
        parts_resp.append(sresp[own])
    return _inside(np.vstack(parts_xy), np.concatenate(parts_resp), w, h, cfg.edge_threshold)


def _inside(xy: np.ndarray, resp: np.ndarray, w: int, h: int, e: int) -> tuple[np.ndarray, np.ndarray]:
    inside = (xy[:, 0] >= e) & (xy[:, 1] >= e) & (xy[:, 0] < w - e) & (xy[:, 1] < h - e)
    return xy[inside], resp[inside]


def _cell_index(xy: np.ndarray, cell: float, width: int) -> np.ndarray:
    ncols = int(np.ceil(width / cell))
    return (xy[:, 1] // cell).astype(np.int64) * ncols + (xy[:, 0] // cell).astype(np.int64)


def spread_select(xy: np.ndarray, resp: np.ndarray, n: int, width: int, height: int) -> np.ndarray:
    """Indices of n corners spread evenly: about n buckets, the best of each first, then the second best..."""
    if len(xy) <= n:
        return np.arange(len(xy))
    cell = max(np.sqrt(width * height / max(n, 1)), 1.0)
    cells = _cell_index(xy, cell, width)
    rel = resp / (resp.max() + 1.0)  # in [0, 1): sorts within a cell without a second key
    order = np.argsort(cells - rel, kind="stable")  # by cell, best first within a cell
    sorted_cells = cells[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_cells)) + 1]
    run_start = np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order)) - run_start
    pick = np.argsort(rank - rel, kind="stable")[:n]
    return np.sort(pick)


def ic_angles(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(K,) ORB orientation in degrees [0, 360) by the intensity centroid of a radius-15 disc; xy in this level."""
    if len(xy) == 0:
        return np.zeros(0)
    pad = cv2.copyMakeBorder(img, HALF_PATCH, HALF_PATCH, HALF_PATCH, HALF_PATCH, cv2.BORDER_REFLECT_101)
    stride = pad.shape[1]
    base = (np.rint(xy[:, 1]).astype(np.intp) + HALF_PATCH) * stride + np.rint(xy[:, 0]).astype(np.intp) + HALF_PATCH
    vals = np.take(pad.ravel(), base[:, None] + (_DY * stride + _DX)[None, :]).astype(np.float32)
    m10 = vals @ _DX.astype(np.float32)
    m01 = vals @ _DY.astype(np.float32)
    return np.degrees(np.arctan2(m01, m10).astype(np.float64)) % 360.0


def detect_orb(image: np.ndarray, cfg: OrbConfig) -> OrbPoints:
    """ORB features evenly spread over a (H,W) uint8 image; positions in level-0 pixels."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise PlvoError(f"ORB: image must be (H,W) uint8, got shape {image.shape} dtype {image.dtype}")
    pyramid = build_pyramid(image, cfg)
    wanted = features_per_level(cfg)
    keypoints: list[cv2.KeyPoint] = []
    for lvl, (img, n) in enumerate(zip(pyramid, wanted)):
        xy, resp = _fast_corners(img, cfg)
        if len(xy) == 0 or n <= 0:
            continue
        sel = spread_select(xy, resp, int(n), img.shape[1], img.shape[0])
        xy, resp = xy[sel], resp[sel]
        ang = ic_angles(img, xy)
        s = cfg.scale_factor**lvl
        size = PATCH_SIZE * s
        keypoints.extend(
            cv2.KeyPoint(x, y, size, a, r, lvl)
            for (x, y), a, r in zip((xy * s).tolist(), ang.tolist(), resp.tolist())
        )
    return _describe(image, keypoints, cfg)


def _describe(image: np.ndarray, keypoints: list[cv2.KeyPoint], cfg: OrbConfig) -> OrbPoints:
    if not keypoints:
        return _empty()
    orb = cv2.ORB_create(
        nfeatures=cfg.n_features,
        scaleFactor=cfg.scale_factor,
        nlevels=cfg.n_levels,
        edgeThreshold=cfg.edge_threshold,
        patchSize=PATCH_SIZE,
    )
    kps, desc = orb.compute(image, keypoints)
    if desc is None or not kps:
        return _empty()
    n = len(kps)
    xy = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(n, 2)
    octave = np.fromiter((k.octave for k in kps), dtype=np.int32, count=n)
    angle = np.fromiter((k.angle for k in kps), dtype=np.float64, count=n)
    response = np.fromiter((k.response for k in kps), dtype=np.float64, count=n)
    return OrbPoints(xy, octave, angle, response, desc)


def _empty() -> OrbPoints:
    return OrbPoints(
        np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0), np.zeros(0), np.zeros((0, 32), np.uint8)
    )
