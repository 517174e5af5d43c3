"""Feature extraction of one image (paper, II-A): ORB points and repaired LSD segments with LBD descriptors.

The line pipeline (LSD, repair, LBD) and ORB are independent; with `LineConfig.in_thread` the lines run in a
worker thread while ORB runs in the caller's. OpenCV releases the GIL in LSD, FAST, ORB and LBD, so on two cores
the frame costs about the longer of the two instead of their sum.
"""

from __future__ import annotations

import atexit
import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from plvo.config import LineConfig, OrbConfig
from plvo.errors import PlvoError
from plvo.features.lbd import compute_lbd
from plvo.features.lines import LineSegments, detect_lines
from plvo.features.points import detect_orb
from plvo.types import FeatureSet

log = logging.getLogger(__name__)

_pool: ThreadPoolExecutor | None = None


def _executor() -> ThreadPoolExecutor:
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="plvo-lines")
        atexit.register(_pool.shutdown, wait=False)
    return _pool


def extract_lines(image: np.ndarray, cfg: LineConfig) -> tuple[LineSegments, np.ndarray]:
    """Repaired LSD segments of a (H,W) uint8 image and their (M,32) uint8 LBD descriptors."""
    lines = detect_lines(image, cfg)
    return lines, compute_lbd(image, lines.segments)


def _no_lines() -> tuple[LineSegments, np.ndarray]:
    return LineSegments(np.zeros((0, 4)), np.zeros((0, 4)), (), 0), np.zeros((0, 32), np.uint8)


def extract_features(
    image: np.ndarray, orb_cfg: OrbConfig, line_cfg: LineConfig, points_only: bool = False
) -> FeatureSet:
    """ORB points and LSD+LBD lines of a (H,W) uint8 image, in its pixels; no lines when points_only."""
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8 or min(image.shape) < 2 * orb_cfg.edge_threshold:
        raise PlvoError(
            f"extract_features: field 'image' must be (H,W) uint8 of at least "
            f"{2 * orb_cfg.edge_threshold} px a side, got shape {image.shape} dtype {image.dtype}"
        )
    image = np.ascontiguousarray(image)
    future = None
    if points_only:
        lines, line_desc = _no_lines()
    elif line_cfg.in_thread:
        future = _executor().submit(extract_lines, image, line_cfg)
    else:
        lines, line_desc = extract_lines(image, line_cfg)
    points = detect_orb(image, orb_cfg)
    if future is not None:
        lines, line_desc = future.result()
    return FeatureSet(
        keypoints=points.xy,
        kp_octave=points.octave,
        kp_angle=points.angle,
        kp_response=points.response,
        descriptors=points.descriptors,
        segments=lines.segments,
        line_descriptors=line_desc,
        raw_segments=lines.raw,
        segment_sources=lines.sources,
        image_size=(int(image.shape[1]), int(image.shape[0])),
    )
