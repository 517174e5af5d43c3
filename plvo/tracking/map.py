"""The landmark map: point and line landmarks, keyframe poses, observations with their depth priors, graph edges.

Everything lives in growable numpy arrays, landmarks in rows sorted by id (ids are never reused; removal clears
the `alive` flag, and `drop_unreachable` deletes the rows of landmarks nothing can use any more, so that memory
follows what is kept, not the length of the run), so the hot paths (gathering the positions of the landmarks seen
in the previous frame) are one binary search and one fancy-indexing call. Observations are flat arrays (landmark
id, keyframe id, feature index, measurement, prior).

One owner, one writer: the tracker adds keyframes, landmarks and observations; the workers (back end, loop closer)
never write it. They read copies taken at fixed points (`window_data`, `global_data`, `poses`) and return typed
`MapCorrection`s, which `apply` writes in one place (plvo.tracking.corrections has the rule). Keyframe poses are
held read-only outside `add_keyframe` and `apply`. Only the tracker's thread touches the map, so it has no lock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.geometry import se3
from plvo.tracking.columns import Columns, LandmarkTable
from plvo.tracking.corrections import (
    GlobalData,
    GraphEdge,
    MapCorrection,
    WindowData,
    corrected_poses,
    motion_for,
    move_points,
    transform_each,
)
from plvo.tracking.point_budget import budget_share, owner_ranks

_DESC_BYTES = 32  # ORB and LBD descriptors are both 256 bits


def _point_store() -> LandmarkTable:
    return LandmarkTable({
        "position": ((3,), np.float64, np.nan), "descriptor": ((_DESC_BYTES,), np.uint8, 0),
        "has_depth": ((), np.bool_, False), "alive": ((), np.bool_, False), "n_obs": ((), np.int32, 0),
        "first_kf": ((), np.int64, -1), "last_kf": ((), np.int64, -1), "last_seen_frame": ((), np.int64, -1),
    })


def _line_store() -> LandmarkTable:
    return LandmarkTable({
        "endpoints": ((2, 3), np.float64, np.nan), "descriptor": ((_DESC_BYTES,), np.uint8, 0),
        "has_depth": ((), np.bool_, False), "alive": ((), np.bool_, False), "n_obs": ((), np.int32, 0),
        "first_kf": ((), np.int64, -1), "last_kf": ((), np.int64, -1), "last_seen_frame": ((), np.int64, -1),
    })


def _obs_store(meas_shape: tuple[int, ...], prior_shape: tuple[int, ...]) -> Columns:
    # prior: the observing keyframe's depth prior of the feature (z for points, camera-frame endpoints for lines);
    # prior_rms: the rms of the lidar returns about the plane a point's prior was fitted to, which weighs it in the
    # bundle adjustments (backend.depth_prior_rms_factor); NaN for lines, whose priors are not weighed by it
    return Columns({
        "landmark": ((), np.int64, -1), "keyframe": ((), np.int64, -1), "feature": ((), np.int64, -1),
        "measurement": (meas_shape, np.float64, np.nan), "prior": (prior_shape, np.float64, np.nan),
        "prior_rms": ((), np.float64, np.nan),
    })


@dataclass(frozen=True)
class MapSnapshot:
    """A consistent copy of the map at `version`.

    point_ids (P,), point_positions (P,3) world, point_has_depth (P,); line_ids (L,), line_endpoints (L,2,3)
    world, line_has_depth (L,); keyframe_ids (F,), keyframe_frames (F,) dataset frame index, keyframe_T_world_cam
    (F,4,4). Only live landmarks are included.
    """

    version: int
    point_ids: np.ndarray
    point_positions: np.ndarray
    point_has_depth: np.ndarray
    line_ids: np.ndarray
    line_endpoints: np.ndarray
    line_has_depth: np.ndarray
    keyframe_ids: np.ndarray
    keyframe_frames: np.ndarray
    keyframe_T_world_cam: np.ndarray


@dataclass(frozen=True)
class Observations:
    """Observations of one landmark kind: landmark (K,), keyframe (K,), feature index (K,), measurement (K,2)
    pixels for points or (K,4) segments for lines."""

    landmark: np.ndarray
    keyframe: np.ndarray
    feature: np.ndarray
    measurement: np.ndarray
    prior: np.ndarray | None = None  # (K,) depth z for points, (K,2,3) camera-frame endpoints for lines; NaN none


class LandmarkMap:
    """Point and line landmarks in the world frame, keyframe poses T_world_cam, and keyframe observations."""

    def __init__(self) -> None:
        self.version = 0
        self._pts = _point_store()
        self._lines = _line_store()
        self._pobs = _obs_store((2,), ())
        self._lobs = _obs_store((4,), (2, 3))
        self._kfs = Columns({"frame": ((), np.int64, -1), "T_world_cam": ((4, 4), np.float64, np.nan)})
        self._kfs.cols["T_world_cam"].flags.writeable = False
        self.edges: list[GraphEdge] = []
        # per keyframe, the number of observation rows when it was made (points, lines): see _window_obs
        self._obs_start: dict[bool, list[int]] = {False: [], True: []}

    # ---- sizes -------------------------------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return int(self._pts["alive"].sum())

    @property
    def n_lines(self) -> int:
        return int(self._lines["alive"].sum())

    @property
    def n_keyframes(self) -> int:
        return self._kfs.n

    # ---- keyframes ---------------------------------------------------------------------------------------
    def add_keyframe(self, frame_index: int, T_world_cam: np.ndarray) -> int:
        """Register a keyframe with its (4,4) pose; returns its id (0, 1, ...)."""
        T = se3.orthonormalize_batch(np.asarray(T_world_cam, float)[None])
        self._kfs.cols["T_world_cam"].flags.writeable = True
        row = self._kfs.append(frame=np.array([frame_index]), T_world_cam=T)
        self._kfs.cols["T_world_cam"].flags.writeable = False
        self._obs_start[False].append(self._pobs.n)
        self._obs_start[True].append(self._lobs.n)
        self.version += 1
        return int(row[0])

    def poses(self) -> np.ndarray:
        """(N,4,4) T_world_cam of every keyframe, by id (a copy)."""
        return self._kfs["T_world_cam"].copy()

    def keyframe_pose(self, kf_id: int) -> np.ndarray:
        """(4,4) T_world_cam of keyframe kf_id (a copy)."""
        return self._kfs["T_world_cam"][kf_id].copy()

    def keyframe_frame(self, kf_id: int) -> int:
        return int(self._kfs["frame"][kf_id])

    # ---- adding landmarks --------------------------------------------------------------------------------
    def add_points(self, positions: np.ndarray, descriptors: np.ndarray, has_depth: np.ndarray, kf_id: int,
                   feature_idx: np.ndarray, uv: np.ndarray, depth: np.ndarray | None = None,
                   depth_rms: np.ndarray | None = None) -> np.ndarray:
        """(n,3) world positions, (n,32) ORB, (n,) bool, keyframe id, (n,) keypoint indices, (n,2) px, optional (n,)
        depth prior z of each and (n,) its plane rms (m) -> (n,) ids. Each new landmark gets its first observation in
        keyframe kf_id.
        """
        positions = np.asarray(positions, dtype=float).reshape(-1, 3)
        n = len(positions)
        ids = self._pts.append(
            position=positions, descriptor=np.asarray(descriptors).reshape(n, _DESC_BYTES),
            has_depth=np.asarray(has_depth, bool).reshape(n), alive=np.ones(n, bool),
            first_kf=np.full(n, kf_id), last_seen_frame=np.full(n, self.keyframe_frame(kf_id) if n else -1),
        )
        self._add_obs(self._pts, self._pobs, ids, kf_id, feature_idx, np.asarray(uv, float).reshape(n, 2), depth,
                      depth_rms)
        return ids

    def add_lines(self, endpoints: np.ndarray, descriptors: np.ndarray, has_depth: np.ndarray, kf_id: int,
                  segment_idx: np.ndarray, segments: np.ndarray, prior: np.ndarray | None = None) -> np.ndarray:
        """(n,2,3) world endpoints, (n,32) LBD, (n,) bool, keyframe id, (n,) segment indices, (n,4), optional
        (n,2,3) camera-frame prior endpoints -> (n,) ids."""
        endpoints = np.asarray(endpoints, dtype=float).reshape(-1, 2, 3)
        n = len(endpoints)
        ids = self._lines.append(
            endpoints=endpoints, descriptor=np.asarray(descriptors).reshape(n, _DESC_BYTES),
            has_depth=np.asarray(has_depth, bool).reshape(n), alive=np.ones(n, bool),
            first_kf=np.full(n, kf_id), last_seen_frame=np.full(n, self.keyframe_frame(kf_id) if n else -1),
        )
        self._add_obs(self._lines, self._lobs, ids, kf_id, segment_idx, np.asarray(segments, float).reshape(n, 4),
                      prior)
        return ids

    def add_point_observations(self, ids: np.ndarray, kf_id: int, feature_idx: np.ndarray, uv: np.ndarray,
                               depth: np.ndarray | None = None, depth_rms: np.ndarray | None = None) -> None:
        """Record that point landmarks ids (k,) were seen in keyframe kf_id at keypoints feature_idx, (k,2) px,
        with (k,) depth priors z (NaN or None: none) and (k,) their plane rms (m)."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        self._add_obs(self._pts, self._pobs, ids, kf_id, feature_idx, np.asarray(uv, float).reshape(-1, 2), depth,
                      depth_rms)

    def add_line_observations(self, ids: np.ndarray, kf_id: int, segment_idx: np.ndarray,
                              segments: np.ndarray, prior: np.ndarray | None = None) -> None:
        """Record that line landmarks ids (k,) were seen in keyframe kf_id as segments (k,4), with (k,2,3)
        camera-frame prior endpoints (NaN or None: none)."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        self._add_obs(self._lines, self._lobs, ids, kf_id, segment_idx, np.asarray(segments, float).reshape(-1, 4),
                      prior)

    def _add_obs(self, store: LandmarkTable, obs: Columns, ids: np.ndarray, kf_id: int, feature_idx: np.ndarray,
                 meas: np.ndarray, prior: np.ndarray | None = None, prior_rms: np.ndarray | None = None) -> None:
        rows, found = store.rows(ids)
        k = int(found.sum())
        if k == 0:
            return
        # A landmark dropped by `drop_unreachable` (never one the tracker still follows) gets no observation.
        values = dict(landmark=ids[found], keyframe=np.full(k, kf_id),
                      feature=np.asarray(feature_idx).reshape(-1)[found], measurement=meas[found])
        if prior is not None:
            values["prior"] = np.asarray(prior, float).reshape(len(ids), *obs.cols["prior"].shape[1:])[found]
        if prior_rms is not None:
            values["prior_rms"] = np.asarray(prior_rms, float).reshape(len(ids))[found]
        obs.append(**values)
        np.add.at(store.cols["n_obs"], rows[found], 1)
        np.maximum.at(store.cols["last_kf"], rows[found], kf_id)
        self.version += 1

    # ---- reading -----------------------------------------------------------------------------------------
    def point_positions(self, ids: np.ndarray) -> np.ndarray:
        """(k,) ids -> (k,3) world positions; NaN for removed landmarks."""
        rows, ok = self._pts.live_rows(ids)
        out = self._pts.cols["position"][rows]
        out[~ok] = np.nan
        return out

    def line_endpoints(self, ids: np.ndarray) -> np.ndarray:
        """(k,) ids -> (k,2,3) world endpoints; NaN for removed landmarks."""
        rows, ok = self._lines.live_rows(ids)
        out = self._lines.cols["endpoints"][rows]
        out[~ok] = np.nan
        return out

    def point_alive(self, ids: np.ndarray) -> np.ndarray:
        return self._pts.live_rows(ids)[1]

    def line_alive(self, ids: np.ndarray) -> np.ndarray:
        return self._lines.live_rows(ids)[1]

    def point_descriptors(self, ids: np.ndarray) -> np.ndarray:
        """(k,) ids of live landmarks -> (k,32) ORB descriptors."""
        return self._pts.cols["descriptor"][self._pts.rows(ids)[0]]

    def line_descriptors(self, ids: np.ndarray) -> np.ndarray:
        """(k,) ids of live landmarks -> (k,32) LBD descriptors."""
        return self._lines.cols["descriptor"][self._lines.rows(ids)[0]]

    def point_observations(self, ids: np.ndarray | None = None) -> Observations:
        """Observations of the given point landmarks (all when None) that are still alive."""
        return self._observations(self._pts, self._pobs, ids)

    def line_observations(self, ids: np.ndarray | None = None) -> Observations:
        return self._observations(self._lines, self._lobs, ids)

    @staticmethod
    def _observations(store: LandmarkTable, obs: Columns, ids: np.ndarray | None) -> Observations:
        lm = obs["landmark"]
        keep = store.live_rows(lm)[1]
        if ids is not None:
            keep &= np.isin(lm, np.asarray(ids, dtype=np.int64))
        return Observations(lm[keep].copy(), obs["keyframe"][keep].copy(), obs["feature"][keep].copy(),
                            obs["measurement"][keep].copy(), obs["prior"][keep].copy())

    def mark_seen(self, point_ids: np.ndarray, line_ids: np.ndarray, frame_index: int) -> None:
        """Stamp the landmarks tracked in frame_index (`drop_unreachable` keeps what was just tracked)."""
        for store, ids in ((self._pts, point_ids), (self._lines, line_ids)):
            rows, found = store.rows(ids)
            store.cols["last_seen_frame"][rows[found]] = frame_index

    # ---- removing and updating ---------------------------------------------------------------------------
    def remove_points(self, ids: np.ndarray) -> None:
        rows, found = self._pts.rows(ids)
        self._pts.cols["alive"][rows[found]] = False
        self.version += 1

    def remove_lines(self, ids: np.ndarray) -> None:
        rows, found = self._lines.rows(ids)
        self._lines.cols["alive"][rows[found]] = False
        self.version += 1

    def drop_unreachable(self, frame_index: int, oldest_reachable_kf: int, min_views: int = 2,
                         global_ba_points: int | None = 0) -> tuple[int, int]:
        """Drop (rows and observations) the landmarks nothing can use any more, and those removed before.

        Unreachable: seen by no keyframe from oldest_reachable_kf on (so in no back-end window or tracker search
        from now on: the caller passes the oldest keyframe any of them may still read) and not tracked in this
        frame or the one before; for points, also in no future global bundle adjustment (which adjusts no lines):
        seen by fewer than min_views keyframes, or, with a budget of global_ba_points (> 0), ranked above the
        share that budget gives each keyframe now (plvo.tracking.point_budget: no later adjustment picks them,
        but for its reprojection gate, which may leave out observations of the points it ranks before them).
        global_ba_points None: there is no global adjustment, 0: it takes every point min_views keyframes see.
        Most landmarks are such: at 900 frames of the town 80 % of the points had one view. Their ids stay valid:
        reads find them gone, as removed ones. Returns the live (points, lines) dropped."""
        counts = []
        for store, obs, lines in ((self._pts, self._pobs, False), (self._lines, self._lobs, True)):
            unreachable = store["alive"] & (store["last_kf"] < oldest_reachable_kf) & (
                store["last_seen_frame"] < frame_index - 1)
            if not lines and global_ba_points is not None:
                unreachable &= ~self._in_global_ba(min_views, global_ba_points)
            counts.append(int(unreachable.sum()))
            drop = unreachable | ~store["alive"]
            if not drop.any():
                continue
            store.keep(~drop)
            keep_obs = store.rows(obs["landmark"])[1]
            if not keep_obs.all():
                kept_before = np.r_[0, np.cumsum(keep_obs)]
                self._obs_start[lines] = kept_before[np.asarray(self._obs_start[lines], np.int64)].tolist()
                obs.keep(keep_obs)
        if any(counts):
            self.version += 1
        return counts[0], counts[1]

    def _in_global_ba(self, min_views: int, max_points: int) -> np.ndarray:
        """(n,) bool over the point rows: those a global bundle adjustment with a budget of max_points (0: none)
        would take now."""
        multi = self._pts["alive"] & (self._pts["n_obs"] >= min_views)
        if max_points <= 0:
            return multi
        rows = np.flatnonzero(multi)
        rank = owner_ranks(self._pts["first_kf"][rows], self._pts["n_obs"][rows], self._pts["id"][rows])
        share = budget_share(rank, max_points)
        if share is None:
            return multi
        picked = np.zeros(self._pts.n, bool)
        picked[rows[rank <= share]] = True  # the share's own rank too: dropping it could raise a later share
        return picked

    def nbytes(self) -> int:
        """Bytes the map's arrays hold (landmarks, observations, keyframes), capacity included."""
        return sum(c.nbytes() for c in (self._pts, self._lines, self._pobs, self._lobs, self._kfs))

    def apply_update(self, point_ids: np.ndarray | None = None, point_positions: np.ndarray | None = None,
                     line_ids: np.ndarray | None = None, line_endpoints: np.ndarray | None = None,
                     keyframe_ids: np.ndarray | None = None, keyframe_T_world_cam: np.ndarray | None = None) -> int:
        """The write of a correction: (k,) ids with (k,3) positions, (l,) ids with (l,2,3) endpoints,
        (f,) keyframe ids with (f,4,4) poses, all world. Removed landmarks are skipped. Returns the new version."""
        if point_ids is not None and len(point_ids):
            rows, ok = self._pts.live_rows(point_ids)
            self._pts.cols["position"][rows[ok]] = np.asarray(point_positions, float).reshape(-1, 3)[ok]
        if line_ids is not None and len(line_ids):
            rows, ok = self._lines.live_rows(line_ids)
            self._lines.cols["endpoints"][rows[ok]] = np.asarray(line_endpoints, float).reshape(-1, 2, 3)[ok]
        if keyframe_ids is not None and len(keyframe_ids):
            ids = np.asarray(keyframe_ids, dtype=np.int64)
            # Re-projected onto SE(3) on every write: workers chain these poses through rigid inverses
            # (transposes), which turn a rotation's tiny non-orthogonality into a larger one each keyframe;
            # unchecked it grew x3 a keyframe, to a 1e-3 scale error in the rotation blocks after ~35
            # keyframes, which squeezed keyframe spacing by a quarter on straight synthetic streets.
            T = np.asarray(keyframe_T_world_cam, float).reshape(-1, 4, 4)
            poses = self._kfs.cols["T_world_cam"]
            poses.flags.writeable = True
            try:
                poses[ids] = se3.orthonormalize_batch(T)
            finally:
                poses.flags.writeable = False
        self.version += 1
        return self.version

    # ---- the one place worker results are written -------------------------------------------------------
    def apply(self, correction: MapCorrection) -> int:
        """Apply a worker's correction (rebasing what moved since its snapshot, see plvo.tracking.corrections):
        keyframe poses, landmarks, graph edges. Returns the new version."""
        self.edges.extend(correction.edges)
        if not correction.moves_poses:
            self.version += 1
            return self.version
        current = self._kfs["T_world_cam"]
        new, D, M = corrected_poses(correction, current)
        kf_ids = np.arange(len(new))
        # Keyframes the correction left exactly where they were (new == current) are not touched, so that a
        # window's correction costs what the window holds, not what the whole map holds.
        changed = np.flatnonzero(np.any(new != current, axis=(1, 2)))
        cids = np.asarray(correction.keyframe_ids, np.int64)
        cids = cids[cids < len(current)]
        pt_ids, pts = self._moved(self._pts, "position", changed, D, correction.point_ids,
                                  correction.point_positions, cids, M)
        ln_ids, lns = self._moved(self._lines, "endpoints", changed, D, correction.line_ids,
                                  correction.line_endpoints, cids, M)
        return self.apply_update(pt_ids, pts, ln_ids, lns, kf_ids[changed], new[changed])

    def _moved(self, store: LandmarkTable, column: str, changed: np.ndarray, D: np.ndarray, ids: np.ndarray,
               refined: np.ndarray, cids: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Landmark ids and new positions: the refined ones rebased by their creator's motion since the snapshot,
        the others created by a changed keyframe moved with it."""
        first = store["first_kf"]  # non-decreasing: landmarks are made by the newest keyframe
        shape = store.cols[column].shape[1:]
        k = int(np.prod(shape)) // 3  # 3D points a landmark: 1 for points, 2 endpoints for lines
        rows, ok = store.live_rows(ids)  # landmarks dropped since the snapshot are left out
        rows, refined = rows[ok], np.asarray(refined, float).reshape(-1, *shape)[ok]
        start = int(np.searchsorted(first, changed.min())) if len(changed) else len(first)
        tail = np.arange(start, len(first))
        tail = tail[store["alive"][start:] & np.isin(first[start:], changed)]
        others = np.setdiff1d(tail, rows)
        moved = move_points(store[column][others].reshape(-1, 3), np.repeat(first[others], k), D)
        if len(rows):
            Mi = motion_for(first[rows], cids, M) if len(M) else np.broadcast_to(np.eye(4), (len(rows), 4, 4))
            refined = transform_each(np.repeat(Mi, k, axis=0), refined.reshape(-1, 3))
        else:
            refined = np.zeros((0, 3))
        out_ids = store["id"][np.r_[others, rows].astype(np.int64)]
        out = np.r_[moved, refined].reshape(-1, *shape)
        return out_ids, out

    def window_data(self, kf_ids: np.ndarray, use_lines: bool = True) -> WindowData:
        """A copy of what a bundle adjustment of keyframes kf_ids (W,) ascending needs (see WindowData)."""
        kf_ids = np.asarray(kf_ids, np.int64)
        T = self._kfs["T_world_cam"][kf_ids].copy()
        pts = self._window_obs(self._pts, self._pobs, "position", kf_ids)
        lns = self._window_obs(self._lines, self._lobs, "endpoints", kf_ids) if use_lines else None
        inside = set(kf_ids.tolist())
        edges = tuple(e for e in self.edges if e.i in inside and e.j in inside)
        version = self.version
        out = dict(kf_ids=kf_ids, T_world_cam=T, point_ids=pts[0], points=pts[1], pt_kf=pts[2], pt_idx=pts[3],
                   pt_uv=pts[4], pt_depth=pts[5], pt_depth_rms=pts[6], edges=edges, version=version)
        if lns is not None:
            out.update(line_ids=lns[0], lines=lns[1], ln_kf=lns[2], ln_idx=lns[3], ln_seg=lns[4], ln_prior=lns[5])
        return WindowData(**out)

    def _window_obs(self, store: LandmarkTable, obs: Columns, column: str, kf_ids: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        # A keyframe's observations are recorded from when it is made on (the triangulation ablation adds some to
        # the keyframe before it then): the window's all lie after its first keyframe's start.
        start = int(self._obs_start[obs is self._lobs][int(kf_ids.min())]) if len(kf_ids) else obs.n
        keep = np.isin(obs["keyframe"][start:], kf_ids)
        keep &= store.live_rows(obs["landmark"][start:])[1]
        rows = start + np.flatnonzero(keep)
        ids, idx = np.unique(obs["landmark"][rows], return_inverse=True)
        return (ids, store[column][store.rows(ids)[0]], np.searchsorted(kf_ids, obs["keyframe"][rows]), idx,
                obs["measurement"][rows].copy(), obs["prior"][rows].copy(), obs["prior_rms"][rows].copy())

    def global_data(self, min_views: int = 2) -> GlobalData:
        """A copy of every keyframe, every graph edge and the point observations of landmarks min_views or more
        keyframes see (what the global bundle adjustment after a loop needs)."""
        lm, kf = self._pobs["landmark"], self._pobs["keyframe"]
        rows, keep = self._pts.live_rows(lm)
        counts = np.bincount(rows[keep], minlength=self._pts.n)
        keep &= counts[rows] >= min_views
        ids = np.unique(lm[keep])
        return GlobalData(
            kf_ids=np.arange(self._kfs.n), T_world_cam=self._kfs["T_world_cam"].copy(), edges=tuple(self.edges),
            landmark=lm[keep].copy(), keyframe=kf[keep].copy(), measurement=self._pobs["measurement"][keep].copy(),
            depth=self._pobs["prior"][keep].copy(), depth_rms=self._pobs["prior_rms"][keep].copy(),
            positions=self._pts["position"][self._pts.rows(ids)[0]],
            version=self.version)

    def point_ids_and_first_keyframes(self) -> tuple[np.ndarray, np.ndarray]:
        """Live point landmark ids (P,) and the keyframe that created each (P,)."""
        alive = self._pts["alive"]
        return self._pts["id"][alive], self._pts["first_kf"][alive]

    def snapshot(self) -> MapSnapshot:
        """A frozen, consistent copy of the live landmarks and all keyframe poses."""
        pa, la = self._pts["alive"], self._lines["alive"]
        return MapSnapshot(
            version=self.version,
            point_ids=self._pts["id"][pa], point_positions=self._pts["position"][pa].copy(),
            point_has_depth=self._pts["has_depth"][pa].copy(),
            line_ids=self._lines["id"][la], line_endpoints=self._lines["endpoints"][la].copy(),
            line_has_depth=self._lines["has_depth"][la].copy(),
            keyframe_ids=np.arange(self._kfs.n), keyframe_frames=self._kfs["frame"].copy(),
            keyframe_T_world_cam=self._kfs["T_world_cam"].copy(),
        )
