"""The street grid and the car's trajectory on it: lane-following routes with rounded turns, stops and loops.

The car keeps to the right lane (LANE_OFFSET_M right of the street's centre line) at CAMERA_HEIGHT_M, turns at
crossings on arcs of TURN_RADIUS_M, and moves by speed * 0.1 s a frame. Without a loop the route is a staircase
(two alternating headings), so it never crosses itself; with a loop it circles a rectangle of blocks and drives
on past its start, revisiting the first street.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.errors import SynthError
from plvo_synth.sensors import CAMERA_HEIGHT_M, FRAME_DT

GRID_HALF = 500  # streets on each side of the origin: 25-45 km of town either way (routes are <= 20 km)
BLOCK_MIN_M, BLOCK_MAX_M = 50.0, 90.0
ROAD_HALF_WIDTH_M = 6.0  # kerb to centre line
LANE_OFFSET_M = 2.0
TURN_RADIUS_M = 8.0
TURN_PROB = 0.35
LOOP_MIN_OVERLAP_M = 30.0  # a loop drives at least this far along the already driven start street
STOP_DECEL, STOP_ACCEL, STOP_HOLD_FRAMES = 4.0, 3.0, 20  # m/s^2, m/s^2, frames standing still


@dataclass(frozen=True)
class StreetGrid:
    """Street centre lines: streets along y at x = xs[i], streets along x at y = ys[j]; index 0 at the origin."""

    xs: np.ndarray  # (2*GRID_HALF+1,) metres, xs[GRID_HALF] = 0
    ys: np.ndarray

    def x(self, i: int) -> float:
        return float(self.xs[i + GRID_HALF])

    def y(self, j: int) -> float:
        return float(self.ys[j + GRID_HALF])


def make_grid(seed: int) -> StreetGrid:
    """Street positions from the seed: block lengths uniform in [BLOCK_MIN_M, BLOCK_MAX_M]."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 1]))

    def axis() -> np.ndarray:
        steps = rng.uniform(BLOCK_MIN_M, BLOCK_MAX_M, 2 * GRID_HALF)
        pos = np.concatenate([[0.0], np.cumsum(steps)])
        return pos - pos[GRID_HALF]

    return StreetGrid(axis(), axis())


class LanePath:
    """A smooth planar path: lines joined by quarter arcs, sampled by arc length s (m)."""

    def __init__(self, centre_vertices: np.ndarray) -> None:
        """(M,2) street-centre polyline (axis-aligned legs) -> the right-lane path with filleted corners."""
        pts = np.asarray(centre_vertices, np.float64)
        dirs = np.diff(pts, axis=0)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        right = np.stack([dirs[:, 1], -dirs[:, 0]], axis=1)
        corners = [pts[0] + LANE_OFFSET_M * right[0]]
        for k in range(1, len(pts) - 1):
            corners.append(pts[k] + LANE_OFFSET_M * (right[k - 1] + right[k]))
        corners.append(pts[-1] + LANE_OFFSET_M * right[-1])
        self._prims: list[tuple] = []  # ("line", p0, d, length) or ("arc", centre, radius, a0, sign, length)
        start = corners[0]
        for k in range(1, len(corners) - 1):
            d1, d2 = dirs[k - 1], dirs[k]
            t1, t2 = corners[k] - TURN_RADIUS_M * d1, corners[k] + TURN_RADIUS_M * d2
            self._line(start, t1)
            sign = 1.0 if d1[0] * d2[1] - d1[1] * d2[0] > 0 else -1.0  # +1: left turn (counter-clockwise)
            centre = t1 + TURN_RADIUS_M * sign * np.array([-d1[1], d1[0]])
            a0 = np.arctan2(t1[1] - centre[1], t1[0] - centre[0])
            self._prims.append(("arc", centre, TURN_RADIUS_M, a0, sign, TURN_RADIUS_M * np.pi / 2))
            start = t2
        self._line(start, corners[-1])
        self.lengths = np.array([p[-1] for p in self._prims])
        self.starts = np.concatenate([[0.0], np.cumsum(self.lengths)])
        self.length = float(self.starts[-1])

    def _line(self, a: np.ndarray, b: np.ndarray) -> None:
        length = float(np.linalg.norm(b - a))
        if length > 1e-9:
            self._prims.append(("line", a, (b - a) / length, length))

    def sample(self, s: np.ndarray) -> np.ndarray:
        """(N,) arc lengths (m) -> (N,3) x, y, yaw (rad, heading from +x towards +y)."""
        s = np.asarray(s, np.float64)
        k = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self._prims) - 1)
        out = np.zeros((len(s), 3))
        for i in np.unique(k):
            m = k == i
            ds = s[m] - self.starts[i]
            prim = self._prims[i]
            if prim[0] == "line":
                _, p0, d, _ = prim
                out[m, :2] = p0 + ds[:, None] * d
                out[m, 2] = np.arctan2(d[1], d[0])
            else:
                _, c, r, a0, sign, _ = prim
                a = a0 + sign * ds / r
                out[m, 0], out[m, 1] = c[0] + r * np.cos(a), c[1] + r * np.sin(a)
                out[m, 2] = a + sign * np.pi / 2
        return out


def staircase_route(grid: StreetGrid, length_m: float, rng: np.random.Generator) -> np.ndarray:
    """(M,2) street-centre polyline at least `length_m` long: +x and one of +-y alternately, never crossing."""
    side = 1 if rng.random() < 0.5 else -1
    i, j, heading = 0, 0, 0  # heading 0: +x, 1: +-y
    pts = [np.array([0.5 * (grid.x(0) + grid.x(1)), grid.y(0)])]
    total, prev = 0.0, pts[0]
    while total < length_m:
        if heading == 0:
            i += 1
            nxt = np.array([grid.x(i), grid.y(j)])
        else:
            j += side
            nxt = np.array([grid.x(i), grid.y(j)])
        total += float(np.linalg.norm(nxt - prev))
        prev = nxt
        if rng.random() < TURN_PROB:
            pts.append(nxt)
            heading = 1 - heading
    if np.linalg.norm(prev - pts[-1]) > 0:
        pts.append(prev)
    return np.array(pts)


def _lap_length(width: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Length of one clockwise lap in the right lane around a width x height rectangle of street centres."""
    return 2.0 * (width + height) - 8.0 * LANE_OFFSET_M - 4.0 * (2.0 - np.pi / 2.0) * TURN_RADIUS_M


def loop_route(grid: StreetGrid, length_m: float) -> tuple[np.ndarray, float]:
    """(M,2) polyline circling the largest block rectangle whose lap leaves LOOP_MIN_OVERLAP_M of revisit; lap (m)."""
    a, b = np.meshgrid(np.arange(1, 40), np.arange(1, 40), indexing="ij")
    widths = grid.xs[GRID_HALF + a] - grid.x(0)
    heights = grid.y(0) - grid.ys[GRID_HALF - b]
    laps = _lap_length(widths, heights)
    ok = laps <= length_m - LOOP_MIN_OVERLAP_M
    if not ok.any():
        raise SynthError(
            f"loop: the route is only {length_m:.0f} m long (n_frames x speed x {FRAME_DT} s), but a lap around the "
            f"smallest block near the start is {laps.min():.0f} m and the loop must then revisit "
            f"{LOOP_MIN_OVERLAP_M:.0f} m: use at least {laps.min() + LOOP_MIN_OVERLAP_M:.0f} m (more frames or speed)"
        )
    k = np.unravel_index(np.argmax(np.where(ok, laps, -np.inf)), laps.shape)
    ia, ib = int(a[k]), int(b[k])
    corners = np.array([[grid.x(ia), grid.y(0)], [grid.x(ia), grid.y(-ib)], [grid.x(0), grid.y(-ib)],
                        [grid.x(0), grid.y(0)]])
    start = np.array([0.5 * (grid.x(0) + grid.x(1)), grid.y(0)])
    n_laps = int(np.ceil((length_m + 50.0) / laps[k])) + 1
    return np.vstack([start[None], np.tile(corners, (n_laps, 1))]), float(laps[k])


def arc_lengths(n_frames: int, speed_mps: float, stops: bool) -> np.ndarray:
    """(n_frames,) distance driven (m) at each frame; with stops, some runs of frames stand exactly still."""
    v = np.full(n_frames, float(speed_mps))
    if stops:
        n_dec = int(np.ceil(speed_mps / STOP_DECEL / FRAME_DT))
        n_acc = int(np.ceil(speed_mps / STOP_ACCEL / FRAME_DT))
        span = n_dec + STOP_HOLD_FRAMES + n_acc
        if n_frames < span + 10:
            raise SynthError(
                f"stops: a stop at {speed_mps:g} m/s takes {span} frames (braking, {STOP_HOLD_FRAMES} still, "
                f"starting); n_frames must be at least {span + 10}"
            )
        n_stops = max(1, n_frames // 300)
        seg = n_frames // n_stops
        for k in range(n_stops):
            f0 = k * seg + max(5, (seg - span) // 2)
            still = f0 + n_dec  # first of STOP_HOLD_FRAMES frames at speed 0
            v[f0:still + 1] = np.linspace(speed_mps, 0.0, n_dec + 1)
            v[still:still + STOP_HOLD_FRAMES] = 0.0
            go = still + STOP_HOLD_FRAMES - 1
            v[go:go + n_acc + 1] = np.linspace(0.0, speed_mps, n_acc + 1)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * FRAME_DT)])
    return s


def camera_poses(path: LanePath, s: np.ndarray) -> np.ndarray:
    """(N,) arc lengths -> (N,4,4) T_town_cam: cam0 level at CAMERA_HEIGHT_M, looking along the lane."""
    xyyaw = path.sample(s)
    c, sn = np.cos(xyyaw[:, 2]), np.sin(xyyaw[:, 2])
    T = np.tile(np.eye(4), (len(s), 1, 1))
    T[:, :3, 0] = np.stack([sn, -c, np.zeros_like(c)], axis=1)  # x right
    T[:, :3, 1] = [0.0, 0.0, -1.0]  # y down
    T[:, :3, 2] = np.stack([c, sn, np.zeros_like(c)], axis=1)  # z forward
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = xyyaw[:, 0], xyyaw[:, 1], CAMERA_HEIGHT_M
    return T
