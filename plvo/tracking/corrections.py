"""What workers hand back to the map: typed corrections, and the one rule that applies them.

The back end and the loop closer never write the map. Each reads a snapshot (taken by the System in the tracking
thread, at a fixed point of the run) and returns a `MapCorrection`: the keyframe poses it started from and the ones
it found, the landmarks it refined, the graph edges it measured. `LandmarkMap.apply` applies it, under the map's
lock, from the tracking thread; so the map has one writer, and a run is the same whatever the workers' timing.

While a worker ran, the map may have moved (a loop correction applied while the back end optimised an older
window, or back-end refinements while the loop closer solved its pose graph). The rule (`corrected_poses`):

- a keyframe in the correction: new = M_k T_after_k, where M_k = T_current_k T_before_k^-1 is the motion of that
  keyframe since the snapshot (identity when nothing moved it), so a loop correction applied meanwhile carries the
  back end's window along rather than being undone by it;
- keyframes newer than the correction's newest move rigidly with it (the tracker made them meanwhile);
- a landmark in the correction: M of its creating keyframe (clipped to the correction's keyframes) times its
  refined position; every other landmark moves with its creating keyframe's change (identity for keyframes the
  correction does not touch).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from plvo.geometry import se3
from plvo.results import EdgeKind

BACKEND, LOOP, GLOBAL_BA = "back end", "loop", "global BA"
# the newest keyframe solved again after a back-end result it was tracked without (Frontend.relocalise_keyframe)
RELOCALISED = "relocalised"


def _none(shape: tuple[int, ...], dtype: type = float) -> np.ndarray:
    return field(default_factory=lambda: np.zeros(shape, dtype))


@dataclass(frozen=True)
class GraphEdge:
    """A relative-pose constraint between keyframes i < j: T_i_j (4,4) maps camera j into camera i; zeta its
    information weight (0: unusable); kind EdgeKind.ODOMETRY (a registration) or EdgeKind.LOOP (plvo.results);
    weight and rotation_weight further factors of its translation's and its rotation's information, from the alignment's
    residual (plvo.backend.worker.residual_weight); the optimisations use zeta * weight and zeta * rotation_weight."""

    i: int
    j: int
    T_i_j: np.ndarray
    zeta: float
    kind: EdgeKind
    weight: float = 1.0
    rotation_weight: float = 1.0

    @property
    def information(self) -> float:
        return self.zeta * self.weight

    @property
    def rotation_ratio(self) -> float:
        """The rotation's information against the translation's (rotation_weight / weight)."""
        return self.rotation_weight / self.weight


@dataclass(frozen=True)
class WindowData:
    """What the back end reads of the map for one keyframe: a local window, copied at a fixed point of the run.

    kf_ids (W,) ascending, T_world_cam (W,4,4); point_ids (P,), points (P,3) world; per point observation in the
    window: pt_kf (row into kf_ids), pt_idx (row into point_ids), pt_uv (,2) px, pt_depth (depth prior z, NaN none),
    pt_depth_rms (its plane fit's rms, m; NaN unknown);
    likewise for lines: line_ids (L,), lines (L,2,3), ln_kf, ln_idx, ln_seg (,4), ln_prior (,2,3) camera-frame
    endpoints (NaN none); edges: the graph edges between the window's keyframes; version: the map's.
    """

    kf_ids: np.ndarray
    T_world_cam: np.ndarray
    point_ids: np.ndarray
    points: np.ndarray
    pt_kf: np.ndarray
    pt_idx: np.ndarray
    pt_uv: np.ndarray
    pt_depth: np.ndarray
    line_ids: np.ndarray = _none((0,), np.int64)
    lines: np.ndarray = _none((0, 2, 3))
    ln_kf: np.ndarray = _none((0,), np.int64)
    ln_idx: np.ndarray = _none((0,), np.int64)
    ln_seg: np.ndarray = _none((0, 4))
    ln_prior: np.ndarray = _none((0, 2, 3))
    edges: tuple[GraphEdge, ...] = ()
    version: int = -1
    pt_depth_rms: np.ndarray | None = None


@dataclass(frozen=True)
class GlobalData:
    """What the global bundle adjustment reads of the map: every keyframe (kf_ids (K,), T_world_cam (K,4,4)), every
    graph edge, and the point observations of landmarks two or more keyframes see: landmark (n,), keyframe (n,)
    ids, measurement (n,2) px, depth (n,) prior z or NaN, depth_rms (n,) its plane fit's rms (m, NaN unknown);
    positions (P,3) of np.unique(landmark)."""

    kf_ids: np.ndarray
    T_world_cam: np.ndarray
    edges: tuple[GraphEdge, ...]
    landmark: np.ndarray
    keyframe: np.ndarray
    measurement: np.ndarray
    depth: np.ndarray
    positions: np.ndarray
    version: int = -1
    depth_rms: np.ndarray | None = None


@dataclass(frozen=True)
class MapCorrection:
    """One worker result for the map (or the tracker's relocalisation of its newest keyframe).

    source: BACKEND | LOOP | GLOBAL_BA | RELOCALISED; keyframe_ids (K,) ascending; T_before (K,4,4) the poses the
    worker started from (its snapshot's), T_after (K,4,4) what it found; point_ids (P,) with point_positions (P,3)
    and line_ids (L,) with line_endpoints (L,2,3), world, refined; edges: graph edges to add; base_version: the map
    version of the snapshot (for the log and the tests).
    """

    source: str
    keyframe_ids: np.ndarray
    T_before: np.ndarray
    T_after: np.ndarray
    point_ids: np.ndarray = _none((0,), np.int64)
    point_positions: np.ndarray = _none((0, 3))
    line_ids: np.ndarray = _none((0,), np.int64)
    line_endpoints: np.ndarray = _none((0, 2, 3))
    edges: tuple[GraphEdge, ...] = ()
    base_version: int = -1

    @property
    def moves_poses(self) -> bool:
        return len(self.keyframe_ids) > 0


def corrected_poses(correction: MapCorrection, T_current: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All keyframes' current poses (N,4,4) -> (new poses (N,4,4), per-keyframe change D = new cur^-1 (N,4,4),
    per-correction-keyframe motion since the snapshot M (K,4,4))."""
    T_current = np.asarray(T_current, float)
    n = len(T_current)
    ids = np.asarray(correction.keyframe_ids, np.int64)
    new = T_current.copy()
    if len(ids) == 0:
        eye = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        return new, eye, np.zeros((0, 4, 4))
    ok = ids < n
    ids = ids[ok]
    M = T_current[ids] @ se3.inv_batch(np.asarray(correction.T_before, float)[ok])
    new[ids] = M @ np.asarray(correction.T_after, float)[ok]
    newest = int(ids.max())
    carry = new[newest] @ se3.inv(T_current[newest])
    new[newest + 1:] = carry @ T_current[newest + 1:]
    D = new @ se3.inv_batch(T_current)
    return new, D, M


def move_points(points: np.ndarray, first_kf: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(n,3) world points created by keyframes first_kf (n,) -> moved by those keyframes' changes D (N,4,4)."""
    if len(points) == 0:
        return np.asarray(points, float).reshape(-1, 3)
    return transform_each(D[np.clip(first_kf, 0, len(D) - 1)], points)


def motion_for(first_kf: np.ndarray, keyframe_ids: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Per landmark (n,) creating keyframe -> (n,4,4) the motion since the snapshot of the nearest of the
    correction's keyframes (ascending (K,)) at or below it (the first one for older creators)."""
    row = np.searchsorted(keyframe_ids, first_kf, side="right") - 1
    return M[np.clip(row, 0, len(M) - 1)]


def transform_each(C: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n,4,4) transforms, (n,3) points -> (n,3) each point by its own transform."""
    return np.einsum("nij,nj->ni", C[:, :3, :3], points) + C[:, :3, 3]
