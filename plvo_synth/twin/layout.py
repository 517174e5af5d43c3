"""Where the roads of a twin run, how high the ground is, and what kind of place each stretch is.

Roads are the followed path itself (the road surface CAMERA_HEIGHT_M under cam0, sampled every SAMPLE_M) plus
crossing streets; every later decision queries these samples, never the order in which the car drove them, so a
place looks the same whichever pass (and direction) brings the car there. A stretch's zone (city blocks,
residential streets, country road, highway) is drawn per ZONE_CELL_M square of the world from the mean speed of
all passes through it and a seeded hash of the square.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

SAMPLE_M = 0.5
ZONE_CELL_M = 250.0
CROSS_CELL_M = 110.0  # at most one crossing street per square of this size
CROSS_HALF_M = 120.0  # a crossing street runs this far either side of the path
HEIGHT_SIGMA_M = 3.0  # wide enough to average passes whose ground-truth heights disagree (KITTI's drift)
HEIGHT_NEIGHBOURS = 24
HEIGHT_SOFTMIN_M = 0.5


@dataclass(frozen=True)
class Zone:
    name: str
    half_width: float  # road half-width around the driven path (m)
    building_p: float
    setback: tuple[float, float]  # building front behind the road edge (m)
    depth: tuple[float, float]
    height: tuple[float, float]
    width: tuple[float, float]
    tree_p: float
    parked_p: float
    fence_p: float
    hedge_p: float
    wall_p: float
    lamp_p: float
    sign_p: float
    pole_p: float
    crossing_p: float
    verge: str  # what lies beside the road: "pavement" or "grass"


ZONES: tuple[Zone, ...] = (
    Zone("city", 7.5, 0.95, (0.0, 2.5), (10.0, 16.0), (8.0, 24.0), (8.0, 20.0), 0.35, 0.6, 0.0, 0.0, 0.05,
         0.9, 0.3, 0.0, 0.7, "pavement"),
    Zone("residential", 6.5, 0.75, (4.0, 8.0), (8.0, 12.0), (5.0, 9.0), (8.0, 13.0), 0.6, 0.45, 0.45, 0.45, 0.1,
         0.7, 0.2, 0.0, 0.45, "grass"),
    Zone("country", 5.5, 0.05, (8.0, 20.0), (8.0, 14.0), (4.0, 8.0), (8.0, 16.0), 0.45, 0.0, 0.2, 0.15, 0.1,
         0.0, 0.1, 0.6, 0.1, "grass"),
    Zone("highway", 11.0, 0.0, (15.0, 25.0), (10.0, 16.0), (6.0, 12.0), (10.0, 20.0), 0.25, 0.0, 0.0, 0.0, 0.6,
         0.7, 0.15, 0.0, 0.0, "grass"),
)
ZONE_ID = {z.name: k for k, z in enumerate(ZONES)}
HALF_WIDTHS = np.array([z.half_width for z in ZONES], np.float32)


def _cell_rng(seed: int, tag: int, ix: int, iy: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, tag, ix + (1 << 20), iy + (1 << 20)]))


def _densify(points: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) polyline -> (K,3) points every <= step metres and (K,2) unit tangents (xy)."""
    seg = np.diff(points, axis=0)
    length = np.linalg.norm(seg[:, :2], axis=1)
    keep = length > 1e-3  # stopped frames add nothing
    out = []
    for p, d, ln in zip(points[:-1][keep], seg[keep], length[keep]):
        n = max(1, int(np.ceil(ln / step)))
        out.append(p + (np.arange(n)[:, None] / n) * d)
    if not out:  # a car standing still the whole time: one short stretch of road ahead of it
        return points[:1], np.array([[1.0, 0.0]])
    out.append(points[-1:])
    pts = np.concatenate(out)
    # central differences: the same samples driven the other way get exactly the opposite tangents
    d = np.concatenate([pts[1:2] - pts[:1], pts[2:] - pts[:-2], pts[-1:] - pts[-2:-1]])[:, :2]
    return pts, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _canonical_signs(directions: np.ndarray) -> np.ndarray:
    """(N,2) -> (N,) +1 or -1, the same for a direction and its opposite: the sign that turns it towards larger x
    (or larger y when it has no x)."""
    d = np.asarray(directions, np.float64).reshape(-1, 2)
    return np.where((d[:, 0] > 0.0) | ((d[:, 0] == 0.0) & (d[:, 1] > 0.0)), 1.0, -1.0)


def _canonical_arc(xy: np.ndarray) -> np.ndarray:
    """(K,) arc length of each sample of a polyline, counted from the end with the smaller (x, y): a road and
    the same road driven the other way get the same arc length at each place."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    return arc if (xy[0, 0], xy[0, 1]) <= (xy[-1, 0], xy[-1, 1]) else arc[-1] - arc


class Layout:
    """Road samples (xy, z, unit tangent, zone, whether on the driven path, arc length) and queries over them.

    arc: metres along the road at each sample, the same whichever way it is driven (the driven path from its end
    with the smaller (x, y), a crossing street from its crossing point, signed the same way), which road
    markings are laid out by."""

    def __init__(self, road_points: np.ndarray, speed_xy: np.ndarray, speeds: np.ndarray, seed: int,
                 real: np.ndarray | None = None) -> None:
        """road_points (N,3): the driven road in order; speed_xy (F,2), speeds (F,): where the car drove how fast
        (m/s), for the zones (the whole followed file, so that slices of it agree); real (N,): which road points
        were driven (the others continue the road past the file's ends and give it no height)."""
        self.seed = seed
        road_points = np.asarray(road_points, np.float64)
        pts, tang = _densify(road_points, SAMPLE_M)
        driven = road_points if real is None or not np.any(real) else road_points[np.asarray(real, bool)]
        hpts = _densify(driven, SAMPLE_M)[0]
        frame_of = cKDTree(np.asarray(speed_xy)[:, :2]).query(pts[:, :2])[1]
        speed = np.convolve(speeds, np.ones(41) / 41.0, mode="same") if len(speeds) > 41 else speeds
        zone = self._zones(pts[:, :2], speed[frame_of])
        cross = self._crossings(pts, tang, zone)
        self.xy = np.concatenate([pts[:, :2], cross[0]])
        self.z = np.concatenate([pts[:, 2], cross[1]])
        self.tangent = np.concatenate([tang, cross[2]])
        self.zone = np.concatenate([zone, cross[3]]).astype(np.int8)
        self.on_path = np.concatenate([np.ones(len(pts), bool), np.zeros(len(cross[0]), bool)])
        arc = _canonical_arc(pts[:, :2])
        forward = len(arc) < 2 or arc[-1] >= arc[0]
        self.arc = np.concatenate([arc, cross[5]])
        # the unit direction in which arc grows at each sample
        self.arc_dir = np.concatenate([tang if forward else -tang,
                                       cross[2] * _canonical_signs(cross[2])[:, None]])
        self.crossings = cross[4]  # (C, 5): x, y, z of the crossing point, direction x, y of the street
        self.half_width = HALF_WIDTHS[self.zone]
        self.tree = cKDTree(self.xy)
        # Heights come from the driven frames only: crossing streets and the continuations past the file's ends
        # take the ground's height, never give it (they may cross a road that runs higher or lower).
        self._height_tree = cKDTree(hpts[:, :2])
        self._height_z = hpts[:, 2]
        self.lo = self.xy.min(axis=0)
        self.hi = self.xy.max(axis=0)

    def _zones(self, xy: np.ndarray, speed: np.ndarray) -> np.ndarray:
        cells = np.floor(xy / ZONE_CELL_M).astype(np.int64)
        keys, inv = np.unique(cells, axis=0, return_inverse=True)
        inv = inv.ravel()
        mean_v = np.bincount(inv, speed) / np.bincount(inv)
        zone_of_cell = np.empty(len(keys), np.int8)
        for k, (ix, iy) in enumerate(keys):
            r = _cell_rng(self.seed, 31, int(ix), int(iy)).random()
            v = mean_v[k]  # m/s
            if v > 19.0:
                zone_of_cell[k] = ZONE_ID["highway"]
            elif v > 12.5:
                zone_of_cell[k] = ZONE_ID["country"] if r < 0.75 else ZONE_ID["residential"]
            else:
                zone_of_cell[k] = ZONE_ID["city"] if r < (0.7 if v < 8.0 else 0.45) else ZONE_ID["residential"]
        return zone_of_cell[inv]

    def _crossings(self, pts: np.ndarray, tang: np.ndarray, zone: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Crossing streets: at most one per CROSS_CELL_M square the path runs through, at the path sample nearest
        the square's seeded point, perpendicular to the path there, flat at the crossing's height."""
        cells = np.floor(pts[:, :2] / CROSS_CELL_M).astype(np.int64)
        keys = np.unique(cells, axis=0)
        xy, z, tg, zn, info, arc = [], [], [], [], [], []
        tree = cKDTree(pts[:, :2])
        for ix, iy in keys:
            rng = _cell_rng(self.seed, 32, int(ix), int(iy))
            target = (np.array([ix, iy]) + rng.uniform(0.2, 0.8, 2)) * CROSS_CELL_M
            d, k = tree.query(target)
            if d > 0.5 * CROSS_CELL_M or rng.random() >= ZONES[zone[k]].crossing_p:
                continue
            t = tang[k]
            normal = np.array([-t[1], t[0]])
            s = np.arange(-CROSS_HALF_M, CROSS_HALF_M + 1e-9, 1.0)
            xy.append(pts[k, :2] + s[:, None] * normal)
            z.append(np.full(len(s), pts[k, 2]))
            tg.append(np.repeat(normal[None], len(s), axis=0))
            zn.append(np.full(len(s), zone[k]))
            info.append([*pts[k], *normal])
            arc.append(s * _canonical_signs(normal)[0])
        if not xy:
            return np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), np.zeros(0, np.int8), np.zeros((0, 5)), \
                np.zeros(0)
        return np.concatenate(xy), np.concatenate(z), np.concatenate(tg), np.concatenate(zn), np.array(info), \
            np.concatenate(arc)

    def nearest(self, xy: np.ndarray, upper: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(N,2) -> distance to the nearest road sample and its index (len(self.xy) beyond `upper`)."""
        d, k = self.tree.query(np.asarray(xy, np.float64).reshape(-1, 2), distance_upper_bound=upper)
        return d, k

    def road_coords(self, xy: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,2) points and their nearest road samples (N,) -> metres along the road (arc) and signed metres
        across it (positive to the left of arc_dir), both the same whichever way the road is driven."""
        rel = np.asarray(xy, np.float64).reshape(-1, 2) - self.xy[k]
        d = self.arc_dir[k]
        return self.arc[k] + np.einsum("ij,ij->i", rel, d), d[:, 0] * rel[:, 1] - d[:, 1] * rel[:, 0]

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(N,2) -> ground height: a Gaussian-weighted mean of the nearby road heights (smooth, exact on slopes)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        k = min(HEIGHT_NEIGHBOURS, len(self._height_z))
        d, idx = self._height_tree.query(xy, k=k)
        d, idx = d.reshape(len(xy), k), idx.reshape(len(xy), k)
        w = np.exp(-(d**2 - d[:, :1] ** 2) / (2.0 * HEIGHT_SIGMA_M**2))
        z = self._height_z[idx]
        # A soft minimum: where two passes over one place disagree in height (KITTI's ground truth drifts by
        # metres in 02, 08, 09), the ground follows the lower, so no camera ends up under it (the higher one
        # floats; scene.json lists each frame's camera height above the ground). On one pass it is the
        # weighted mean, lowered by its spread^2 / 2 HEIGHT_SOFTMIN_M (millimetres on a 5 % slope).
        z0 = z.min(axis=1, keepdims=True)
        e = w * np.exp(-(z - z0) / HEIGHT_SOFTMIN_M)
        return z0[:, 0] - HEIGHT_SOFTMIN_M * np.log(e.sum(axis=1) / w.sum(axis=1))

    def clearance(self, xy: np.ndarray) -> np.ndarray:
        """(N,2) -> metres beyond the road edge (negative: on a road)."""
        d, k = self.nearest(xy)
        return d - self.half_width[k]
