"""Lidar place recognition for the loop closer: each place's local map, matched by map_closures whichever way it
is driven.

The bags of words of ORB and LBD image features find a place only when the camera sees it again the way it saw it
before: a street driven back in the opposite direction shows the camera the other side of everything and is never
found. The lidar sees all around. Every `loop.lidar_place_spacing_m` of driving a keyframe becomes a place node. Its
local map is its scan and the scans of the keyframes before and after it within `loop.lidar_place_reach_m`, placed
by the loop closer's current pose estimates, in the keyframe's lidar frame (z up), thinned to one point a
`loop.lidar_place_voxel_m` voxel and cropped to `loop.lidar_place_radius_m` around it; so a node is queried once
the car is lidar_place_reach_m past it. map_closures (PRBonn's MapClosures, MIT licence; Gupta et al., ICRA 2024)
draws the map from above as a density image (occupied voxels a column), extracts ORB features from it, matches them
with a Hamming binary search tree against every earlier node's and aligns each node with enough matches in 2D by
RANSAC: a place is found in either direction, with a relative pose good to about a metre and a degree. The
candidates are the nodes more than `loop.min_keyframe_gap` keyframes older with at least
`loop.lidar_place_min_inliers` RANSAC inliers, best first; the loop closer verifies them by registering the two
local maps (plvo.loop.map_registration).

Measured on the out-and-back twin of tests/conftest.py (a city street driven out, turned on, and driven back 3.5 m
to the left) and the 150-frame town loop, seven pairs of true revisits: maps reaching 20 m before and after their
keyframe matched with 7-24 inliers (median 14), maps of the last 30 m with 4-23 (median 8), of the last 45 m with
3-19 (median 5); the 70 m crop found twice the inliers of 50 m (ORB leaves out 31 px, 15.5 m, at each border). No
node of another place reached 5 inliers there or on the first 2040 frames of the KITTI 08 twin.
The binary tree's search is approximate, so a match found between two maps alone can be lost among many nodes.

Cost, on the project's 2-core virtual machine while other work loaded it (load 10-15): map_closures seeds each of
its 73 RANSAC draws with a new std::random_device, whose CPUID probes trap to the hypervisor here, ~4 ms for every
stored node that shares three ORB matches with the query; a Hamming threshold of 40 (map_closures' default 50) and a
node every 10 m keep a query to a median 9 ms, 95th percentile 53 ms, at 145 nodes of the KITTI 08 twin (50: 85 and
295 ms). A node's local map takes 20-40 ms more; keyframes that are no node cost a thinning of their scan (~2 ms).
Memory: map_closures keeps each node's density image and ORB features, 52 kB a node on the 08 twin's maps and up to
116 kB on the town's (~15-35 kB a keyframe at KITTI's 3 m a keyframe); this module keeps the thinned scans of the
last RECENT_KEYFRAMES keyframes (the next nodes' maps) and the node list, the older scans stay in the loop closer's
keyframe store on disk.

Determinism: map_closures' RANSAC draws from std::random_device, so its inlier counts and 2D poses may differ
between runs where a node has many ORB matches of which few agree (three runs of the out-and-back twin gave the same
candidates and poses: with few matches the 73 draws see every pair). A candidate's verification does not depend on
the exact 2D pose (plvo.loop.map_registration rounds the registration's fixed point); whether a node near the
inlier threshold is proposed at all may.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from plvo.config import LoopConfig
from plvo.geometry import se3
from plvo.loop.scans import SCAN_UNIT_M, scan_points, thin_scan

log = logging.getLogger(__name__)

# A local map takes at most this many keyframes' scans on either side of its own: 20 m at 1 m a keyframe (a car
# standing still adds more); the newest ones are kept in memory for the next maps.
MAX_SIDE_KEYFRAMES = 20
RECENT_KEYFRAMES = 2 * MAX_SIDE_KEYFRAMES + 2
MIN_MAP_POINTS = 1000  # a local map with fewer points (an empty scan, a tunnel's mouth) is not a place


@dataclass(frozen=True)
class PlaceCandidate:
    """An older keyframe whose place matched: kf_id, map_closures' RANSAC inliers, and T_cand_query (4,4) lidar
    frame of the query -> lidar frame of the candidate from the 2D alignment (about a metre and a degree)."""

    kf_id: int
    inliers: int
    T_cand_query: np.ndarray


@dataclass(frozen=True)
class PlaceQuery:
    """One place node through the place recognition: kf_id its keyframe (lidar_place_reach_m behind the newest),
    node its map_closures id; candidates best first; n_points of its local map; reason: why there is no candidate
    ("" when there is one); time_ms for the local map and the query."""

    kf_id: int
    node: int
    candidates: tuple[PlaceCandidate, ...]
    n_points: int
    reason: str
    time_ms: float


def lidar_pose(T_world_cam: np.ndarray, T_cam_velo: np.ndarray) -> np.ndarray:
    """(4,4) camera pose -> (4,4) T_world_lidar."""
    return np.asarray(T_world_cam, float) @ T_cam_velo


class LocalMaps:
    """Keyframes' local maps, from their stored scans (int16 centimetres, plvo.loop.scans) and the current poses.

    Keeps the thinned scans of the last RECENT_KEYFRAMES keyframes it was given (int16 centimetres, ~40 kB a KITTI
    keyframe), so a place node's map needs no disk read; older keyframes' scans come from `read_scan` (the loop
    closer's keyframe store)."""

    def __init__(self, cfg: LoopConfig, T_cam_velo: np.ndarray | None,
                 read_scan: Callable[[int], np.ndarray | None]) -> None:
        self.cfg = cfg
        self.T_cam_velo = np.eye(4) if T_cam_velo is None else np.asarray(T_cam_velo, float)
        self._read = read_scan
        self._recent: OrderedDict[int, np.ndarray | None] = OrderedDict()  # kf id -> thinned int16 scan

    def remember(self, kf_id: int, scan: np.ndarray | None) -> None:
        """The newest keyframe's stored scan (or None), kept thinned for the next local maps."""
        thin = None if scan is None else self._thin(scan)
        self._recent[int(kf_id)] = None if thin is None else np.round(thin / SCAN_UNIT_M).astype(np.int16)
        while len(self._recent) > RECENT_KEYFRAMES:
            self._recent.popitem(last=False)

    def _thin(self, scan: np.ndarray) -> np.ndarray:
        return thin_scan(scan_points(scan)[:, :3], self.cfg.lidar_place_voxel_m)

    def _scan(self, kf_id: int) -> np.ndarray | None:
        if kf_id in self._recent:
            kept = self._recent[kf_id]
            return None if kept is None else scan_points(kept)
        scan = self._read(kf_id)
        return None if scan is None else self._thin(scan)

    def build(self, k: int, order: Sequence[int], poses: Mapping[int, np.ndarray]) -> np.ndarray:
        """(N,3) float32 local map of keyframe order[k] in its lidar frame: its scan and those of the keyframes
        before and after it in arrival `order` (keyframe ids, up to the newest) while they lie within
        lidar_place_reach_m of it, thinned to lidar_place_voxel_m, within lidar_place_radius_m of it horizontally;
        poses: T_world_cam by id. Empty (0,3) when the keyframe has no scan."""
        cfg = self.cfg
        center = int(order[k])
        scan = self._scan(center)
        if scan is None:
            return np.zeros((0, 3), np.float32)
        T_center = se3.inv(lidar_pose(poses[center], self.T_cam_velo))
        parts = [scan]
        for side in (range(k - 1, max(-1, k - 1 - MAX_SIDE_KEYFRAMES), -1),
                     range(k + 1, min(len(order), k + 1 + MAX_SIDE_KEYFRAMES))):
            for j in side:
                kf = int(order[j])
                T_c_j = T_center @ lidar_pose(poses[kf], self.T_cam_velo)
                if np.linalg.norm(T_c_j[:3, 3]) > cfg.lidar_place_reach_m:
                    break
                other = self._scan(kf)
                if other is not None:
                    parts.append(se3.transform_points(T_c_j, other).astype(np.float32))
        pts = thin_scan(np.concatenate(parts), cfg.lidar_place_voxel_m) if len(parts) > 1 else parts[0]
        r = cfg.lidar_place_radius_m
        return pts[np.einsum("ij,ij->i", pts[:, :2], pts[:, :2]) <= r * r]


class PlaceRecognizer:
    """map_closures over place nodes: a keyframe every lidar_place_spacing_m of driving, queried and added once the
    car is lidar_place_reach_m past it (its local map then reaches as far ahead of it as behind)."""

    def __init__(self, cfg: LoopConfig) -> None:
        self.cfg = cfg
        self._nodes: list[int] = []  # map_closures id -> keyframe id
        self._last_node_m = -np.inf  # distance driven at the last node
        self._next = 0  # arrival index of the next keyframe that may become a node
        self._closures = None
        self.unavailable = ""
        try:
            from map_closures.config import MapClosuresConfig
            from map_closures.map_closures import MapClosures
        except ImportError as exc:  # an optional dependency: the bags of words still work without it
            self.unavailable = f"map_closures is not installed ({exc})"
            log.warning("lidar place recognition off: %s", self.unavailable)
            return
        self._closures = MapClosures(MapClosuresConfig(
            density_map_resolution=cfg.lidar_place_voxel_m, hamming_distance_threshold=cfg.lidar_place_hamming,
            inliers_threshold=cfg.lidar_place_min_inliers))

    def __len__(self) -> int:
        return len(self._nodes)

    def due(self, driven: Sequence[float]) -> list[int]:
        """Arrival indices that become nodes now, given the distance driven to each keyframe so far (m)."""
        out: list[int] = []
        if self._closures is None:
            return out
        while self._next < len(driven) and driven[-1] - driven[self._next] >= self.cfg.lidar_place_reach_m:
            if driven[self._next] - self._last_node_m >= self.cfg.lidar_place_spacing_m:
                out.append(self._next)
                self._last_node_m = driven[self._next]
            self._next += 1
        return out

    def query(self, kf_id: int, local_map: Callable[[], np.ndarray], eligible: Callable[[int], bool]) -> PlaceQuery:
        """Query and add keyframe kf_id (a node `due`): local_map() gives its map; eligible(kf id) says whether a
        candidate is old enough."""
        t0 = time.perf_counter()
        if self._closures is None:
            return PlaceQuery(kf_id, -1, (), 0, self.unavailable, 0.0)
        pts = local_map()
        if len(pts) < MIN_MAP_POINTS:
            return PlaceQuery(kf_id, -1, (), len(pts), f"local map of only {len(pts)} points",
                              1e3 * (time.perf_counter() - t0))
        node = len(self._nodes)
        self._nodes.append(int(kf_id))
        closures = self._closures.get_closures(node, np.asarray(pts, np.float64))
        found = []
        for c in closures:
            ref = int(c.source_id)
            if ref >= node or c.number_of_inliers < self.cfg.lidar_place_min_inliers:
                continue
            kf = self._nodes[ref]
            if not eligible(kf):
                continue
            # map_closures aligns the reference's map onto the query's: its pose is T_query_ref
            T = se3.orthonormalize(se3.inv(np.asarray(c.pose, float)))
            found.append(PlaceCandidate(kf, int(c.number_of_inliers), T))
        found.sort(key=lambda c: (-c.inliers, c.kf_id))
        cands = tuple(found[: self.cfg.max_verify])
        reason = "" if cands else (f"no older place with {self.cfg.lidar_place_min_inliers} density-map inliers "
                                   f"({len(closures)} weaker)")
        return PlaceQuery(kf_id, node, cands, len(pts), reason, 1e3 * (time.perf_counter() - t0))
