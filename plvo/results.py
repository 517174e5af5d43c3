"""Stage results of tracking, keyframing, back end and loop closing, as the System hands them to recorders.

Each is a frozen dataclass holding numpy arrays (treat them as read-only), tagged with the frame it belongs to.
Front-end results (FeatureSet, FeatureMatches, DepthPriors) live in `plvo.types`. Poses are `T_world_cam` of the
chosen camera, world = cam0 of the first frame; 3D positions are (N,3) in the world frame, metres.
The stage engineers fill these; the recorders only read the fields documented here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from typing import Any

import numpy as np


class EdgeKind(IntEnum):
    """What ties two keyframes in the graph (GraphEdge.kind; GraphResult.edge_kind holds the values as ints)."""

    ODOMETRY = 0  # consecutive keyframes: VO relative pose / lidar registration
    COVISIBILITY = 1  # keyframes sharing landmarks in the local window
    LOOP = 2  # accepted loop closure


class KeyframeReason(StrEnum):
    """Why a frame became a keyframe (plvo.tracking.keyframes), in the order the policy checks them."""

    FIRST = "first frame"
    LOST = "tracking lost: re-initialised from lidar depth"
    OVERRULED = "camera overruled by the lidar: re-initialised from lidar depth"  # plvo.tracking.lidar_check
    FEW_TRACKED = "few tracked landmarks"  # fewer than tracking.min_tracked_landmarks
    ROTATION = "large rotation"  # more than tracking.max_rotation_deg since the last keyframe
    INTERVAL = "interval"  # tracking.keyframe_every frames since the last keyframe


@dataclass(frozen=True)
class KeyframeWhy:
    """A keyframe's reason and the figures that decided it ("12 < 60", "11.2 > 10.0 deg"); reads as the sentence
    the logs and the viewers show."""

    kind: KeyframeReason
    detail: str = ""

    def __str__(self) -> str:
        return f"{self.kind} ({self.detail})" if self.detail else str(self.kind)


def _empty(shape: tuple[int, ...], dtype: type = float) -> np.ndarray:
    return np.zeros(shape, dtype=dtype)


@dataclass(frozen=True)
class TrackingResult:
    """The tracker's answer for one frame.

    T_world_cam: (4,4) estimated pose. point_inliers / line_inliers: indices into this frame's FeatureSet keypoints
    / segments that were tracked and kept by PnP/PnL. ok: False when tracking was lost (then T_world_cam is the
    motion-model prediction). message: a short human-readable decision, e.g. "keyframe: 52 tracked < 60".
    pnpl_point_residuals / pnpl_line_residuals: (k,) px, the frame-to-frame PnPL's inliers' reprojection distances at
    its pose (a point's to its keypoint, a line's farther endpoint's to the projected line), before the landmarks
    re-found by projection join; empty where nothing was solved (first frame, tracking lost).
    """

    frame_index: int
    T_world_cam: np.ndarray
    n_point_matches: int = 0
    n_line_matches: int = 0
    point_inliers: np.ndarray = field(default_factory=lambda: _empty((0,), int))
    line_inliers: np.ndarray = field(default_factory=lambda: _empty((0,), int))
    is_keyframe: bool = False
    ok: bool = True
    message: str = ""
    pnpl_point_residuals: np.ndarray = field(default_factory=lambda: _empty((0,)))
    pnpl_line_residuals: np.ndarray = field(default_factory=lambda: _empty((0,)))


@dataclass(frozen=True)
class KeyframeResult:
    """A frame became a keyframe. T_world_cam: (4,4) its pose, or None while no odometry estimates poses."""

    frame_index: int
    keyframe_id: int
    T_world_cam: np.ndarray | None = None
    reason: KeyframeWhy | None = None


@dataclass(frozen=True)
class GraphResult:
    """The keyframe graph after a back-end (or loop) optimisation.

    keyframe_ids: (K,) int; T_world_cam: (K,4,4) their optimised poses. edges: (E,2) int indices into keyframe_ids;
    edge_kind: (E,) int (EdgeKind); zeta: (E,) alignment-quality information weight of each edge (>= 0, larger is more
    trusted; NaN where the edge has none). scale: scale correction applied at this step (1.0 when none).
    """

    frame_index: int
    keyframe_ids: np.ndarray
    T_world_cam: np.ndarray
    edges: np.ndarray = field(default_factory=lambda: _empty((0, 2), int))
    edge_kind: np.ndarray = field(default_factory=lambda: _empty((0,), int))
    zeta: np.ndarray = field(default_factory=lambda: _empty((0,)))
    scale: float = 1.0


@dataclass(frozen=True)
class MapResult:
    """The landmark map after bundle adjustment. points: (N,3), lines: (M,2,3) endpoints, both in the world frame."""

    frame_index: int
    points: np.ndarray
    lines: np.ndarray = field(default_factory=lambda: _empty((0, 2, 3)))


@dataclass(frozen=True)
class LoopResult:
    """A loop candidate and the verdict on it.

    query_keyframe / match_keyframe: keyframe ids; score: bag-of-words similarity; n_inliers: geometric inliers;
    T_match_query: (4,4) relative pose when verified, else None; reason: why accepted or rejected.
    """

    frame_index: int
    query_keyframe: int
    match_keyframe: int
    accepted: bool
    score: float = float("nan")
    n_inliers: int = 0
    T_match_query: np.ndarray | None = None
    reason: str = ""


@dataclass(frozen=True)
class TimingResult:
    """Wall time of each stage that ran for this frame, seconds, by stage name (e.g. "features", "depth")."""

    frame_index: int
    seconds: Mapping[str, float]

    @property
    def total(self) -> float:
        return float(sum(self.seconds.values()))


@dataclass(frozen=True)
class MetricsResult:
    """Any other per-frame numbers worth plotting, by name (e.g. "scale_factor", "ndt_fitness")."""

    frame_index: int
    values: Mapping[str, float]


# What the run's record hands the evaluation (plvo.runtime.worker_stages.RunRecord; plvo_eval.stage_drift, soak)
@dataclass(frozen=True)
class StageSteps:
    """One back-end result: the frames (previous, newest) of its window's last two keyframes and, by stage
    ("tracker", "scale", "ba"), their relative motion T_prev_new (4,4, camera) as that stage left it (what
    plvo_eval.stage_drift and stage_stats judge each stage by)."""

    frames: tuple[int, int]
    steps: dict[str, np.ndarray]


@dataclass(frozen=True)
class CorrectionEvent:
    """An applied loop or global BA correction: its source (plvo.tracking.corrections), the frame of the keyframe
    it was made at and the frame it was applied at, the keyframes the map held, how far it moved them (the most,
    and the newest) in metres, the worker's seconds; for a loop, its query and match keyframes."""

    source: str
    keyframe_frame: int
    applied_at_frame: int
    keyframes: int
    max_move_m: float
    newest_move_m: float
    seconds: float
    query_keyframe: int | None = None
    match_keyframe: int | None = None

    def as_dict(self) -> dict[str, Any]:
        """As the soak's JSON holds it (the loop's keyframes only for a loop)."""
        out = dataclasses.asdict(self)
        return {k: v for k, v in out.items() if v is not None or k not in ("query_keyframe", "match_keyframe")}
