"""The camera's motion checked against the lidar's: a scan-to-scan registration of the same interval, on demand.

A camera and a lidar see the same motion twice. The tracker asks the lidar (plvo.tracking.frontend) at every
keyframe and whenever the visual estimate has reason to be doubted: a step far from the motion model's, a rescue or
a loss, a gap in the frame times, an image identical to the previous one (and at the first step, with no motion
model yet, a quick look first). A keyframe's quick look costs ~5 ms on KITTI 04, a thorough registration ~20-40 ms,
so none is done at frames nothing calls into doubt.

Registration: point-to-plane ICP (open3d, Tukey kernel) on scans downsampled to `crosscheck.voxel_m`, a wide pass
(correspondences up to 3 voxels) then a tight one (1 voxel), from each guess in turn (the camera's motion, the
motion model's, standing still), the best fitness kept. Measured on the real frames of KITTI 04 three frames
apart (4.0 m): 1.5 m voxels find the motion from standing still (4.03 m) in ~22 ms after ~8 ms of downsampling a
scan; 0.5 m voxels do not (1.58 m, fitness 0.44): a wide first pass at coarse voxels is what reaches large steps.

Degeneracy: the tight pass's point-to-plane normals constrain translation along the eigenvectors of sum(n n^T);
where the smallest eigenvalue is below `crosscheck.degenerate_ratio` of the largest (a tunnel, a road across an
open field: nothing but the ground and parallel walls), the lidar cannot say how far the car went and the camera
is kept.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from plvo.config import CrossCheckConfig
from plvo.geometry import se3

if TYPE_CHECKING:
    import logging

_REG = o3d.pipelines.registration


@dataclass(frozen=True)
class LidarMotion:
    """The lidar's registration of one interval: T_camprev_camcur (4,4) the camera's motion it implies; fitness the
    share of source points with a target within a voxel; rmse_m their point-to-plane residual; conditioning the
    smallest over the largest eigenvalue of the translation's information (degenerate below the config's ratio);
    time_s wall time spent."""

    T_camprev_camcur: np.ndarray
    fitness: float
    rmse_m: float
    conditioning: float
    usable: bool
    time_s: float
    # the motion between the scans' own instants, where T_camprev_camcur is moved to the images' (a stated time
    # offset: Frontend._lidar_motion); None: the same
    T_as_taken: np.ndarray | None = None

    @property
    def rotation_as_taken(self) -> np.ndarray:
        """(3,3) the rotation between the scans as they were taken (what the time offset is estimated from)."""
        return (self.T_camprev_camcur if self.T_as_taken is None else self.T_as_taken)[:3, :3]

    @property
    def step_m(self) -> float:
        return float(np.linalg.norm(self.T_camprev_camcur[:3, 3]))


def disagreement(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two relative motions."""
    D = se3.inv(T_a) @ T_b
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])), float(np.degrees(se3.rotation_angle(D)))


def agrees(T_camera: np.ndarray, lidar: LidarMotion, cfg: CrossCheckConfig) -> bool:
    """The camera's motion within the check's tolerance of the lidar's: agree_m plus agree_share of the step in
    translation, agree_deg in rotation."""
    dm, ddeg = disagreement(T_camera, lidar.T_camprev_camcur)
    return dm <= cfg.agree_m + cfg.agree_share * lidar.step_m and ddeg <= cfg.agree_deg


class LidarOdometer:
    """Scan-to-scan registrations in the camera's frame; keeps the last few downsampled scans by frame index."""

    def __init__(self, T_cam_velo: np.ndarray, cfg: CrossCheckConfig):
        self.cfg = cfg
        self._T_cam_velo = np.asarray(T_cam_velo, float)
        self._T_velo_cam = se3.inv(self._T_cam_velo)
        # each scan downsampled once for each grade of check it takes part in: thorough or quick (_GRADES)
        self._cache: dict[bool, dict[int, o3d.geometry.PointCloud]] = {True: {}, False: {}}

    def _prepared(self, index: int, scan: np.ndarray, thorough: bool = True) -> o3d.geometry.PointCloud:
        cache = self._cache[thorough]
        cloud = cache.get(index)
        if cloud is None:
            returns, neighbours = _GRADES[thorough]
            xyz = np.asarray(scan[:: max(1, len(scan) // returns), :3], float)
            r2 = np.einsum("ij,ij->i", xyz, xyz)
            xyz = xyz[(r2 > self.cfg.min_range_m ** 2) & (r2 < self.cfg.max_range_m ** 2)]
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz)).voxel_down_sample(self.cfg.voxel_m)
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(neighbours))
            if len(cache) >= 4:
                cache.pop(min(cache))
            cache[index] = cloud
        return cloud

    def _icp(self, a: o3d.geometry.PointCloud, b: o3d.geometry.PointCloud, init: np.ndarray, radius: float
             ) -> o3d.pipelines.registration.RegistrationResult:
        return _REG.registration_icp(a, b, radius, init, _REG.TransformationEstimationPointToPlane(
            _REG.TukeyLoss(k=radius / 3 if radius > self.cfg.voxel_m else radius / 2)), _CONVERGED)

    def motion(self, src: tuple[int, np.ndarray], dst: tuple[int, np.ndarray], guesses: list[np.ndarray],
               thorough: bool = True) -> LidarMotion:
        """The camera's motion from frame src to frame dst ((index, scan) each) as the two scans register, from
        the guesses (camera motions T_camsrc_camdst). thorough: from each guess a wide pass then a tight one, the
        best fitness kept (for a motion in doubt, which may be metres from every guess); else one tight pass from
        the first guess (a keyframe's check, where the camera's motion is usually right; the tracker follows a
        disagreeing quick look with a thorough one, plvo.tracking.frontend.Frontend._check)."""
        t0 = time.perf_counter()
        a, b = self._prepared(*src, thorough), self._prepared(*dst, thorough)
        v = self.cfg.voxel_m
        best = None
        # a keyframe's quick look moves a thinned source (its ICP costs by the source point: ~800 of ~3000 a third)
        src_points = a if thorough or len(a.points) <= _QUICK_SOURCE else \
            a.uniform_down_sample(int(np.ceil(len(a.points) / _QUICK_SOURCE)))
        for guess in guesses if thorough else guesses[:1]:
            # open3d's transformation maps the source (src scan) onto the target (dst scan): T_velodst_velosrc
            init = self._T_velo_cam @ se3.inv(np.asarray(guess, float)) @ self._T_cam_velo
            if thorough:
                init = self._icp(a, b, init, 3 * v).transformation
            tight = self._icp(src_points, b, init, v)
            if best is None or tight.fitness > best.fitness:
                best = tight
        assert best is not None
        T_dst_src = np.asarray(best.transformation, dtype=np.float64)
        # A rigid motion, made so: a calibration's rotation is rigid only to its printed digits (KITTI's Tr to ~1e-7)
        # and an ICP keeps its initial guess's departure from a rotation, so where the lidar's motions follow one
        # another (a frozen camera, the camera overruled frame after frame) each guess, made from the last answer,
        # would carry that departure into the next answer and it grew (2e-4 after 36 frozen frames of real 04;
        # a rotation of 1e22 after 20 overruled frames of the realistic twin of 08, where the run then ended)
        T_cam = se3.orthonormalize(self._T_cam_velo @ se3.inv(T_dst_src) @ self._T_velo_cam)
        # the conditioning only matters where the lidar is to overrule the camera: computed for thorough checks
        cond = _conditioning(a, b, T_dst_src, v) if thorough else float("nan")
        usable = best.fitness >= self.cfg.min_fitness and not cond < self.cfg.degenerate_ratio \
            and bool(np.isfinite(T_cam).all())
        return LidarMotion(T_cam, float(best.fitness), float(best.inlier_rmse), cond, bool(usable),
                           time.perf_counter() - t0)


_CONVERGED = _REG.ICPConvergenceCriteria(relative_fitness=1e-4, relative_rmse=1e-4, max_iteration=30)
# A scan thinned to about this many returns before its 1.5 m voxels, and the neighbours of their normals, for a
# thorough check (True) and a keyframe's quick look (False). ~30 000 returns are plenty for 1.5 m voxels (a quarter
# of an HDL-64E's: 4x cheaper, within 3 cm) and 10 neighbours a voxel's plane (20 within 4.5 m cost 1.2 ms more a
# scan, the same answers). The quick look, at every keyframe, only has to tell a camera within 0.3 m + 10 % and
# 1.5 deg of the lidar from one that is not (a disagreement is looked at again thoroughly): on the real frames of
# KITTI 04, 16 keyframe intervals 3 frames apart, from the truth's motion put 0.11 m and 0.17 deg off, 12 000
# returns, 6 neighbours and 800 source points come within 0.07 m (largest 0.12) and 0.08 deg (0.18) of the truth,
# as the thorough grade's scans did with a 1500-point source (0.09 m, largest 0.14, and 0.08 deg, 0.12), in ~5 ms
# a keyframe against ~10 (single-threaded, beside other work)
_GRADES = {True: (30000, 10), False: (12000, 6)}
_QUICK_SOURCE = 800


def _conditioning(src: o3d.geometry.PointCloud, dst: o3d.geometry.PointCloud, T_dst_src: np.ndarray,
                  radius: float) -> float:
    """Smallest over largest eigenvalue of sum(n n^T) over the matched target normals: how well the matched planes
    pin the translation in every direction (0: a direction free, as along a tunnel)."""
    pts = np.asarray(src.points)
    pts = pts[:: max(1, len(pts) // 2000)] @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]
    dist, idx = cKDTree(np.asarray(dst.points)).query(pts, distance_upper_bound=radius)
    n = np.asarray(dst.normals)[idx[np.isfinite(dist)]]
    if len(n) < 10:
        return 0.0
    w = np.linalg.eigvalsh(n.T @ n)
    return float(w[0] / w[-1]) if w[-1] > 0 else 0.0


# Where a frame's pose came from (FrontendResult.source, timings.json's frames_by_source)
CAMERA = "camera"
CAMERA_SEEDED = "camera, seeded by the lidar"
LIDAR = "lidar"
PREDICTION = "motion model"  # tracking lost and the lidar could not tell: the constant-velocity prediction
SOURCES = (CAMERA, CAMERA_SEEDED, LIDAR, PREDICTION)


def mean_abs_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute grey difference of two images on every 4th pixel of every 4th row (a frozen camera's repeat
    gives 0, sensor noise alone 1-3 grey levels); inf when their sizes differ."""
    if a.shape != b.shape:
        return float("inf")
    return float(np.abs(a[::4, ::4].astype(np.int16) - b[::4, ::4].astype(np.int16)).mean())


def same_scan(a: np.ndarray, b: np.ndarray) -> bool:
    """The same scan twice (a driver's repeat): equal sizes and equal points."""
    return a.shape == b.shape and np.array_equal(a[:: max(1, len(a) // 4096)], b[:: max(1, len(b) // 4096)])


@dataclass
class Episode:
    """Consecutive frames with one finding (kind) and what was done about it."""

    kind: str
    first: int
    last: int
    detail: str

    def describe(self) -> str:
        frames = f"frame {self.first}" if self.first == self.last else f"frames {self.first}-{self.last}"
        return f"{frames}: {self.kind}; {self.detail}"


class CheckLog:
    """The run's cross-check findings: each frame's source, and episodes (consecutive frames of one kind), each
    warned once, as one line naming its frames, when it ends."""

    def __init__(self, logger: logging.Logger):
        self._log = logger
        self.by_source = {s: 0 for s in SOURCES}
        self.counts: dict[str, int] = {}
        self.episodes: list[Episode] = []
        self._open: dict[str, Episode] = {}

    def source(self, source: str) -> None:
        self.by_source[source] += 1

    def note(self, frame: int, kind: str, detail: str) -> None:
        """A finding at frame; joins the open episode of its kind when that ended at the frame before."""
        self.counts[kind] = self.counts.get(kind, 0) + 1
        ep = self._open.get(kind)
        if ep is not None and ep.last >= frame - 1:
            ep.last, ep.detail = frame, detail if ep.first == frame else ep.detail
            return
        if ep is not None:
            self._close(kind)
        self._open[kind] = Episode(kind, frame, frame, detail)

    def frame_done(self, frame: int) -> None:
        """Close the episodes that did not reach this frame."""
        for kind in [k for k, ep in self._open.items() if ep.last < frame]:
            self._close(kind)

    def flush(self) -> None:
        for kind in list(self._open):
            self._close(kind)

    def _close(self, kind: str) -> None:
        ep = self._open.pop(kind)
        self.episodes.append(ep)
        self._log.warning("%s", ep.describe())

    def summary(self) -> dict:
        """frames_by_source, findings (frames per kind) and episodes, as timings.json holds them."""
        return {"frames_by_source": dict(self.by_source), "findings": dict(self.counts),
                "episodes": [{"kind": e.kind, "frames": [e.first, e.last], "detail": e.detail}
                             for e in self.episodes + list(self._open.values())]}
