"""Feature extraction of one image (paper, II-A): ORB points and repaired LSD segments with LBD descriptors.

The line pipeline (LSD, repair, LBD) and ORB are independent; with `LineConfig.in_thread` LSD and the repair run
in a worker thread while ORB runs in the caller's, and then the LBD descriptors are split between the two
threads (ORB finishes first: LSD + repair + LBD is the longer path). OpenCV releases the GIL in LSD, FAST, ORB
and LBD, so on two cores the frame costs about max(ORB, LSD + repair) + LBD / 2 instead of the sum.
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
from plvo.priority import LOOKAHEAD_NICENESS, lower_priority
from plvo.types import FeatureSet

log = logging.getLogger(__name__)

_pool: ThreadPoolExecutor | None = None


def _executor() -> ThreadPoolExecutor:
    global _pool
    if _pool is None:
        # at the look-ahead's priority: in the System its work is for frames read ahead (System.prepare)
        _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="plvo-lines", initializer=lower_priority,
                                   initargs=(LOOKAHEAD_NICENESS,))
        atexit.register(_pool.shutdown, wait=False)
    return _pool


def extract_lines(image: np.ndarray, cfg: LineConfig) -> tuple[LineSegments, np.ndarray]:
    """Repaired LSD segments of a (H,W) uint8 image and their (M,32) uint8 LBD descriptors."""
    lines = detect_lines(image, cfg)
    return lines, compute_lbd(image, lines.segments)


_SPLIT_MIN_LINES = 16  # fewer: LBD's fixed cost (its own Sobel images, ~2 ms) outweighs sharing the lines


def _split_lbd(image: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(M,32) LBD descriptors of (M,4) segments, every other one computed in the worker thread meanwhile.

    A segment's descriptor depends on the image and that segment alone, so the two calls' rows equal one call's.
    """
    if len(segments) < _SPLIT_MIN_LINES:
        return compute_lbd(image, segments)
    # every other segment: they come longest first, and LBD's cost is proportional to the length
    other = _executor().submit(compute_lbd, image, segments[1::2])
    out = np.empty((len(segments), 32), np.uint8)
    out[0::2] = compute_lbd(image, segments[0::2])
    out[1::2] = other.result()
    return out


def _no_lines() -> tuple[LineSegments, np.ndarray]:
    return LineSegments(np.zeros((0, 4)), np.zeros((0, 4)), (), 0), np.zeros((0, 32), np.uint8)


def extract_features(
    image: np.ndarray, orb_cfg: OrbConfig, line_cfg: LineConfig, points_only: bool = False, split_lbd: bool = True
) -> FeatureSet:
    """ORB points and LSD+LBD lines of a (H,W) uint8 image, in its pixels; no lines when points_only.

    split_lbd (with line_cfg.in_thread): the LBD descriptors computed by both threads, each of which computes the
    image's gradients for LBD (~1.2 ms of CPU a KITTI frame): a frame's features sooner for more CPU. The
    descriptors are the same either way."""
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
        future = _executor().submit(detect_lines, image, line_cfg)
    else:
        lines, line_desc = extract_lines(image, line_cfg)
    points = detect_orb(image, orb_cfg)
    if future is not None:
        lines = future.result()
        line_desc = _split_lbd(image, lines.segments) if split_lbd else compute_lbd(image, lines.segments)
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
