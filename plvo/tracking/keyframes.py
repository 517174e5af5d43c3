"""When to make a keyframe: every cfg.keyframe_every frames (the paper: 3-4), earlier when tracking weakens.

Reasons, checked in this order: the first frame; tracking was lost (re-initialisation); fewer tracked landmarks
than cfg.min_tracked_landmarks; rotation since the last keyframe above cfg.max_rotation_deg; the regular
interval. cfg.keyframe_max_gap caps the interval when keyframe_every is set larger than it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from plvo.config import TrackingConfig
from plvo.geometry import se3
from plvo.geometry.camera import pixel_rays, project
from plvo.lidar.deskew import Sweep
from plvo.lidar.scan import registration_scan
from plvo.results import KeyframeReason, KeyframeWhy
from plvo.types import DepthPriors, FeatureSet, Frame


@dataclass(frozen=True)
class KeyframeDecision:
    """Why the frame is a keyframe (None: it is not); frames_since_last and rotation_deg since the last keyframe."""

    reason: KeyframeWhy | None
    frames_since_last: int
    rotation_deg: float

    @property
    def is_keyframe(self) -> bool:
        return self.reason is not None


class KeyframePolicy:
    """Stateful keyframe decisions; call `decide` once a frame and `accept` when a keyframe was made."""

    def __init__(self, cfg: TrackingConfig):
        self.cfg = cfg
        self.interval = max(1, min(cfg.keyframe_every, cfg.keyframe_max_gap))
        self.last_frame: int | None = None
        self.last_T_world_cam: np.ndarray | None = None

    def decide(self, frame_index: int, T_world_cam: np.ndarray, n_tracked: int, lost: bool = False
               ) -> KeyframeDecision:
        """Frame index, its (4,4) pose and the number of landmarks tracked into it -> decision."""
        if self.last_frame is None or self.last_T_world_cam is None:
            return KeyframeDecision(KeyframeWhy(KeyframeReason.FIRST), 0, 0.0)
        gap = frame_index - self.last_frame
        rot = float(np.degrees(se3.rotation_angle(se3.inv(self.last_T_world_cam) @ T_world_cam)))
        if lost:
            return KeyframeDecision(KeyframeWhy(KeyframeReason.LOST), gap, rot)
        if gap <= 0:
            return KeyframeDecision(None, gap, rot)
        if n_tracked < self.cfg.min_tracked_landmarks:
            why = KeyframeWhy(KeyframeReason.FEW_TRACKED, f"{n_tracked} < {self.cfg.min_tracked_landmarks}")
            return KeyframeDecision(why, gap, rot)
        if rot > self.cfg.max_rotation_deg:
            why = KeyframeWhy(KeyframeReason.ROTATION, f"{rot:.1f} > {self.cfg.max_rotation_deg} deg")
            return KeyframeDecision(why, gap, rot)
        if gap >= self.interval:
            return KeyframeDecision(KeyframeWhy(KeyframeReason.INTERVAL, f"{gap} frames"), gap, rot)
        return KeyframeDecision(None, gap, rot)

    def accept(self, frame_index: int, T_world_cam: np.ndarray) -> None:
        """A keyframe was made at frame_index with pose (4,4)."""
        self.last_frame = int(frame_index)
        self.last_T_world_cam = np.array(T_world_cam, dtype=float)


@dataclass(frozen=True)
class KeyframeInfo:
    """A keyframe as the back end receives it.

    kf_id in the map; frame (image and scan); T_world_cam (4,4) at creation; features; depth_priors (None in
    the no-depth-priors ablation, except for lidar initialisations); point_landmark (N,) / line_landmark (M,):
    the landmark id of each feature (-1 none), already recorded as observations in the map; sweep: how its
    registration scan is deskewed before the workers get it (plvo.lidar.deskew, plvo.runtime.system), None when it is
    not."""

    kf_id: int
    frame_index: int
    T_world_cam: np.ndarray
    frame: Frame
    features: FeatureSet
    depth_priors: DepthPriors | None
    point_landmark: np.ndarray
    line_landmark: np.ndarray
    reason: KeyframeWhy
    sweep: Sweep | None = None

    @cached_property
    def registration_scan(self) -> np.ndarray:
        """The scan as registration uses it (plvo.lidar.scan), made once for the back end and the loop closer."""
        return registration_scan(self.frame)


def triangulate_tracks(K: np.ndarray, T_world_cam0: np.ndarray, uv0: np.ndarray, T_world_cam1: np.ndarray,
                       uv1: np.ndarray, max_reproj_px: float, min_parallax_deg: float = 1.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Two views (4,4) with matched pixels (n,2) each -> (n,3) world points (midpoint of the rays) and (n,) ok.

    ok requires positive depth in both views, reprojection below max_reproj_px in both and a ray angle of at
    least min_parallax_deg (less gives depths too uncertain to track with).
    """
    n = len(uv0)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    c0, c1 = T_world_cam0[:3, 3], T_world_cam1[:3, 3]
    r0 = pixel_rays(K, uv0) @ T_world_cam0[:3, :3].T
    r1 = pixel_rays(K, uv1) @ T_world_cam1[:3, :3].T
    r0 /= np.linalg.norm(r0, axis=1, keepdims=True)
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    w = c0 - c1
    b = np.sum(r0 * r1, axis=1)
    d, e = r0 @ w, r1 @ w
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - d) / denom
        t = (e - b * d) / denom
    pw = 0.5 * ((c0 + s[:, None] * r0) + (c1 + t[:, None] * r1))
    ok = (denom > 1e-12) & (b < np.cos(np.radians(min_parallax_deg)))
    for T, uv in ((T_world_cam0, uv0), (T_world_cam1, uv1)):
        puv, z = project(K, se3.transform_points(se3.inv(T), pw))
        with np.errstate(invalid="ignore"):
            ok &= (z > 0) & (np.linalg.norm(puv - uv, axis=1) < max_reproj_px)
    return pw, ok


def closest_points_on_lines(A: np.ndarray, B: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Lines through A,B (n,3) and ray pairs (n,2,3) from the origin -> (n,2,3) points of each line closest to each
    ray; NaN where a ray is parallel to its line."""
    d = B - A
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rays / np.linalg.norm(rays, axis=2, keepdims=True)
    b = np.einsum("nkc,nc->nk", r, d)
    e = np.einsum("nkc,nc->nk", r, A)
    f = np.einsum("nc,nc->n", d, A)[:, None]
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(denom > 1e-12, (b * e - f) / denom, np.nan)
    return A[:, None, :] + t[..., None] * d[:, None, :]
