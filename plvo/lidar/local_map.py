"""A local map of the recent keyframes' scans in the world frame, and the registration of a new scan to it.

Keyframe-to-keyframe registration measures each keyframe step against one scan, so its heading errors add up
along the trajectory as a random walk; lidar odometry systems (KISS-ICP, CT-ICP) register each scan to a map of
the recent scans instead, whose extent (tens of metres) anchors the heading. `LocalMap` keeps the last
`max_keyframes` keyframes' scans, each downsampled once in its own lidar frame, and places them at the keyframes'
*current* poses whenever it is told them (`place`): the back end's keyframe poses change after every bundle
adjustment and loop correction, and a map built from poses frozen at insertion would disagree with the window it
constrains. Keyframes the caller no longer gives a pose for move rigidly with the oldest one it does give, so the
map follows a correction as a whole. What the map holds depends only on what it was given, in order.

`align` registers a scan to the map: point-to-plane ICP (open3d, a Tukey kernel) from an initial T_world_lidar,
judged as plvo.lidar.registration judges its results (at least min_fitness of the scan's points with a map point
within max_correspondence_m, no jump beyond max_jump_m / max_jump_deg from the guess, and one more iteration from
the result does not move it: converged). Besides the pose it returns the alignment's information: the Gauss-Newton
Hessian J^T W J / sigma^2 of the robust point-to-plane residuals at the result, in the scan's own tangent
(T_world_lidar exp(xi), xi = (rho, phi) in the lidar frame). Its shape says which directions the scene fixes:
along a straight corridor or a featureless highway the forward translation gets a small eigenvalue. Its scale is
that of independent residuals, which neighbouring returns of one surface are not (the registration's real
accuracy is centimetres, the Hessian's a tenth of a millimetre). e_hat, e_bar and zeta are the alignment errors
and weight of plvo.lidar.registration, against the map. `align_best` also starts from a second guess (the back
end's constant-velocity prediction of the lidar) when the first had to be moved suspiciously far.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from plvo.config import BackendConfig, RegistrationConfig
from plvo.errors import PlvoError
from plvo.geometry import se3
from plvo.lidar.registration import zeta_from_errors
from plvo.lidar.voxels import voxel_means

_REG = o3d.pipelines.registration
_NORMAL_NEIGHBOURS = 10  # as plvo.lidar.registration's targets
# A converged ICP barely moves when given one more Gauss-Newton step (plvo.lidar.registration's bounds for NDT).
_SETTLED_M, _SETTLED_DEG = 0.02, 0.1
# How far the registration may move the tracker's pose before another start is tried (align_best): on development
# twin 04 it moves it a median 0.05 deg / 2 cm, at most 0.36 deg / 0.24 m, and 2 keyframes of 103 beyond these.
_SUSPECT_M, _SUSPECT_DEG = 0.25, 0.25


@dataclass(frozen=True)
class MapAlignment:
    """T_world_lidar (4,4) the registered pose of the scan (the initial guess when not converged); information
    (6,6) the alignment's Hessian in the lidar-frame tangent of T_world_lidar exp(xi), (rho, phi) (zeros when not
    converged); e_hat, e_bar metres (NaN when not converged) and zeta as plvo.lidar.registration; fitness the share of
    source points with a map point within max_correspondence_m; n_map the map's points; why: the failure, if any."""

    T_world_lidar: np.ndarray
    information: np.ndarray
    e_hat: float
    e_bar: float
    zeta: float
    converged: bool
    fitness: float
    n_map: int
    time_s: float
    why: str = ""


@dataclass
class _Entry:
    kf_id: int
    T_world_lidar: np.ndarray  # where the map last placed it
    scan: np.ndarray | None  # (N,3) lidar frame, as given, until `downsampled` has used it
    points: np.ndarray | None = None  # (M,3) downsampled to the map's voxel, in the keyframe's own lidar frame
    normals: np.ndarray | None = None  # (M,3) their unit normals, estimated once in that frame

    def downsampled(self, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(points, normals), made on first use: when the back end's worker has nothing else to do (LocalMap.prepare)
        or else at the map's first build after the keyframe was added (~25-35 ms for a KITTI scan, which the next
        keyframe's registration, and at a run's end the run, would otherwise wait for). Whenever they are made, the
        same values."""
        if self.points is None or self.normals is None:
            assert self.scan is not None
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.scan)).voxel_down_sample(voxel_m)
            # a scan's normals move with it: estimated here once, not on the whole map at every placement
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=_NORMAL_NEIGHBOURS))
            self.points, self.normals, self.scan = np.asarray(pc.points), np.asarray(pc.normals), None
        return self.points, self.normals


class LocalMap:
    """The scans of the last `max_keyframes` keyframes (see the module doc); voxel_m is the map's resolution;
    max_source_points: an alignment's source points at most, evenly thinned (BackendConfig.local_map_source_points)."""

    def __init__(self, max_keyframes: int, voxel_m: float, cfg: RegistrationConfig | None = None,
                 max_source_points: int = BackendConfig.local_map_source_points):
        if max_keyframes < 1 or not voxel_m > 0 or max_source_points < 6:
            raise PlvoError(f"local map: max_keyframes must be >= 1, voxel_m > 0 and max_source_points >= 6, got "
                            f"{max_keyframes}, {voxel_m}, {max_source_points}")
        self.max_keyframes, self.voxel_m = int(max_keyframes), float(voxel_m)
        self.max_source_points = int(max_source_points)
        self.cfg = cfg or RegistrationConfig()
        self._entries: list[_Entry] = []
        self._built: tuple[o3d.geometry.PointCloud, cKDTree] | None = None

    @property
    def kf_ids(self) -> list[int]:
        return [e.kf_id for e in self._entries]

    def poses(self) -> dict[int, np.ndarray]:
        """{kf_id: T_world_lidar (4,4)} where the map places each of its keyframes' scans now."""
        return {e.kf_id: e.T_world_lidar.copy() for e in self._entries}

    def __len__(self) -> int:
        return len(self._entries)

    def add(self, kf_id: int, points: np.ndarray, T_world_lidar: np.ndarray) -> None:
        """Insert keyframe kf_id's scan ((N,3) lidar frame, e.g. a registration-prepared cloud's points) at its
        pose; it is downsampled to the map's voxel when a map is first built with it (_Entry.downsampled). The
        oldest keyframes beyond max_keyframes are dropped."""
        pts = np.asarray(points, float)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise PlvoError(f"local map: keyframe {kf_id}'s points must have shape (N,3), got {pts.shape}")
        if self._entries and kf_id <= self._entries[-1].kf_id:
            raise PlvoError(f"local map: keyframe {kf_id} added after keyframe {self._entries[-1].kf_id}")
        self._entries.append(_Entry(int(kf_id), np.array(T_world_lidar, float), np.array(pts[:, :3], float)))
        del self._entries[:-self.max_keyframes]
        self._built = None

    def place(self, kf_ids: np.ndarray, T_world_lidar: np.ndarray) -> None:
        """The current poses (W,4,4) of keyframes kf_ids (W,): the map's scans of those keyframes go there; the
        others move rigidly with the oldest of kf_ids the map holds (unchanged when it holds none of them)."""
        given = {int(k): np.asarray(T, float) for k, T in zip(kf_ids, T_world_lidar)}
        held = [e for e in self._entries if e.kf_id in given]
        if not held:
            return
        anchor = min(held, key=lambda e: e.kf_id)
        carry = given[anchor.kf_id] @ se3.inv(anchor.T_world_lidar)
        for e in self._entries:
            e.T_world_lidar = given[e.kf_id].copy() if e.kf_id in given else carry @ e.T_world_lidar
        self._built = None

    def prepare(self) -> None:
        """Downsample the keyframes' scans that no map was built with yet: what the next registration's map would
        do first, done ahead when there is time for it (BackendCore.idle). Changes no result."""
        for e in self._entries:
            e.downsampled(self.voxel_m)

    def cloud(self) -> o3d.geometry.PointCloud:
        """The map as one world-frame cloud, downsampled to voxel_m, with normals (built once per placement)."""
        return self._build()[0]

    def _build(self) -> tuple[o3d.geometry.PointCloud, cKDTree]:
        if self._built is None:
            if not self._entries:
                raise PlvoError("local map: no keyframe scans to build a map from")
            parts = [(e.T_world_lidar, *e.downsampled(self.voxel_m)) for e in self._entries]
            pts = np.concatenate([se3.transform_points(T, p) for T, p, _ in parts])
            nrm = np.concatenate([n @ T[:3, :3].T for T, _, n in parts])
            # where scans overlap, a voxel's normal is the mean of theirs (their signs are each scan's own: a
            # normal is turned towards its scan's sensor, so two scans' normals of a surface agree in sign); open3d's
            # voxel_down_sample's values, in four fifths of its time (plvo.lidar.voxels)
            means, normals = voxel_means(pts, self.voxel_m, nrm)
            assert normals is not None
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(means))
            pc.normals = o3d.utility.Vector3dVector(normals)
            # sliding-midpoint splits without node shrinking: under half the balanced tree's build time, the same
            # nearest neighbours (exact either way); the tree is rebuilt at every placement, once a keyframe
            self._built = (pc, cKDTree(np.asarray(pc.points), balanced_tree=False, compact_nodes=False))
        return self._built

    def align(self, source: np.ndarray, T_world_lidar_init: np.ndarray) -> MapAlignment:
        """(N,3) source points (lidar frame, downsampled as registration sources are), (4,4) initial T_world_lidar
        -> MapAlignment (see the module doc)."""
        t0 = time.perf_counter()
        init = np.asarray(T_world_lidar_init, float)
        if init.shape != (4, 4) or not np.all(np.isfinite(init)):
            raise PlvoError(f"local map: T_world_lidar_init must be a finite (4,4) matrix, got shape {init.shape}")
        src = np.asarray(source, float)[:, :3]
        if len(src) > self.max_source_points:  # evenly thinned: an ICP iteration costs by the source point
            src = src[np.linspace(0, len(src) - 1, self.max_source_points).astype(int)]
        target, tree = self._build()
        cfg = self.cfg
        T, why = init, ""
        at_bar = None
        normals, q = np.asarray(target.normals), np.asarray(target.points)
        info = np.zeros((6, 6))
        try:
            T = _icp(src, target, init, cfg)
            why = _judge(init, T, cfg)
            if not why:
                at_bar = _matches(src, T, tree, cfg.max_correspondence_m)
                fitness = float(np.mean(at_bar[1])) if len(src) else 0.0
                info, step = _gauss_newton(src, T, at_bar, q, normals, cfg.max_correspondence_m / 2)
                # one more Gauss-Newton step from the result, on the same correspondences: a converged ICP barely
                # moves (what plvo.lidar.registration checks with one more NDT iteration)
                moved_m, moved_deg = float(np.linalg.norm(step[:3])), float(np.degrees(np.linalg.norm(step[3:])))
                if fitness < cfg.min_fitness:
                    why = f"fitness {fitness:.2f} < {cfg.min_fitness}"
                elif moved_m > _SETTLED_M or moved_deg > _SETTLED_DEG:
                    why = f"icp not converged (a further step moves {moved_m:.3f} m, {moved_deg:.2f} deg)"
        except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:  # open3d: RuntimeError on degenerate input
            why = f"icp raised: {exc}"
        n_map = len(target.points)
        if why or at_bar is None:
            return MapAlignment(init, np.zeros((6, 6)), float("nan"), float("nan"), 0.0, False, 0.0, n_map,
                                time.perf_counter() - t0, why)
        at_hat = _matches(src, init, tree, cfg.max_correspondence_m)
        e_bar = _plane_error(at_bar, q, normals, cfg.max_correspondence_m, at_bar[1])
        e_hat = _plane_error(at_hat, q, normals, cfg.max_correspondence_m, at_bar[1])
        return MapAlignment(T, info, e_hat, e_bar, zeta_from_errors(e_hat, e_bar, cfg.zeta_formula), True, fitness,
                            n_map, time.perf_counter() - t0)

    def align_best(self, source: np.ndarray, guesses: list[np.ndarray]) -> MapAlignment:
        """align from the first guess (the tracker's pose); when that fails, or has to move the guess further than
        the tracker's pose is off but for 1 keyframe in 50 on development twin 04 (_SUSPECT_M / _SUSPECT_DEG), also
        from each other guess (the lidar's own prediction) -> the converged alignment with the smallest e_bar.
        A guess that is off by a degree can settle half-way when something moving near the sensor lends its
        surfaces to the wrong pose: on twin 01 run from frame 600, a car overtaking turned the tracker's pose 1.1
        and 1.6 deg at frames 628 and 635, and the registration from it settled 0.57 and 0.97 deg off (the run from
        frame 0 kept a 2 deg heading error from there on); with the prediction tried as well, 0.05 and 0.03 deg."""
        best = self.align(source, guesses[0])
        if best.converged and _within(guesses[0], best.T_world_lidar, _SUSPECT_M, _SUSPECT_DEG):
            return best
        spent = best.time_s
        for guess in guesses[1:]:
            if _within(guess, guesses[0], _SETTLED_M, _SETTLED_DEG):
                continue  # one ICP would settle where the other did
            other = self.align(source, guess)
            spent += other.time_s
            if other.converged and (not best.converged or other.e_bar < best.e_bar):
                best = other
        return dataclasses.replace(best, time_s=spent)


def _within(A: np.ndarray, B: np.ndarray, metres: float, degrees: float) -> bool:
    D = se3.inv(np.asarray(A, float)) @ np.asarray(B, float)
    return bool(np.linalg.norm(D[:3, 3]) <= metres and np.degrees(se3.rotation_angle(D)) <= degrees)


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


def _icp(src: np.ndarray, target: o3d.geometry.PointCloud, init: np.ndarray, cfg: RegistrationConfig) -> np.ndarray:
    """Point-to-plane ICP with a Tukey kernel (as plvo.lidar.registration's fallback) -> T_world_lidar, rounded far
    below its accuracy: open3d's parallel sums differ between identical calls in the last bits, and the back end's
    discrete decisions would amplify that into different runs."""
    est = _REG.TransformationEstimationPointToPlane(_REG.TukeyLoss(k=cfg.max_correspondence_m / 2))
    # stop when an iteration changes the rms by less than 1e-5 of it (open3d's default 1e-6 runs ~2x the iterations
    # for sub-millimetre changes)
    crit = _REG.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-5, max_iteration=cfg.max_iterations)
    res = _REG.registration_icp(_cloud(src), target, cfg.max_correspondence_m, init, est, crit)
    return np.round(np.asarray(res.transformation), 9)


def _judge(init: np.ndarray, T: np.ndarray, cfg: RegistrationConfig) -> str:
    """Why the ICP result T cannot be accepted whatever its fit ("" when it can)."""
    if not np.all(np.isfinite(T)):
        return "icp gave a non-finite transform"
    jump = se3.inv(init) @ T
    if np.linalg.norm(jump[:3, 3]) > cfg.max_jump_m or np.degrees(se3.rotation_angle(jump)) > cfg.max_jump_deg:
        return f"icp jumped {np.linalg.norm(jump[:3, 3]):.2f} m from the initial guess"
    return ""


def _matches(src: np.ndarray, T: np.ndarray, tree: cKDTree, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (T p (N,3), (N,) bool a map point within radius, (N,) its index (clipped))."""
    p = se3.transform_points(T, src)
    dist, idx = tree.query(p, k=1, distance_upper_bound=radius)
    near = np.isfinite(dist)
    return p, near, np.minimum(idx, tree.n - 1)


def _residuals(m: tuple[np.ndarray, np.ndarray, np.ndarray], q: np.ndarray, normals: np.ndarray) -> np.ndarray:
    p, _, idx = m
    return np.einsum("ni,ni->n", normals[idx], p - q[idx])


def _plane_error(m: tuple[np.ndarray, np.ndarray, np.ndarray], q: np.ndarray, normals: np.ndarray, radius: float,
                 subset: np.ndarray) -> float:
    """Mean truncated point-to-plane distance over `subset` (plvo.lidar.registration's e), radius where none."""
    if not np.any(subset):
        return float(radius)
    r = np.where(m[1], np.minimum(np.abs(_residuals(m, q, normals)), radius), radius)
    return float(np.mean(r[subset]))


def _gauss_newton(src: np.ndarray, T: np.ndarray, m: tuple[np.ndarray, np.ndarray, np.ndarray], q: np.ndarray,
                  normals: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """The robust point-to-plane problem at T for source points s (lidar frame), residuals r = n . (T exp(xi) s - q)
    with Tukey weights W (threshold k), sigma^2 their weighted mean square -> (information J^T W J / sigma^2 (6,6),
    the Gauss-Newton step xi (6,) from T). With the normal in the lidar frame m = R^T n, J = [m, s x m] in
    (rho, phi). A problem without six directions' worth of residuals gives zeros and a step of infinity."""
    p, near, idx = m
    n = normals[idx[near]]
    r = np.einsum("ni,ni->n", n, p[near] - q[idx[near]])
    w = np.where(np.abs(r) < k, (1.0 - (r / k) ** 2) ** 2, 0.0)
    if w.sum() <= 6:
        return np.zeros((6, 6)), np.full(6, np.inf)
    n_lidar = n @ T[:3, :3]
    J = np.concatenate([n_lidar, np.cross(src[near], n_lidar)], axis=1)
    H = (J * w[:, None]).T @ J
    step = -np.linalg.lstsq(H, J.T @ (w * r), rcond=None)[0]
    sigma2 = max(float(np.sum(w * r * r) / w.sum()), 1e-8)
    return H / sigma2, step
