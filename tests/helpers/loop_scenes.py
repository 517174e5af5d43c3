"""Procedural images and a planar scene for the loop-closure tests (tests/plvo/loop/).

scene_image(seed): a 1241x376 grey image of random rectangles, discs, bars and texture noise, distinct for each
seed. planar_view(image, T_b_a, depth): the image seen as a fronto-parallel textured wall at `depth` metres from
camera a, re-rendered from camera b by the plane homography, so that every pixel of a has an exact 3D point.
"""

from __future__ import annotations

import cv2
import numpy as np

from plvo.geometry.camera import backproject
from plvo.loop.verification import LoopKeyframe

K = np.array([[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]])
W, H = 1241, 376


def scene_image(seed: int, width: int = W, height: int = H) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (height // 8, width // 8), dtype=np.uint8), (3, 3), 0)
    img = cv2.resize(img, (width, height), interpolation=cv2.INTER_CUBIC)
    for _ in range(120):
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        w, h = int(rng.integers(8, 90)), int(rng.integers(8, 60))
        shade = int(rng.integers(0, 256))
        kind = rng.integers(3)
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + w, y + h), shade, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), w // 3 + 3, shade, -1)
        else:
            cv2.line(img, (x, y), (x + w * 3, y + int(rng.integers(-5, 6))), shade, int(rng.integers(2, 5)))
    noise = rng.normal(0, 6, img.shape)
    return np.clip(img.astype(float) + noise, 0, 255).astype(np.uint8)


def plane_homography(T_b_a: np.ndarray, depth: float) -> np.ndarray:
    """Pixels of a -> pixels of b for the plane z = depth in camera a (normal (0,0,1))."""
    R, t = T_b_a[:3, :3], T_b_a[:3, 3]
    n = np.array([0.0, 0.0, 1.0])
    Hm = K @ (R + np.outer(t, n) / depth) @ np.linalg.inv(K)
    return Hm / Hm[2, 2]


def planar_view(image: np.ndarray, T_b_a: np.ndarray, depth: float) -> np.ndarray:
    return cv2.warpPerspective(image, plane_homography(T_b_a, depth), (image.shape[1], image.shape[0]),
                               flags=cv2.INTER_LINEAR, borderValue=0)


def planar_keyframe(kf_id: int, image: np.ndarray, depth: float | None, T_world_cam=None) -> LoopKeyframe:
    """Features of `image`; with `depth`, every point and segment endpoint lies on the wall z = depth."""
    from plvo.config import LineConfig, OrbConfig
    from plvo.features.extract import extract_features

    fs = extract_features(image, OrbConfig(), LineConfig())
    n, m = fs.n_points, fs.n_lines
    if depth is None:
        pts, lines = np.full((n, 3), np.nan), np.full((m, 2, 3), np.nan)
    else:
        pts = backproject(K, fs.keypoints, np.full(n, depth))
        lines = backproject(K, fs.segments.reshape(-1, 2), np.full(2 * m, depth)).reshape(m, 2, 3)
    T = np.eye(4) if T_world_cam is None else T_world_cam
    return LoopKeyframe(kf_id, T, fs.keypoints, fs.descriptors, pts, fs.segments, fs.line_descriptors, lines)
