"""Pinhole projection and back-projection in OpenCV's camera frame (x right, y down, z forward)."""

from __future__ import annotations

import numpy as np


def project(K: np.ndarray, pts_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) camera-frame points -> (N,2) pixels and (N,) depths z. Points with z <= 0 give NaN pixels."""
    pts_cam = np.asarray(pts_cam, dtype=float).reshape(-1, 3)
    z = pts_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (pts_cam[:, :2] / z[:, None]) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    uv[z <= 0] = np.nan
    return uv, z


def backproject(K: np.ndarray, uv: np.ndarray, depth: np.ndarray | float = 1.0) -> np.ndarray:
    """(N,2) pixels and (N,) depths along z -> (N,3) camera-frame points."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    rays = pixel_rays(K, uv)
    return rays * np.asarray(depth, dtype=float).reshape(-1, 1)


def pixel_rays(K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,2) pixels -> (N,3) rays with z = 1."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0]
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=1)


def in_image(uv: np.ndarray, width: int, height: int, margin: float = 0.0) -> np.ndarray:
    """(N,2) pixels -> (N,) bool, inside [margin, size - margin)."""
    u, v = uv[:, 0], uv[:, 1]
    with np.errstate(invalid="ignore"):
        return (u >= margin) & (v >= margin) & (u < width - margin) & (v < height - margin)
