"""What both viewers (the Rerun recorder and the viser viewer) draw the same way: colours, thinning, the ground
truth moved into the estimate's world, the estimated trajectory that follows the back end's refinements; and the
viewer's SceneStore with `load_rrd`, which fills it from a saved recording (no viser import here)."""

from __future__ import annotations

import bisect
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from plvo.geometry.se3 import inv, transform_points
from plvo.recording import RunInfo
from plvo.results import EDGE_LOOP

GREY, GREEN, RED, ORANGE, CYAN, MAGENTA = (170, 170, 170), (40, 220, 60), (230, 50, 50), (255, 150, 20), \
    (40, 200, 230), (255, 0, 255)
ZETA_FULL = float(np.exp(-2.0))  # the paper's zeta rarely exceeds exp(-2): green from there on


def thin(n: int, budget: int) -> slice:
    """A stride slice keeping at most `budget` of `n` items."""
    return slice(None, None, max(1, -(-n // max(1, budget))))


def depth_colors(z: np.ndarray, near: float = 2.0, far: float = 50.0) -> np.ndarray:
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
    colors[np.asarray(kind) == EDGE_LOOP] = MAGENTA
    return colors


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
    end's refinement of a keyframe moves the frames tracked from it (as plvo.system.System.poses does)."""

    def __init__(self) -> None:
        self.frames: list[int] = []
        self._ref: list[int] = []  # keyframe id, -1 before the first keyframe
        self._p: list[np.ndarray] = []  # (3,) position in the reference keyframe's camera frame
        self.kf_pose: dict[int, np.ndarray] = {}
        self._ref_kf = -1

    def on_tracking(self, frame_index: int, T_world_cam: np.ndarray) -> None:
        T_kf = self.kf_pose.get(self._ref_kf, np.eye(4))
        self.frames.append(int(frame_index))
        self._ref.append(self._ref_kf)
        self._p.append(transform_points(inv(T_kf), np.asarray(T_world_cam, float)[None, :3, 3])[0])

    def on_keyframe(self, kf_id: int, frame_index: int, T_world_cam: np.ndarray) -> None:
        self.kf_pose[int(kf_id)] = np.asarray(T_world_cam, float)
        self._ref_kf = int(kf_id)
        if self.frames and self.frames[-1] == frame_index:  # the keyframe's own frame: its own reference
            self._ref[-1], self._p[-1] = int(kf_id), np.zeros(3)

    def on_graph(self, kf_ids: np.ndarray, T_world_cam: np.ndarray) -> None:
        self.kf_pose.update({int(k): np.asarray(T, float) for k, T in zip(kf_ids, T_world_cam)})

    def positions(self) -> np.ndarray:
        """(N,3) float64 world positions of every frame so far, in order."""
        if not self.frames:
            return np.zeros((0, 3))
        ref, p = np.asarray(self._ref), np.asarray(self._p)
        out = p.copy()
        for k in np.unique(ref[ref >= 0]):
            rows = ref == k
            out[rows] = transform_points(self.kf_pose[int(k)], p[rows])
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


def _unpack_colors(values: list[int]) -> np.ndarray:
    """Rerun's packed 0xRRGGBBAA colours -> (N,3) uint8."""
    c = np.asarray(values, np.uint32)
    return np.stack([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], axis=1).astype(np.uint8)


def load_rrd(path: str | Path) -> SceneStore:
    """Read a plvo .rrd (also one cut short by Ctrl-C) into a SceneStore. See rerun_reader.read_entities."""
    from plvo_app.rrd_reader import read_rrd

    data = read_rrd(path)
    store = SceneStore(name=data.properties.get("plvo:sequence", Path(path).stem))
    pin = data.static.get("/world/camera/image", {})
    if "Pinhole:image_from_camera" in pin:
        store.K = np.asarray(pin["Pinhole:image_from_camera"][0], float).reshape(3, 3).T  # column-major
        store.width, store.height = (int(v) for v in pin["Pinhole:resolution"][0])
    gt = data.static.get("/world/trajectory/gt", {}).get("LineStrips3D:strips")
    if gt:
        store.gt = np.asarray(gt[0], np.float32)
    for f in data.frames():
        store.add_frame(f)
    for f, row in data.rows("/world/camera"):
        store.put("pose", f, _pose_from_row(row))
    for f, row in data.rows("/world/camera/image"):
        if row.get("EncodedImage:blob"):
            store.put("image", f, bytes(row["EncodedImage:blob"][0]))
    lidar = dict(data.rows("/world/lidar"))
    for f, row in data.rows("/world/lidar/scan"):
        T = _pose_from_row(lidar[f]) if f in lidar else np.eye(4)
        pts = np.asarray(row["Points3D:positions"], np.float64).reshape(-1, 3)
        colors = _unpack_colors(row["Points3D:colors"]) if row.get("Points3D:colors") else np.full_like(pts, 200, np.uint8)
        if len(colors) != len(pts):
            colors = np.broadcast_to(colors[:1], pts.shape).copy()
        store.put("scan", f, ((pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32), colors))
    for layer, entity, key in [("map_points", "/world/map/points", "Points3D:positions"),
                               ("keyframes", "/world/keyframes", "Points3D:positions"),
                               ("map_lines", "/world/map/lines", "LineStrips3D:strips"),
                               ("loops", "/world/loops", "LineStrips3D:strips")]:
        for f, row in data.rows(entity):
            if row.get(key) is not None:
                store.put(layer, f, np.asarray(row[key], np.float32))
    for f, row in data.rows("/world/graph"):
        if row.get("LineStrips3D:strips") is not None:
            segs = np.asarray(row["LineStrips3D:strips"], np.float32).reshape(-1, 2, 3)
            colors = _unpack_colors(row["LineStrips3D:colors"]) if row.get("LineStrips3D:colors") else None
            if colors is None or len(colors) != len(segs):
                colors = np.tile(np.array(ORANGE, np.uint8), (len(segs), 1))
            store.put("graph", f, (segs, colors))
    for f, row in data.rows("/world/trajectory/est"):
        if row.get("LineStrips3D:strips"):
            store.put("est", f, np.asarray(row["LineStrips3D:strips"][0], np.float32))
    for f, row in data.rows("/log"):
        if row.get("TextLog:text"):
            store.put("log", f, str(row["TextLog:text"][0]))
    return store


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
    from plvo_app.guards import deferred_signals

    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("wait_for_interrupt needs the main thread (signals)")
    with deferred_signals("") as held:
        held.what = None
        while not held.seen:
            time.sleep(0.2)
