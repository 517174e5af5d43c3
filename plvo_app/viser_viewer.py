"""The viser web viewer: live during a run (`ViserRecorder`) and replay of a saved .rrd (`load_rrd`).

Both fill a `SceneStore` (per-frame layers with Rerun's latest-at semantics) that `ViserViewer` shows on
127.0.0.1: a frame slider with play/pause, layer toggles, the camera frustum with its image. It thins what it
shows (never what is recorded) so that it stays responsive on a whole sequence; positions are sent as float32
(float16 quantises at KITTI's hundreds of metres). World frame: RDF (OpenCV camera convention), so up is -y.
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import viser
import viser.transforms as vtf

from plvo.recording import RunInfo
from plvo.types import Frame
from plvo_app.rerun_recorder import GREEN, ORANGE, depth_colors, thin

log = logging.getLogger(__name__)

# layer name -> (GUI label, shown by default)
LAYERS = {
    "scan": ("scan", True),
    "map_points": ("map points", True),
    "map_lines": ("map lines", True),
    "graph": ("keyframe graph", True),
    "loops": ("loops", True),
    "gt": ("ground truth", True),
    "est": ("estimate", True),
    "camera": ("camera", True),
}


@dataclass(frozen=True)
class ViewLimits:
    """How much the browser is sent at most, per layer."""

    scan_points: int = 30000
    map_points: int = 60000
    lines: int = 5000
    trajectory_points: int = 3000
    image_width: int = 480


@dataclass
class SceneStore:
    """What the viewer can show, by frame. Thread-safe; each layer is a time series with latest-at lookup.

    Layers: "pose" (4,4) T_world_cam; "image" JPEG bytes; "scan" ((N,3) float32 world, (N,3) uint8); "map_points"
    (N,3); "map_lines" (M,2,3); "keyframes" (K,3); "graph" (E,2,3); "loops" (L,2,3); "est" (T,3); "log" str.
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


def _jpeg_small(image: np.ndarray, width: int) -> bytes:
    h, w = image.shape[:2]
    if w > width:
        image = cv2.resize(image, (width, round(h * width / w)), interpolation=cv2.INTER_AREA)
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()


class ViserViewer:
    """Serves a SceneStore on host:port. `live=True` adds a "follow live" toggle that tracks the newest frame."""

    def __init__(self, store: SceneStore, host: str = "127.0.0.1", port: int = 8080, live: bool = False,
                 limits: ViewLimits | None = None, frustum_scale: float = 1.5):
        self.store = store
        self.limits = limits or ViewLimits()
        self.frustum_scale = frustum_scale
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("-y")
        self.shown_frame: int | None = None  # the dataset frame on screen
        self._lock = threading.RLock()
        self._handles: dict[str, Any] = {}
        self._camera_placed = False
        self._stop = threading.Event()
        self._build_gui(live)
        self._player = threading.Thread(target=self._play_loop, name="viser-play", daemon=True)
        self._player.start()
        self.refresh()

    @property
    def port(self) -> int:
        return self.server.get_port()

    # ---- GUI -----------------------------------------------------------------------------------------------
    def _build_gui(self, live: bool) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="medium")
        with gui.add_folder("Playback"):
            self.slider = gui.add_slider("frame", min=0, max=max(1, len(self.store.frames) - 1), step=1, initial_value=0)
            self.play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
            self.fps = gui.add_slider("frames/s", min=1, max=30, step=1, initial_value=10)
            self.follow = gui.add_checkbox("follow live", live, visible=live)
            self.status = gui.add_markdown("")
        with gui.add_folder("Layers"):
            self.toggles = {k: gui.add_checkbox(label, on) for k, (label, on) in LAYERS.items()}
        self.playing = False
        self.slider.on_update(lambda _: self._on_slider())
        self.play.on_click(lambda _: self._toggle_play())
        for box in self.toggles.values():
            box.on_update(lambda _: self.show(self.slider.value, force=True))

    def _on_slider(self) -> None:
        if self.follow.value and self.slider.value < len(self.store.frames) - 1:
            self.follow.value = False  # the user went back in time: stop following
        self.show(self.slider.value)

    def _toggle_play(self) -> None:
        self.playing = not self.playing
        self.play.label = "Pause" if self.playing else "Play"
        self.play.icon = viser.Icon.PLAYER_PAUSE if self.playing else viser.Icon.PLAYER_PLAY

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            time.sleep(1.0 / max(1, self.fps.value))
            n = len(self.store.frames)
            if self.playing and n:
                self.slider.value = (int(self.slider.value) + 1) % n

    def refresh(self) -> None:
        """New frames arrived: extend the slider; when following, jump to the newest."""
        n = len(self.store.frames)
        if n == 0:
            return
        self.slider.max = max(1, n - 1)
        if self.follow.value:
            self.slider.value = n - 1  # triggers show through on_update
        if self.shown_frame is None or self.follow.value:
            self.show(int(self.slider.value), force=True)

    # ---- scene ---------------------------------------------------------------------------------------------
    def show(self, position: int, force: bool = False) -> None:
        """Draw the scene as it was at slider position `position` (index into store.frames)."""
        with self._lock:
            frames = self.store.frames
            if not frames:
                return
            f = frames[int(np.clip(position, 0, len(frames) - 1))]
            if f == self.shown_frame and not force:
                return
            if not self._camera_placed:
                self._place_camera(f)
            with self.server.atomic():
                self._draw(f)
            self.shown_frame = f  # after drawing: readers of shown_frame see a finished scene
            self.status.content = self._status_text(f, int(position))

    def _place_camera(self, f: int) -> None:
        """Start the browser's view above and behind the first camera pose, looking down the road."""
        T = self.store.latest("pose", f)
        if T is None:
            return
        forward, up = T[:3, 2], -T[:3, 1]  # camera z forward, y down
        cam = self.server.initial_camera
        cam.position = tuple(T[:3, 3] - 18.0 * forward + 14.0 * up)
        cam.look_at = tuple(T[:3, 3] + 12.0 * forward)
        cam.up = tuple(up)
        self._camera_placed = True

    def _status_text(self, f: int, position: int) -> str:
        msg = self.store.latest("log", f) or ""
        return f"**{self.store.name}** frame **{f}** ({position + 1}/{len(self.store.frames)})  \n{msg}"

    def _set(self, key: str, visible: bool, make) -> None:
        """Replace scene node `key` by make() when visible, else hide it."""
        handle = self._handles.pop(key, None)
        if handle is not None:
            handle.remove()
        if visible:
            handle = make()
            if handle is not None:
                self._handles[key] = handle

    def _draw(self, f: int) -> None:
        s, lim, on = self.store, self.limits, {k: b.value for k, b in self.toggles.items()}
        scene = self.server.scene
        scan = s.latest("scan", f)
        self._set("scan", on["scan"] and scan is not None, lambda: scene.add_point_cloud(
            "/scan", scan[0][thin(len(scan[0]), lim.scan_points)], scan[1][thin(len(scan[0]), lim.scan_points)],
            point_size=0.05, precision="float32", point_shape="circle"))
        pts = s.latest("map_points", f)
        self._set("map_points", on["map_points"] and pts is not None and len(pts), lambda: scene.add_point_cloud(
            "/map/points", pts[thin(len(pts), lim.map_points)], (70, 70, 90), point_size=0.1, precision="float32",
            point_shape="circle"))
        self._segments("map_lines", "/map/lines", s.latest("map_lines", f), on["map_lines"], (40, 200, 230))
        self._segments("graph", "/graph", s.latest("graph", f), on["graph"], (255, 170, 0))
        kfs = s.latest("keyframes", f)
        self._set("keyframes", on["graph"] and kfs is not None and len(kfs), lambda: scene.add_point_cloud(
            "/keyframes", np.asarray(kfs, np.float32), ORANGE, point_size=0.4, precision="float32", point_shape="circle"))
        self._segments("loops", "/loops", s.latest("loops", f), on["loops"], (255, 0, 255), 0.15)
        self._polyline("gt", "/trajectory/gt", s.gt, on["gt"], ORANGE)
        self._polyline("est", "/trajectory/est", s.latest("est", f), on["est"], GREEN)
        self._camera(f, on["camera"])

    def _segments(self, key: str, name: str, segs: np.ndarray | None, visible: bool, color, width: float = 0.05):
        ok = visible and segs is not None and len(segs) > 0
        self._set(key, ok, lambda: self.server.scene.add_line_segments(
            name, np.asarray(segs, np.float32)[thin(len(segs), self.limits.lines)], color, thickness=width))

    def _polyline(self, key: str, name: str, pts: np.ndarray | None, visible: bool, color) -> None:
        if pts is None or len(pts) < 2:
            self._set(key, False, lambda: None)
            return
        p = np.asarray(pts, np.float32)
        p = np.vstack([p[thin(len(p), self.limits.trajectory_points)], p[-1:]])
        self._segments(key, name, np.stack([p[:-1], p[1:]], axis=1), visible, color, 0.15)

    def _camera(self, f: int, visible: bool) -> None:
        s = self.store
        T = s.latest("pose", f)
        if T is None or s.K is None:
            self._set("camera", False, lambda: None)
            return
        jpeg = s.latest("image", f)
        image = None
        if jpeg is not None:
            image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR_RGB)
            image = cv2.resize(image, (self.limits.image_width, round(image.shape[0] * self.limits.image_width
                                                                       / image.shape[1])))
        fov = 2 * np.arctan2(s.height / 2, s.K[1, 1])
        self._set("camera", visible, lambda: self.server.scene.add_camera_frustum(
            "/camera", fov=float(fov), aspect=s.width / s.height, scale=self.frustum_scale, image=image,
            format="jpeg", color=(40, 220, 60), wxyz=vtf.SO3.from_matrix(T[:3, :3]).wxyz, position=T[:3, 3]))

    def close(self) -> None:
        self._stop.set()
        self.server.stop()


class ViserRecorder:
    """A Recorder feeding a live ViserViewer: converts stage results into SceneStore layers as they come."""

    def __init__(self, viewer: ViserViewer, min_interval_s: float = 0.1):
        self.viewer = viewer
        self.store = viewer.store
        self.min_interval_s = min_interval_s
        self._frame: Frame | None = None
        self._pose: np.ndarray | None = None
        self._pose_from_gt = False
        self._est: list[np.ndarray] = []
        self._keyframes: dict[int, np.ndarray] = {}
        self._loops: list[np.ndarray] = []
        self._last_refresh = 0.0

    def on_run_start(self, info: RunInfo) -> None:
        s = self.store
        s.name, s.K, s.width, s.height = info.name, info.calib.K, info.calib.width, info.calib.height
        if info.gt_T_world_cam is not None:
            s.gt = np.asarray(info.gt_T_world_cam)[:, :3, 3].astype(np.float32)
        self._pose_from_gt = not info.extra.get("has_odometry", True)

    def on_frame(self, frame: Frame) -> None:
        self._frame = frame
        self.store.put("image", frame.index, _jpeg_small(frame.image, 2 * self.viewer.limits.image_width))
        if self._pose_from_gt and frame.gt_T_world_cam is not None:
            self._pose = np.asarray(frame.gt_T_world_cam, float)
            self.store.put("pose", frame.index, self._pose)
        self.store.add_frame(frame.index)
        now = time.monotonic()
        if now - self._last_refresh >= self.min_interval_s:
            self._last_refresh = now
            self.viewer.refresh()

    def on_stage(self, frame_index: int, result: Any) -> None:
        known = ("TrackingResult", "KeyframeResult", "MapResult", "GraphResult", "LoopResult")
        # along the MRO: a stage may hand a richer subclass (the tracker's FrontendResult)
        name = next((c.__name__ for c in type(result).__mro__ if c.__name__ in known), "")
        s = self.store
        if name == "TrackingResult":
            self._pose_from_gt = False
            self._pose = np.asarray(result.T_world_cam, float)
            s.put("pose", frame_index, self._pose)
            self._est.append(self._pose[:3, 3].astype(np.float32))
            s.put("est", frame_index, np.array(self._est))
            if not result.ok:
                s.put("log", frame_index, f"tracking lost: {result.message}")
        elif name == "KeyframeResult":
            self._keyframe(frame_index, result)
        elif name == "MapResult":
            s.put("map_points", frame_index, np.asarray(result.points, np.float32))
            s.put("map_lines", frame_index, np.asarray(result.lines, np.float32))
        elif name == "GraphResult":
            pos = np.asarray(result.T_world_cam, float)[:, :3, 3]
            self._keyframes.update({int(k): p for k, p in zip(result.keyframe_ids, pos)})
            s.put("keyframes", frame_index, np.array(list(self._keyframes.values()), np.float32))
            if len(result.edges):
                s.put("graph", frame_index, pos[np.asarray(result.edges)].astype(np.float32))
        elif name == "LoopResult" and result.accepted:
            a, b = self._keyframes.get(result.query_keyframe), self._keyframes.get(result.match_keyframe)
            if a is not None and b is not None:
                self._loops.append(np.array([a, b], np.float32))
                s.put("loops", frame_index, np.array(self._loops))

    def _keyframe(self, frame_index: int, kf: Any) -> None:
        pose = kf.T_world_cam if kf.T_world_cam is not None else self._pose
        frame = self._frame
        self.store.put("log", frame_index, f"keyframe {kf.keyframe_id}: {kf.reason}")
        if pose is None or frame is None:
            return
        self._keyframes[kf.keyframe_id] = np.asarray(pose)[:3, 3]
        self.store.put("keyframes", frame_index, np.array(list(self._keyframes.values()), np.float32))
        scan = frame.scan[thin(len(frame.scan), self.viewer.limits.scan_points), :3].astype(np.float64)
        T = np.asarray(pose) @ frame.calib.T_cam_velo
        world = (scan @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        self.store.put("scan", frame_index, (world, depth_colors(np.linalg.norm(scan, axis=1))))

    def close(self) -> None:
        self.viewer.refresh()


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
                               ("graph", "/world/graph", "LineStrips3D:strips"),
                               ("loops", "/world/loops", "LineStrips3D:strips")]:
        for f, row in data.rows(entity):
            if row.get(key) is not None:
                store.put(layer, f, np.asarray(row[key], np.float32))
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
