"""Small analytic scenes for the depth-prior tests: a KITTI-like camera and HDL-64E, ray cast against a ground
plane, axis-aligned boxes and vertical cylinders (lidar frame: x forward, y left, z up). Imported by the tests of
plvo.depth (tests/plvo/depth/); tests/helpers/test_depth_scene.py checks the ray caster itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from plvo.types import Calibration

# KITTI odometry 04 calib.txt: P0 and Tr (velodyne -> cam0), image 1241x376 as in the odometry benchmark.
K_KITTI = np.array([[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]])
TR_KITTI = np.array(
    [
        [-1.857739385241e-03, -9.999659513510e-01, -8.039975204516e-03, -4.784029760483e-03],
        [-6.481465826011e-03, 8.051860151134e-03, -9.999466081774e-01, -7.337429464231e-02],
        [9.999773098287e-01, -1.805528627661e-03, -6.496203536139e-03, -3.339968064433e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
WIDTH, HEIGHT = 1241, 376
LIDAR_HEIGHT = 1.73
ELEVATIONS_DEG = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])


def kitti_calib() -> Calibration:
    return Calibration(K=K_KITTI.copy(), T_cam_velo=TR_KITTI.copy(), width=WIDTH, height=HEIGHT)


@dataclass
class Scene:
    """Ground z = -LIDAR_HEIGHT, boxes (lo (3,), hi (3,)) and vertical cylinders (cx, cy, r, z0, z1), lidar frame."""

    boxes: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    cylinders: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    ground: bool = True

    def raycast(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(3,) origin, (N,3) directions -> (N,) smallest t > 0 with origin + t dir on a surface (inf if none)."""
        t_best = np.full(len(dirs), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.ground:
                t = (-LIDAR_HEIGHT - origin[2]) / dirs[:, 2]
                t_best = np.where((t > 1e-6) & (t < t_best), t, t_best)
            for lo, hi in self.boxes:
                t1 = (lo - origin) / dirs
                t2 = (hi - origin) / dirs
                tn = np.nanmax(np.minimum(t1, t2), axis=1)
                tf = np.nanmin(np.maximum(t1, t2), axis=1)
                hit = (tn <= tf) & (tn > 1e-6)
                t_best = np.where(hit & (tn < t_best), tn, t_best)
            for cx, cy, r, z0, z1 in self.cylinders:
                ox, oy = origin[0] - cx, origin[1] - cy
                a = dirs[:, 0] ** 2 + dirs[:, 1] ** 2
                b = 2 * (ox * dirs[:, 0] + oy * dirs[:, 1])
                c = ox**2 + oy**2 - r**2
                disc = b * b - 4 * a * c
                t = (-b - np.sqrt(disc)) / (2 * a)
                zt = origin[2] + t * dirs[:, 2]
                hit = (disc >= 0) & (t > 1e-6) & (zt >= z0) & (zt <= z1)
                t_best = np.where(hit & (t < t_best), t, t_best)
        return t_best


def lidar_scan(scene: Scene, az_step_deg: float = 0.09, fov_deg: float = 50.0, noise_m: float = 0.0, seed: int = 0):
    """HDL-64E-like scan of the scene, front sector only -> (N,4) float32 x,y,z,reflectance (lidar frame)."""
    az = np.deg2rad(np.arange(-fov_deg, fov_deg, az_step_deg))
    el = np.deg2rad(ELEVATIONS_DEG)
    A, E = np.meshgrid(az, el)
    dirs = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    t = scene.raycast(np.zeros(3), dirs)
    ok = np.isfinite(t) & (t < 100.0)
    rng = np.random.default_rng(seed)
    r = t[ok] + rng.normal(0.0, noise_m, ok.sum()) if noise_m > 0 else t[ok]
    pts = dirs[ok] * r[:, None]
    return np.concatenate([pts, np.full((len(pts), 1), 0.5)], axis=1).astype(np.float32)


def true_depth(scene: Scene, uv: np.ndarray) -> np.ndarray:
    """(N,2) pixels -> (N,) exact z-depth in cam0 of the first surface hit (inf if none)."""
    T_velo_cam = np.linalg.inv(TR_KITTI)
    rays = np.stack(
        [(uv[:, 0] - K_KITTI[0, 2]) / K_KITTI[0, 0], (uv[:, 1] - K_KITTI[1, 2]) / K_KITTI[1, 1], np.ones(len(uv))], 1
    )
    # Directions with z_cam = 1, so the hit parameter is the z-depth.
    return scene.raycast(T_velo_cam[:3, 3], rays @ T_velo_cam[:3, :3].T)


def to_cam(pts_velo: np.ndarray) -> np.ndarray:
    """(N,3) lidar frame -> (N,3) cam0 frame."""
    return pts_velo @ TR_KITTI[:3, :3].T + TR_KITTI[:3, 3]


def box(x0, x1, y0, y1, z0=-LIDAR_HEIGHT, z1=3.0):
    return (np.array([x0, y0, z0], float), np.array([x1, y1, z1], float))


def street_scene() -> Scene:
    """Ground, a square pillar and a round pole in front of a wall, boxes at 5-40 m, a far wall at 45 m."""
    return Scene(
        boxes=[
            box(8.0, 8.3, -0.15, 0.15, z1=2.0),  # square pillar, front face at x = 8
            box(14.0, 14.3, -4.0, 4.0),  # wall behind the pillar
            box(5.0, 9.0, 3.0, 6.0, z1=1.0),  # low box on the left, 5-9 m
            box(11.0, 13.0, -8.0, -5.0, z1=2.0),  # box on the right, 11-13 m
            box(22.0, 26.0, 5.0, 10.0, z1=4.0),  # building block on the left, 22-26 m
            box(30.0, 33.0, -15.0, -6.0, z1=4.0),  # building block on the right, 30-33 m
            box(45.0, 46.0, -40.0, 40.0, z1=8.0),  # far wall
        ],
        cylinders=[(10.0, 2.0, 0.15, -LIDAR_HEIGHT, 3.0)],
    )


def box_edges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(12,2,3) edges of an axis-aligned box, lidar frame."""
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pairs = [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(c[i] != c[j]) == 1]
    return np.array([[c[i], c[j]] for i, j in pairs])


def visible_segments(scene: Scene, edges_velo: np.ndarray, min_len_px: float = 40.0, step: float = 0.02):
    """(E,2,3) lidar-frame edges -> segments (S,4) px and their cam0 3D edges (S,2,3): the longest visible run of
    each edge (not occluded, inside the image, in front of the camera)."""
    segs, lines3d = [], []
    for a, b in edges_velo:
        n = max(int(np.linalg.norm(b - a) / step), 2)
        s = np.linspace(0.0, 1.0, n)
        P = to_cam(a[None] + s[:, None] * (b - a)[None])
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = P[:, :2] / P[:, 2:3] * np.array([K_KITTI[0, 0], K_KITTI[1, 1]]) + K_KITTI[:2, 2]
        ok = (P[:, 2] > 1.0) & (uv[:, 0] >= 2) & (uv[:, 0] < WIDTH - 2) & (uv[:, 1] >= 2) & (uv[:, 1] < HEIGHT - 2)
        zt = np.full(n, np.inf)
        zt[ok] = true_depth(scene, uv[ok])
        ok &= zt >= P[:, 2] - 0.02  # nothing in front of the edge
        best, cur, start = (0, -1), 0, 0
        for i, o in enumerate(ok):
            if o:
                if cur == 0:
                    start = i
                cur += 1
                if cur > best[1] - best[0] + 1:
                    best = (start, i)
            else:
                cur = 0
        i0, i1 = best
        if i1 <= i0 or np.linalg.norm(uv[i1] - uv[i0]) < min_len_px:
            continue
        segs.append(np.r_[uv[i0], uv[i1]])
        lines3d.append(np.stack([P[i0], P[i1]]))
    return np.array(segs).reshape(-1, 4), np.array(lines3d).reshape(-1, 2, 3)


def ray_line_points(segments: np.ndarray, lines3d: np.ndarray) -> np.ndarray:
    """(S,4) segments, (S,2,3) cam0 3D edges -> (S,2,3) points of each edge on the rays of the segment's ends."""
    out = np.empty((len(segments), 2, 3))
    for i, (seg, (a, b)) in enumerate(zip(segments, lines3d)):
        d = (b - a) / np.linalg.norm(b - a)
        for k in range(2):
            r = np.array([(seg[2 * k] - K_KITTI[0, 2]) / K_KITTI[0, 0],
                          (seg[2 * k + 1] - K_KITTI[1, 2]) / K_KITTI[1, 1], 1.0])
            r /= np.linalg.norm(r)
            A = np.array([[1.0, -(r @ d)], [r @ d, -1.0]])
            s, t = np.linalg.solve(A, [a @ r, a @ d])
            out[i, k] = a + t * d
    return out
