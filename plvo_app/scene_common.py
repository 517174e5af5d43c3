"""What both viewers (the Rerun recorder and the viser viewer) draw the same way: colours, thinning, the ground
truth moved into the estimate's world, the estimated trajectory that follows the back end's refinements; and the
live viewer's SceneStore (a saved recording is replayed from plvo_app.rrd_index.load_rrd's store; no viser import
here)."""

from __future__ import annotations

import bisect
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from plvo.geometry.se3 import inv, transform_points
from plvo.recording import RunInfo
from plvo.results import EdgeKind
from plvo_app.guards import deferred_signals

GREY, GREEN, RED, ORANGE, CYAN, MAGENTA = (170, 170, 170), (40, 220, 60), (230, 50, 50), (255, 150, 20), \
    (40, 200, 230), (255, 0, 255)
MAP_POINT = (70, 70, 90)  # the map's points in the viser viewer (dark: under the scan's colours)
ZETA_FULL = float(np.exp(-2.0))  # the paper's zeta rarely exceeds exp(-2): green from there on
DEPTH_NEAR, DEPTH_FAR = 2.0, 50.0  # metres: the ends of the depth colour scale (depth_colors)


def thin(n: int, budget: int) -> slice:
    """A stride slice keeping at most `budget` of `n` items."""
    return slice(None, None, max(1, -(-n // max(1, budget))))


def simplify_polyline(p: np.ndarray, tolerance: float, budget: int) -> np.ndarray:
    """Indices of the vertices of polyline p (N,3) that keep it within `tolerance` of itself (Ramer-Douglas-Peucker),
    at most `budget` of them (then strided): a road's straight stretch needs its two ends, a bend keeps its points,
    where a stride spends as many on the straights as on the bends. All the spans of one depth at once: a whole
    sequence's 4541 positions to 513 in ~5 ms, a span at a time took 18."""
    p = np.asarray(p, np.float64)
    n = len(p)
    keep = np.zeros(n, bool)
    keep[[0, -1]] = True
    while True:
        kept = np.flatnonzero(keep)
        inner = np.flatnonzero(~keep)
        if not len(inner):
            break
        span = np.searchsorted(kept, inner) - 1  # the kept vertices on either side of each other one
        a, b = p[kept[span]], p[kept[span + 1]]
        d, q = b - a, p[inner] - a
        t = np.clip(np.einsum("ij,ij->i", q, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
        dist = np.linalg.norm(q - t[:, None] * d, axis=1)  # to the segment, not its line: a U-turn folds back
        starts = np.r_[0, np.flatnonzero(np.diff(span)) + 1]
        most = np.maximum.reduceat(dist, starts)
        if not (most > tolerance).any():
            break
        sizes = np.diff(np.r_[starts, len(dist)])
        at = np.flatnonzero((dist == np.repeat(most, sizes)) & np.repeat(most > tolerance, sizes))
        keep[inner[at[np.r_[True, span[at][1:] != span[at][:-1]]]]] = True  # the farthest vertex of each such span
    idx = np.flatnonzero(keep)
    if len(idx) > budget:
        idx = np.union1d(idx[thin(len(idx), budget - 1)], idx[-1:])
    return idx


def depth_colors(z: np.ndarray, near: float = DEPTH_NEAR, far: float = DEPTH_FAR) -> np.ndarray:
    """(N,) depths -> (N,3) uint8 colours, near red to far blue (turbo)."""
    t = np.clip((np.log(np.maximum(z, near)) - np.log(near)) / (np.log(far) - np.log(near)), 0, 1)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return lut[(255 * (1 - t)).astype(np.uint8)]


def zeta_colors(zeta: np.ndarray, kind: np.ndarray) -> np.ndarray:
    """(E,) zeta and edge kinds -> (E,3) uint8: red (0, no factor) through yellow to green (>= exp(-2)); loops
    magenta; NaN (no registration) grey. A fixed scale, so that a colour means the same all along a run."""
    z = np.asarray(zeta, float)
    t = np.clip(np.nan_to_num(z, nan=0.0) / ZETA_FULL, 0, 1)
    colors = np.stack([255 * np.clip(2 - 2 * t, 0, 1), 220 * np.clip(2 * t, 0, 1), 40 + 0 * t], 1).astype(np.uint8)
    colors[np.isnan(z)] = GREY
    colors[np.asarray(kind) == EdgeKind.LOOP] = MAGENTA
    return colors


_EMPTY = 1 << 16  # RangeFaces.encode's empty pixel, above every uint16 count


@dataclass(frozen=True)
class RangeFaces:
    """A keyframe's scan thinned for every recording level: z-buffered into the depth images of `n` virtual pinhole
    cameras around the lidar (each `360/n` degrees wide, `up`/`down` degrees above and below the horizon, pixels
    `deg` degrees at the centre), stored as 16-bit PNGs of `unit`-metre counts.

    Why images rather than thinned points: a point costs 12 bytes as Rerun's float32 positions and LZ4 compresses
    them hardly at all (a KITTI scan voxel-thinned to 3 m kept 1369 points in 16 kB), while the PNGs of the depth
    images hold ~3700 KITTI points in ~3.0 kB (2 degrees; 6500 in 6.4 kB at 1.5 degrees, 5 cm), and Rerun draws a
    depth image under a pinhole as points in 3D. What is lost: a point's direction is its pixel's (up to half a
    pixel off: 0.9 m at 50 m) and its depth is rounded to `unit`, to 2 units beyond `coarse_beyond` metres (there half
    a pixel is about a unit wide: the depth errs by no more than the direction; on KITTI 04 the points' distance
    to the scan went from a median 0.100 m to 0.105, 95th percentile 0.45 m either way, and the PNGs 7 % smaller);
    of the points of a pixel only the nearest is kept. Each PNG is packed by zlib's run-length strategy (lossless:
    3165 bytes a KITTI 04 keyframe, against 3327 by the default strategy, 3213 filtered, 3158 the smallest of the
    three each time, which took ten times as long; _PNG_RLE)."""

    n: int = 4
    deg: float = 2.0
    unit: float = 0.1
    up: float = 15.0  # covers Velodyne HDL-64 (+2..-25), HDL-32 (+10..-30) and VLP-16 (+-15)
    down: float = 30.0
    coarse_beyond: float = 5.0  # metres; half a 2-degree pixel is 0.09 m wide at 5 m
    # Points projected at most (a stride through the scan): this runs in the tracking thread at every keyframe, and a
    # 2-degree pixel holds ~100 of an HDL-64's 120k points, ~25 of every 4th. On KITTI 04 (with another job on the
    # machine) the whole scan took 19-22 ms, 30000 points 8-9 ms for 5 % more bytes (3150 against 3000) and 1 % fewer
    # pixels; 15000 points 7 ms for 15 % more bytes
    max_points: int = 30000

    @property
    def K(self) -> np.ndarray:
        f = 1.0 / np.tan(np.radians(self.deg))
        w, _ = self.size
        return np.array([[f, 0.0, w / 2], [0.0, f, self._rows_up()], [0.0, 0.0, 1.0]])

    def _rows_up(self) -> int:
        f, half = 1.0 / np.tan(np.radians(self.deg)), np.pi / self.n
        return int(np.ceil(np.tan(np.radians(self.up)) / np.cos(half) * f))  # a face's corners see furthest up

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of a face's image."""
        f, half = 1.0 / np.tan(np.radians(self.deg)), np.pi / self.n
        down = int(np.ceil(np.tan(np.radians(self.down)) / np.cos(half) * f))
        return 2 * int(np.ceil(np.tan(half) * f)), self._rows_up() + down

    def R_velo_face(self, k: int) -> np.ndarray:
        """(3,3) face k's camera axes (RDF: x right, y down, z forward) in the lidar frame (x forward, y left, z up);
        face 0 looks forward, the next ones turn left."""
        a = 2 * np.pi * k / self.n
        return np.column_stack([[np.sin(a), -np.cos(a), 0.0], [0.0, 0.0, -1.0], [np.cos(a), np.sin(a), 0.0]])

    def counts(self, z: np.ndarray) -> np.ndarray:
        """Depths (m) -> the PNG's uint16 counts: `unit` steps, 2 of them beyond `coarse_beyond` (0: no return)."""
        z = np.asarray(z, float)
        far = z > self.coarse_beyond
        c = np.where(far, 2 * np.round(z / (2 * self.unit)), np.round(z / self.unit))
        return np.clip(c, 1, 65535).astype(np.uint16)

    def returns(self, scan: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """(N,3) lidar-frame points -> for each face, the (K,) pixels (row-major) its returns land in and their
        (K,) depth counts: the scan thinned to max_points, each face projecting only its sector's points (and a
        margin: its image reaches a little past it)."""
        K, (w, h) = self.K, self.size
        f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
        pts = np.asarray(scan[thin(len(scan), self.max_points), :3], float)
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
        # a face's own points are at least 0.5 m in front of it (its camera's z); its camera coordinates are taken
        # from R_velo_face's columns (the face's right and forward axes horizontal, down the lidar's -z) term by term
        # rather than by a matrix product: the same PNG bytes on 202 scans (real KITTI 04, the realistic twin 05,
        # raw drive 0009), the whole encoding 2.7 ms of CPU a scan against 4.5
        margin = np.sqrt(x * x + y * y) * np.cos(min(np.pi / self.n + np.radians(3.0 * self.deg), np.pi))
        np.maximum(margin, 0.5, out=margin)
        out = []
        for k in range(self.n):
            right, down, ahead = self.R_velo_face(k).T
            forward = x * ahead[0] + y * ahead[1]
            sel = np.flatnonzero(forward > margin)
            zc = forward[sel]
            u = np.floor((x[sel] * right[0] + y[sel] * right[1]) / zc * f + cx).astype(np.int64)
            v = np.floor(z[sel] * down[2] / zc * f + cy).astype(np.int64)
            inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
            out.append((v[inside] * w + u[inside], self.counts(zc[inside])))
        return out

    def encode(self, scan: np.ndarray) -> list[bytes]:
        """(N,3) lidar-frame points -> one 16-bit PNG a face (0: no return in that pixel)."""
        w, h = self.size
        out = []
        for pixel, count in self.returns(scan):
            # the nearest point of each pixel: its smallest count, by an unbuffered minimum in uint32 (numpy's fast
            # path wants one dtype; 2^16, above every count, marks an empty pixel): the same images as sorting the
            # (pixel, count) keys, the whole encoding 2.2 ms a KITTI 04 keyframe against 3.0
            img = np.full(h * w, _EMPTY, np.uint32)
            np.minimum.at(img, pixel, count.astype(np.uint32))
            img[img == _EMPTY] = 0
            out.append(cv2.imencode(".png", img.astype(np.uint16).reshape(h, w), _PNG_RLE)[1].tobytes())
        return out


# A face is mostly empty pixels between runs of returns: zlib's run-length strategy packs it as well as the best of
# the default, filtered and run-length strategies (KITTI 04's keyframes: 3165 bytes against 3158 a keyframe) in a
# tenth of their time (0.23 ms against 5 ms a keyframe, in the tracking thread)
_PNG_RLE = [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]


def depth_image_points(png: bytes, K: np.ndarray, meter: float) -> np.ndarray:
    """A 16-bit depth PNG (counts, `meter` counts a metre) under pinhole K -> (N,3) camera-frame points, at the
    pixels' centres (how Rerun draws it)."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        return np.zeros((0, 3))
    v, u = np.nonzero(img)
    z = img[v, u].astype(float) / meter
    x = (u + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (v + 0.5 - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1)


def inlier_colors(inlier: np.ndarray) -> np.ndarray:
    return np.where(np.asarray(inlier, bool)[:, None], np.array(GREEN, np.uint8), np.array(RED, np.uint8))


def gt_in_estimate_world(info: RunInfo) -> np.ndarray | None:
    """(N,4,4) ground truth moved into the estimate's world (cam0 at the first frame that runs), or None.

    The dataset's ground truth is in cam0 of the sequence's frame 0; a run of frames A:B starts its estimate at
    identity in frame A's cam0, so both are drawn in the same place only after this change."""
    if info.gt_T_world_cam is None or not len(info.gt_T_world_cam):
        return None
    gt = np.asarray(info.gt_T_world_cam, float)
    T_cam0_cam = np.asarray(info.calib.T_cam0_cam, float)
    return T_cam0_cam @ inv(gt[0]) @ gt


class EstimateTrail:
    """Every frame's estimated position, kept in the frame of the keyframe it was tracked from, so that the back
    end's refinement of a keyframe moves the frames tracked from it (as plvo.runtime.system.System.poses does)."""

    def __init__(self) -> None:
        self.frames: list[int] = []
        self._ref: list[int] = []  # keyframe id, -1 before the first keyframe
        self._p: list[np.ndarray] = []  # (3,) position in the reference keyframe's camera frame
        self.kf_pose: dict[int, np.ndarray] = {}
        self._ref_kf = -1
        self._version = 0  # bumped by every change, for the cached positions
        self._cache: dict[str, tuple[int, np.ndarray]] = {}

    def cached_positions(self) -> np.ndarray:
        """positions(), recomputed only after a change (a viewer draws it far more often than it changes)."""
        hit = self._cache.get("p")
        if hit is None or hit[0] != self._version:
            self._cache["p"] = hit = (self._version, self.positions().astype(np.float32))
        return hit[1]

    def cached_keyframe_positions(self) -> np.ndarray:
        hit = self._cache.get("k")
        if hit is None or hit[0] != self._version:
            self._cache["k"] = hit = (self._version, self.keyframe_positions().astype(np.float32))
        return hit[1]

    def on_tracking(self, frame_index: int, T_world_cam: np.ndarray) -> None:
        T_kf = self.kf_pose.get(self._ref_kf, np.eye(4))
        p = transform_points(inv(T_kf), np.asarray(T_world_cam, float)[None, :3, 3])[0]
        self._version += 1
        self.frames.append(int(frame_index))
        self._ref.append(self._ref_kf)
        self._p.append(p)

    def on_keyframe(self, kf_id: int, frame_index: int, T_world_cam: np.ndarray) -> None:
        self.kf_pose[int(kf_id)] = np.asarray(T_world_cam, float)
        self._version += 1
        self._ref_kf = int(kf_id)
        if self.frames and self.frames[-1] == frame_index:  # the keyframe's own frame: its own reference
            self._ref[-1], self._p[-1] = int(kf_id), np.zeros(3)

    def on_graph(self, kf_ids: np.ndarray, T_world_cam: np.ndarray) -> None:
        self.kf_pose.update({int(k): np.asarray(T, float) for k, T in zip(kf_ids, T_world_cam)})
        self._version += 1

    def positions(self) -> np.ndarray:
        """(N,3) float64 world positions of every frame so far, in order."""
        # Ctrl-C raises anywhere in a step, also between the appends above: the rows all three lists have
        n = min(len(self.frames), len(self._ref), len(self._p))
        if not n:
            return np.zeros((0, 3))
        ref, p = np.asarray(self._ref[:n]), np.asarray(self._p[:n])
        out = p.copy()
        has = ref >= 0
        if has.any():  # all at once: 4541 frames of 1514 keyframes in 1.9 ms, a loop over keyframes took 48 ms
            ids = np.unique(ref[has])
            T = np.stack([self.kf_pose[int(k)] for k in ids])[np.searchsorted(ids, ref[has])]
            out[has] = np.einsum("nij,nj->ni", T[:, :3, :3], p[has]) + T[:, :3, 3]
        return out

    def keyframe_positions(self) -> np.ndarray:
        """(K,3) keyframe positions, by id."""
        return np.array([self.kf_pose[k][:3, 3] for k in sorted(self.kf_pose)]).reshape(-1, 3)


@dataclass
class SceneStore:
    """What the viewer can show, by frame. Thread-safe; each layer is a time series with latest-at lookup.

    Layers: "pose" (4,4) T_world_cam; "image" JPEG bytes; "scan" ((N,3) float32 world, (N,3) uint8); "map_points"
    (N,3); "map_lines" (M,2,3); "keyframes" (K,3); "graph" ((E,2,3), (E,3) uint8 colours by zeta); "loops" (L,2,3);
    "est" (T,3); "log" str.
    Static: gt (G,3) positions, K (3,3), width, height, name.
    """

    frames: list[int] = field(default_factory=list)
    layers: dict[str, tuple[list[int], list[Any]]] = field(default_factory=dict)
    gt: np.ndarray | None = None
    K: np.ndarray | None = None
    width: int = 0
    height: int = 0
    name: str = ""
    lock: threading.RLock = field(default_factory=threading.RLock)

    def clear(self) -> None:
        """Drop every frame and layer (a run started again); the statics stay."""
        with self.lock:
            self.frames.clear()
            self.layers.clear()

    def add_frame(self, frame_index: int) -> None:
        with self.lock:
            if not self.frames or frame_index > self.frames[-1]:
                self.frames.append(frame_index)
            elif frame_index not in self.frames:
                bisect.insort(self.frames, frame_index)

    def put(self, layer: str, frame_index: int, value: Any) -> None:
        with self.lock:
            keys, values = self.layers.setdefault(layer, ([], []))
            if keys and frame_index == keys[-1]:
                values[-1] = value
            elif not keys or frame_index > keys[-1]:
                keys.append(frame_index)
                values.append(value)
            else:
                i = bisect.bisect_left(keys, frame_index)
                if i < len(keys) and keys[i] == frame_index:
                    values[i] = value
                else:
                    keys.insert(i, frame_index)
                    values.insert(i, value)

    def latest(self, layer: str, frame_index: int) -> Any:
        """The value of `layer` at or before `frame_index`, or None."""
        with self.lock:
            keys, values = self.layers.get(layer, ([], []))
            i = bisect.bisect_right(keys, frame_index)
            return values[i - 1] if i else None

    def count(self, layer: str) -> int:
        with self.lock:
            return len(self.layers.get(layer, ([], []))[0])

    def value_at(self, layer: str, frame_index: int) -> Any:
        """The value put at exactly `frame_index`, or None."""
        with self.lock:
            keys, values = self.layers.get(layer, ([], []))
            i = bisect.bisect_left(keys, frame_index)
            return values[i] if i < len(keys) and keys[i] == frame_index else None

    def replace(self, layer: str, frame_index: int, value: Any) -> None:
        """Swap the value at `frame_index` (e.g. for a thinned one) without changing which frames have one."""
        with self.lock:
            keys, values = self.layers.get(layer, ([], []))
            i = bisect.bisect_left(keys, frame_index)
            if i < len(keys) and keys[i] == frame_index:
                values[i] = value


def _pose_from_row(row: dict[str, Any]) -> np.ndarray:
    T = np.eye(4)
    if row.get("Transform3D:mat3x3"):
        T[:3, :3] = np.asarray(row["Transform3D:mat3x3"][0], float).reshape(3, 3).T  # Rerun stores column-major
    if row.get("Transform3D:translation"):
        T[:3, 3] = np.asarray(row["Transform3D:translation"][0], float)
    return T


def wait_for_interrupt() -> None:
    """Block until Ctrl-C or SIGTERM: the servers run in background threads and stay up for inspection meanwhile.

    The signal is taken by a handler rather than as a KeyboardInterrupt, which could land before a `try` is
    entered (and a viewer quit this way would then report "interrupted")."""
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("wait_for_interrupt needs the main thread (signals)")
    with deferred_signals("") as held:
        held.what = None
        while not held.seen:
            time.sleep(0.2)
