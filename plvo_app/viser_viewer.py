"""The viser web viewer: live during a run (`ViserRecorder`) and replay of a saved .rrd (`load_rrd`).

Both fill a `SceneStore` (per-frame layers with Rerun's latest-at semantics) that `ViserViewer` shows on
127.0.0.1: a frame slider with play/pause, layer toggles with a legend of their colours, the camera frustum with its
image and the image in a panel of its own, a view that follows the car, and (replay) the list of the frames with
full detail, to jump to. It thins what it shows (never what is recorded) so that it stays responsive on a whole
sequence; positions are sent as float32 (float16 quantises at KITTI's hundreds of metres). World frame: RDF (OpenCV
camera convention), so up is -y.
"""

from __future__ import annotations

import bisect
import html
import logging
import sys
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import viser
import viser.transforms as vtf

from plvo.recording import RunInfo
from plvo.results import GraphResult, KeyframeResult, LoopResult, MapResult, TimingResult, TrackingResult
from plvo.types import Frame
from plvo_app.guards import deferred_signals
from plvo_app.rrd_index import load_rrd
from plvo_app.scene_common import (
    CYAN,
    DEPTH_FAR,
    DEPTH_NEAR,
    GREEN,
    MAGENTA,
    MAP_POINT,
    ORANGE,
    ZETA_FULL,
    EstimateTrail,
    SceneStore,
    depth_colors,
    gt_in_estimate_world,
    simplify_polyline,
    thin,
    zeta_colors,
)

__all__ = ["LAYERS", "SceneStore", "ViewLimits", "ViserRecorder", "ViserViewer", "load_rrd"]  # load_rrd: replay

log = logging.getLogger(__name__)

GT_COLOR = (60, 60, 60)  # dark grey: apart from the green estimate and the orange keyframes
BY_LIDAR_COLOR = (230, 30, 30)  # red: frames whose pose came from the lidar or was matched from its motion
# layer name -> (GUI label, shown by default)
LAYERS = {
    "scan": ("scan", True),
    "map_points": ("map points", True),
    "map_lines": ("map lines", True),
    "graph": ("keyframe graph", True),
    "loops": ("loops", True),
    "gt": ("ground truth", True),
    "est": ("estimate", True),
    "by_lidar": ("poses by the lidar", True),
    "camera": ("camera", True),
}
# layer -> its colour: one RGB, or "depth" (scene_common.depth_colors) or "zeta" (zeta_colors). What _draw draws
# with and what the legend shows, so that the two cannot differ.
LAYER_COLORS: dict[str, Any] = {
    "scan": "depth",
    "map_points": MAP_POINT,
    "map_lines": CYAN,
    "graph": "zeta",
    "keyframes": ORANGE,
    "loops": MAGENTA,
    "gt": GT_COLOR,
    "est": GREEN,
    "by_lidar": BY_LIDAR_COLOR,
    "camera": GREEN,
}
LEGEND_NOTES = {
    "scan": f"by distance, {DEPTH_NEAR:g} m to {DEPTH_FAR:g} m",
    "graph": "edges by zeta, 0 to exp(-2); the keyframes",
}


def _css(rgb) -> str:
    return "rgb({},{},{})".format(*(int(c) for c in rgb))


def legend_html() -> str:
    """The layers and their colours as HTML, from LAYER_COLORS and the colour functions the scene uses: two columns
    of swatches, then what the gradients mean."""
    cells = []
    for key, (label, _) in LAYERS.items():
        color = LAYER_COLORS[key]
        if color == "depth":
            stops = depth_colors(np.geomspace(DEPTH_NEAR, DEPTH_FAR, 6))
        elif color == "zeta":
            stops = zeta_colors(np.linspace(0.0, ZETA_FULL, 5), np.zeros(5, int))
        else:
            stops = [color]
        fill = _css(stops[0]) if len(stops) == 1 else f"linear-gradient(90deg,{','.join(map(_css, stops))})"
        swatch = f'<span style="display:inline-block;width:22px;height:9px;margin-right:5px;background:{fill}">' \
                 "</span>"
        if key == "graph":  # its toggle also shows the keyframes
            swatch += f'<span style="display:inline-block;width:9px;height:9px;margin-right:5px;border-radius:5px;' \
                      f'background:{_css(LAYER_COLORS["keyframes"])}"></span>'
        cells.append(f'<div data-layer="{key}" style="white-space:nowrap">{swatch}{html.escape(label)}</div>')
    notes = "; ".join(f"{LAYERS[k][0]}: {html.escape(n)}" for k, n in LEGEND_NOTES.items())
    return ('<div class="plvo-legend" style="font-size:12px;line-height:18px">'
            f'<div style="display:grid;grid-template-columns:1fr 1fr;column-gap:6px">{"".join(cells)}</div>'
            f'<div style="color:#888;line-height:15px;margin-top:3px">{notes}</div></div>')


@dataclass(frozen=True)
class ViewLimits:
    """How much the browser is sent at most, per layer."""

    scan_points: int = 30000
    map_points: int = 60000
    lines: int = 5000
    # Lines cost the browser most, by the segment: 3000 -> 800 trajectory points took a frame change on a 4541-frame
    # replay in headless Chromium (software GL, a loaded 2-core machine) from ~730 to ~420 ms. Simplified to
    # `trajectory_tolerance` metres rather than strided, a road's straights cost two points.
    trajectory_points: int = 800
    trajectory_tolerance: float = 0.05
    image_width: int = 480
    panel_image_width: int = 320  # the camera image in the sidebar


def _jpeg_small(image: np.ndarray, width: int) -> bytes:
    h, w = image.shape[:2]
    if w > width:
        image = cv2.resize(image, (width, round(h * width / w)), interpolation=cv2.INTER_AREA)
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()


class ViserViewer:
    """Serves a SceneStore on host:port. `live=True` adds a "follow live" toggle that tracks the newest frame.
    "follow the car" (on at the start) moves every browser's view along with the camera pose, keeping its angle;
    a browser starts behind and above the car."""

    def __init__(self, store: SceneStore, host: str = "127.0.0.1", port: int = 8080, live: bool = False,
                 limits: ViewLimits | None = None, frustum_scale: float = 1.5):
        self.store = store
        self.limits = limits or ViewLimits()
        self.frustum_scale = frustum_scale
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("-y")
        self.shown_frame: int | None = None  # the dataset frame on screen
        self._lock = threading.RLock()
        self._handles: dict[str, Any] = {}  # scene nodes, made once and updated in place
        self._drawn: dict[str, Any] = {}  # the store value each node shows
        self._drawn_image: Any = None
        self._panel_image: Any = None  # the JPEG the sidebar's image shows
        self._camera_placed = False
        self._followed: np.ndarray | None = None  # camera position the browsers' views were last moved with
        self._live = live
        self._stop = threading.Event()
        self._build_gui(live)
        self._player = threading.Thread(target=self._play_loop, name="viser-play", daemon=True)
        self._player.start()
        self.server.on_client_connect(self._on_connect)
        self.refresh()

    @property
    def port(self) -> int:
        return self.server.get_port()

    # ---- GUI -----------------------------------------------------------------------------------------------
    def _build_gui(self, live: bool) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="medium")
        with gui.add_folder("Playback"):
            self.slider = gui.add_slider("frame", min=0, max=max(1, len(self.store.frames) - 1), step=1,
                                         initial_value=0)
            self.play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
            self.fps = gui.add_slider("frames/s", min=1, max=30, step=1, initial_value=10)
            self.follow = gui.add_checkbox("follow live", live, visible=live)
            self.follow_car = gui.add_checkbox("follow the car", True,
                                               hint="move the view along with the car (keeping its angle)")
            self.status = gui.add_markdown("")
        with gui.add_folder("Camera image"):
            self.image_panel = gui.add_image(np.full((60, self.limits.panel_image_width, 3), 235, np.uint8),
                                             format="jpeg", jpeg_quality=85)
            self.image_caption = gui.add_markdown("no image yet")
        detail = list(getattr(self.store, "detail", []))
        with gui.add_folder("Full detail", visible=bool(detail)) as self.detail_folder:
            self.detail_text = gui.add_markdown(self._detail_text(detail))
            self._detail_options = {self._detail_label(a, b, why): a for a, b, why in detail}
            self.detail_pick = gui.add_dropdown("frames", list(self._detail_options) or ["none"])
            self.detail_go = gui.add_button("Go to these frames", icon=viser.Icon.ARROW_RIGHT)
        with gui.add_folder("Layers"):
            self.toggles = {k: gui.add_checkbox(label, on) for k, (label, on) in LAYERS.items()}
            self.legend = gui.add_html(legend_html())
        self.playing = False
        self.slider.on_update(lambda _: self._on_slider())
        self.play.on_click(lambda _: self._toggle_play())
        self.follow_car.on_update(lambda _: self._on_follow_car())
        self.detail_go.on_click(lambda _: self.jump_to_detail(self.detail_pick.value))
        for box in self.toggles.values():
            box.on_update(lambda _: self.show(self.slider.value, force=True))

    @staticmethod
    def _detail_label(a: int, b: int, why: str) -> str:
        frames = f"{a}" if b == a + 1 else f"{a}-{b - 1}"
        return f"{frames}: {why if len(why) <= 60 else why[:57] + '...'}"

    @staticmethod
    def _detail_text(detail: list[tuple[int, int, str]]) -> str:
        if not detail:
            return ""
        n, w = sum(b - a for a, b, _ in detail), len(detail)
        return (f"{n} frame{'s' * (n != 1)} in {w} window{'s' * (w != 1)} {'have' if n != 1 else 'has'} every layer "
                "(the image with its overlays, the whole map); the others show their keyframe's thinned scan and "
                "image.")

    def jump_to_detail(self, label: str) -> None:
        """Move the timeline to the first frame of the detail window named `label` (a dropdown option)."""
        frame = self._detail_options.get(label)
        frames = self.store.frames
        if frame is None or not frames:
            return
        self.playing = False
        self.play.label, self.play.icon = "Play", viser.Icon.PLAYER_PLAY
        if self.follow.value:
            self.follow.value = False  # a jump back in a live run: stop following the newest frame
        self.slider.value = min(bisect.bisect_left(frames, frame), len(frames) - 1)

    def _on_follow_car(self) -> None:
        self._followed = None  # on again: start behind the car where it is now
        if self.follow_car.value and self.shown_frame is not None:
            self._follow(self.shown_frame)

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
            with self.server.atomic():  # one websocket window: the page applies it in one render frame
                self._draw(f)
                self.status.content = self._status_text(f, int(position))  # with the scene it names, not before
            if self.follow_car.value:
                self._follow(f)
            self.shown_frame = f  # after drawing: readers of shown_frame see a finished scene
            self._show_image(f)  # after the scene: a frame change reaches the page first, its image follows

    @staticmethod
    def _view_of(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, look_at, up) of a browser view above and behind camera pose T, looking down the road."""
        forward, up = T[:3, 2], -T[:3, 1]  # camera z forward, y down
        return T[:3, 3] - 18.0 * forward + 14.0 * up, T[:3, 3] + 12.0 * forward, up

    def _place_camera(self, f: int) -> None:
        """The view a new browser starts with: behind the first camera pose shown."""
        T = self.store.latest("pose", f)
        if T is None:
            return
        cam = self.server.initial_camera
        position, look_at, up = self._view_of(T)
        cam.position, cam.look_at, cam.up = tuple(position), tuple(look_at), tuple(up)
        self._camera_placed = True

    def _on_connect(self, client: viser.ClientHandle) -> None:
        """A browser joining later (e.g. after a live run) starts behind the frame on screen, not the first one."""
        T = None if self.shown_frame is None else self.store.latest("pose", self.shown_frame)
        if T is None:
            return
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5.0:  # the client reports its camera shortly after connecting
            if self._place_client(client, T):
                return
            time.sleep(0.05)

    def _place_client(self, client: viser.ClientHandle, T: np.ndarray) -> bool:
        """Put `client`'s view behind and above camera pose T; False while its camera is not reported yet."""
        position, look_at, up = self._view_of(T)
        try:
            client.camera.up_direction = up
            client.camera.position = position
            client.camera.look_at = look_at
            return True
        except AssertionError:
            return False

    def _follow(self, f: int) -> None:
        """Move every browser's view along with the camera (keeping the angle the user gave it); the first time (or
        after "follow the car" is ticked again), put it behind the car."""
        T = self.store.latest("pose", f)
        if T is None:
            return
        for client in self.server.get_clients().values():
            if self._followed is None:
                self._place_client(client, T)
                continue
            try:
                client.camera.position = client.camera.position + (T[:3, 3] - self._followed)  # moves look_at along
            except AssertionError:  # camera not reported yet: _on_connect places it
                pass
        self._followed = T[:3, 3].copy()

    def _show_image(self, f: int) -> None:
        """The sidebar's camera image: the frame's own (detail frames) or its keyframe's thinned one."""
        jpeg = self.store.latest("image", f)
        source = getattr(self.store, "source", None)
        where = source("image", f) if source is not None else None
        if where is not None:
            caption = f"frame {where[1]}" + (" (full detail)" if where[0] == "full" else
                                             " (keyframe, thinned)" if where[1] == f else " (its keyframe's, thinned)")
        else:
            caption = "no image" if jpeg is None else f"frame {f}"
        if caption != self.image_caption.content:
            self.image_caption.content = caption
        if jpeg is None or jpeg is self._panel_image:
            return
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR_RGB)
        if img is None:
            return
        w = self.limits.panel_image_width
        self.image_panel.image = cv2.resize(img, (w, max(1, round(img.shape[0] * w / img.shape[1]))),
                                            interpolation=cv2.INTER_AREA)
        self._panel_image = jpeg

    def _status_text(self, f: int, position: int) -> str:
        msg = self.store.latest("log", f) or ""
        why = next((w for a, b, w in getattr(self.store, "detail", []) if a <= f < b), None)
        where = "" if why is None else f"  \nfull detail: {why}"
        return f"**{self.store.name}** frame **{f}** ({position + 1}/{len(self.store.frames)})  \n{msg}{where}"

    def _layer(self, key: str, visible: bool, data: Any, make, update) -> None:
        """Show scene node `key`: made once by make(), then updated in place by update(handle) only when `data`
        (the store's value, by identity) changed since it was drawn; hidden, not removed, when not visible. A
        toggle or a frame that shares the layer's value with the last one sends nothing for it."""
        handle = self._handles.get(key)
        if not visible or data is None:
            if handle is not None and handle.visible:
                handle.visible = False
            return
        if handle is None:
            handle = make()
            if handle is None:
                return
            self._handles[key] = handle
        elif self._drawn.get(key) is not data:
            update(handle)
        self._drawn[key] = data  # held, so that its id cannot be reused by another value
        if not handle.visible:
            handle.visible = True

    def _cloud(self, key: str, name: str, data: Any, pts: np.ndarray | None, colors, visible: bool,
               point_size: float) -> None:
        def make():
            return self.server.scene.add_point_cloud(name, pts, colors, point_size=point_size, precision="float32",
                                                     point_shape="circle")

        def update(h):
            h.points = np.asarray(pts, np.float32)
            h.colors = np.broadcast_to(np.asarray(colors, np.uint8), (len(pts), 3)).copy() \
                if np.ndim(colors) == 1 else np.asarray(colors, np.uint8)

        self._layer(key, visible and pts is not None and len(pts) > 0, data, make, update)

    def _draw(self, f: int) -> None:
        s, lim, on = self.store, self.limits, {k: b.value for k, b in self.toggles.items()}
        scan = s.latest("scan", f)
        cut = None if scan is None else thin(len(scan[0]), lim.scan_points)
        self._cloud("scan", "/scan", scan, None if scan is None else scan[0][cut],
                    None if scan is None else scan[1][cut], on["scan"], 0.05)
        pts = s.latest("map_points", f)
        self._cloud("map_points", "/map/points", pts, None if pts is None else pts[thin(len(pts), lim.map_points)],
                    LAYER_COLORS["map_points"], on["map_points"], 0.1)
        lines = s.latest("map_lines", f)
        self._segments("map_lines", "/map/lines", lines, lines, on["map_lines"], LAYER_COLORS["map_lines"], 1.5)
        graph = s.latest("graph", f)
        self._segments("graph", "/graph", graph, None if graph is None else graph[0], on["graph"],
                       None if graph is None else np.repeat(graph[1][:, None], 2, axis=1), 2.0)
        kfs = s.latest("keyframes", f)
        self._cloud("keyframes", "/keyframes", kfs, None if kfs is None else np.asarray(kfs, np.float32),
                    LAYER_COLORS["keyframes"], on["graph"], 0.4)
        loops = s.latest("loops", f)
        self._segments("loops", "/loops", loops, loops, on["loops"], LAYER_COLORS["loops"], 3.0)
        self._polyline("gt", "/trajectory/gt", s.gt, on["gt"], LAYER_COLORS["gt"], 2.0)
        est = s.latest("est", f)
        self._polyline("est", "/trajectory/est", est, on["est"], LAYER_COLORS["est"])
        self._polyline("est_tail", "/trajectory/est_tail", self._tail(f, est), on["est"], LAYER_COLORS["est"])
        by = s.latest("by_lidar", f)
        self._cloud("by_lidar", "/trajectory/by_lidar", by, None if by is None else np.asarray(by, np.float32),
                    LAYER_COLORS["by_lidar"], on["by_lidar"], 0.5)
        self._camera(f, on["camera"])

    def _tail(self, f: int, est: Any) -> np.ndarray | None:
        """A replay's estimate is redrawn every few keyframes: from its end to the car, the camera's own positions
        (the store's track), so that the trajectory reaches the car on every frame. None live (redrawn each
        keyframe) and when the estimate is drawn at this very frame."""
        track, where = getattr(self.store, "track", None), getattr(self.store, "source", None)
        at = None if track is None or where is None else where("est", f)
        if at is None or at[1] >= f or est is None or not len(est):
            return None
        return np.vstack([np.asarray(est, np.float32)[-1:], track(at[1], f)])

    def _segments(self, key: str, name: str, data: Any, segs: np.ndarray | None, visible: bool, color,
                  width_px: float) -> None:
        """Line segments `width_px` pixels wide. Not in metres: viser draws a world-unit line twice (an antialiased
        fringe over its core) with a costlier shader, and on a 4541-frame replay in headless Chromium's software GL a
        render frame took ~80 ms with them, ~50 with these; a trajectory seen from afar stays visible, too."""
        ok = visible and segs is not None and len(segs) > 0
        if not ok:
            self._layer(key, False, data, None, None)
            return
        cut = thin(len(segs), self.limits.lines)
        segs = np.asarray(segs, np.float32)[cut]
        color = np.asarray(color, np.uint8)[cut] if np.ndim(color) == 3 else color  # per segment: thinned along

        def make():
            return self.server.scene.add_line_segments(name, segs, color, thickness=width_px,
                                                       thickness_units="screen")

        def update(h):
            h.points = segs
            h.colors = np.asarray(color, np.uint8) if np.ndim(color) == 3 else \
                np.broadcast_to(np.asarray(color, np.uint8), (len(segs), 2, 3)).copy()

        self._layer(key, True, data, make, update)

    def _polyline(self, key: str, name: str, pts: np.ndarray | None, visible: bool, color,
                  width_px: float = 3.0) -> None:
        if pts is None or len(pts) < 2:
            self._layer(key, False, None, None, None)
            return
        if self._drawn.get(key) is pts and key in self._handles:  # same trajectory: nothing to make or send
            self._layer(key, visible, pts, None, None)
            return
        p = np.asarray(pts, np.float32)
        p = p[simplify_polyline(p, self.limits.trajectory_tolerance, self.limits.trajectory_points)]
        self._segments(key, name, pts, np.stack([p[:-1], p[1:]], axis=1), visible, color, width_px)

    def _camera(self, f: int, visible: bool) -> None:
        s = self.store
        T = s.latest("pose", f)
        if T is None or s.K is None:
            self._layer("camera", False, None, None, None)
            return
        jpeg = s.latest("image", f)

        def image():
            if jpeg is None:
                return None
            img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR_RGB)
            return cv2.resize(img, (self.limits.image_width, round(img.shape[0] * self.limits.image_width
                                                                   / img.shape[1])))

        fov = 2 * np.arctan2(s.height / 2, s.K[1, 1])
        wxyz = vtf.SO3.from_matrix(T[:3, :3]).wxyz

        def make():
            self._drawn_image = jpeg
            return self.server.scene.add_camera_frustum(
                "/camera", fov=float(fov), aspect=s.width / s.height, scale=self.frustum_scale, image=image(),
                format="jpeg", color=LAYER_COLORS["camera"], wxyz=wxyz, position=T[:3, 3])

        def update(h):
            h.wxyz, h.position = wxyz, T[:3, 3]
            if self._drawn_image is not jpeg:  # the same JPEG (a frame without its own image): not re-sent
                h.image = image()
                self._drawn_image = jpeg

        self._layer("camera", visible, T, make, update)

    def close(self) -> None:
        self._stop.set()
        self.server.stop()


class ViserRecorder:
    """A Recorder feeding a live ViserViewer: converts stage results into SceneStore layers as they come.

    Memory stays bounded over a whole sequence: the estimate and the keyframes are views of one EstimateTrail (not a
    copy a keyframe, which grew quadratically), and of the images, scans and maps only the last `keep` are kept
    whole (older images and scans are dropped, older maps thinned tenfold)."""

    def __init__(self, viewer: ViserViewer, min_interval_s: float = 0.1, keep: int = 300):
        self.viewer = viewer
        self.store = viewer.store
        self.min_interval_s = min_interval_s
        self._frame: Frame | None = None
        self._pose: np.ndarray | None = None
        self._trail = EstimateTrail()
        self._by_lidar: list[int] = []  # rows of the trail whose pose came from the lidar (or its motion)
        self._loops: list[np.ndarray] = []
        self._last_refresh = 0.0
        self.keep = keep
        self._heavy: dict[str, deque[int]] = defaultdict(deque)  # layer -> frames holding a whole value

    def _put_heavy(self, layer: str, frame_index: int, value: Any) -> None:
        s = self.store
        s.put(layer, frame_index, value)
        frames = self._heavy[layer]
        frames.append(frame_index)
        while len(frames) > self.keep:
            old = frames.popleft()
            if layer in ("map_points", "map_lines"):
                v = s.value_at(layer, old)
                s.replace(layer, old, None if v is None else v[::10])
            else:
                s.replace(layer, old, None)

    def _log(self, frame_index: int, text: str) -> None:
        """A line of the frame's log (the status panel's markdown), after those it has."""
        before = self.store.value_at("log", frame_index)
        self.store.put("log", frame_index, text if before is None else f"{before}  \n{text}")

    def on_restart(self, info: RunInfo) -> None:
        """The run starts again from its first frame: the scene so far is dropped and grows again."""
        self.store.clear()
        self._frame, self._pose = None, None
        self._trail, self._by_lidar, self._loops = EstimateTrail(), [], []
        self._heavy.clear()
        self.on_run_start(info)
        why = info.extra.get("restart", {})
        first = info.frame_indices[0] if info.frame_indices else 0
        self._log(first, f"started again from the first frame: {why.get('reason', 'restart')} found at "
                                     f"frame {why.get('at_frame', '?')}")

    def on_run_start(self, info: RunInfo) -> None:
        s = self.store
        s.name, s.K, s.width, s.height = info.name, info.calib.K, info.calib.width, info.calib.height
        gt = gt_in_estimate_world(info)
        if gt is not None:
            s.gt = gt[:, :3, 3].astype(np.float32)

    def on_frame(self, frame: Frame) -> None:
        self._frame = frame
        shown = frame.image if frame.color is None else cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR)  # colour source
        self._put_heavy("image", frame.index, _jpeg_small(shown, 2 * self.viewer.limits.image_width))

    def on_stage(self, frame_index: int, result: Any) -> None:
        # along the MRO: a stage may hand a richer subclass (the tracker's FrontendResult)
        handler = next((_HANDLERS[c] for c in type(result).__mro__ if c in _HANDLERS), None)
        if handler is not None:
            handler(self, frame_index, result)

    def _tracking(self, frame_index: int, result: TrackingResult) -> None:
        self._pose = np.asarray(result.T_world_cam, float)
        self.store.put("pose", frame_index, self._pose)
        self._trail.on_tracking(frame_index, self._pose)
        source = getattr(result, "source", "camera")  # the tracker's FrontendResult: where the pose came from
        if not result.ok:
            self._log(frame_index, result.message or "tracking lost")
        elif source != "camera":
            self._log(frame_index, f"pose by the {source}: {result.message}")
            self._by_lidar.append(len(self._trail.frames) - 1)
            self.store.put("by_lidar", frame_index, TrailView(self._trail, len(self._trail.frames),
                                                              rows=tuple(self._by_lidar)))

    def _map(self, frame_index: int, result: MapResult) -> None:
        self._put_heavy("map_points", frame_index, np.asarray(result.points, np.float32))
        self._put_heavy("map_lines", frame_index, np.asarray(result.lines, np.float32))

    def _graph(self, frame_index: int, result: GraphResult) -> None:
        poses = np.asarray(result.T_world_cam, float)
        self._trail.on_graph(result.keyframe_ids, poses)
        self._put_estimate(frame_index)
        if len(result.edges):
            self.store.put("graph", frame_index, (poses[:, :3, 3][np.asarray(result.edges)].astype(np.float32),
                                                  zeta_colors(result.zeta, result.edge_kind)))

    def _loop(self, frame_index: int, result: LoopResult) -> None:
        if not result.accepted:
            return
        kf = self._trail.kf_pose
        if result.query_keyframe in kf and result.match_keyframe in kf:
            self._loops.append(np.array([kf[result.query_keyframe][:3, 3], kf[result.match_keyframe][:3, 3]],
                                        np.float32))
            self.store.put("loops", frame_index, np.array(self._loops))

    def _timing(self, frame_index: int, result: TimingResult) -> None:
        self._frame_done(frame_index)  # the end of a step: the frame is complete, show it

    def _frame_done(self, frame_index: int) -> None:
        self.store.add_frame(frame_index)
        now = time.monotonic()
        if now - self._last_refresh >= self.min_interval_s:
            self._last_refresh = now
            self.viewer.refresh()

    def _put_estimate(self, frame_index: int) -> None:
        s = self.store
        s.put("keyframes", frame_index, TrailView(self._trail, len(self._trail.kf_pose), keyframes=True))
        if self._trail.frames:
            s.put("est", frame_index, TrailView(self._trail, len(self._trail.frames)))

    def _keyframe(self, frame_index: int, kf: KeyframeResult) -> None:
        pose = np.asarray(kf.T_world_cam if kf.T_world_cam is not None else self._pose, float)
        frame = self._frame
        self._log(frame_index, f"keyframe {kf.keyframe_id}: {kf.reason}")
        self._trail.on_keyframe(kf.keyframe_id, frame_index, pose)
        self._put_estimate(frame_index)
        if frame is None:
            return
        scan = frame.scan[thin(len(frame.scan), self.viewer.limits.scan_points), :3].astype(np.float64)
        T = pose @ frame.calib.T_cam_velo
        world = (scan @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        self._put_heavy("scan", frame_index, (world, depth_colors(np.linalg.norm(scan, axis=1))))

    def close(self) -> None:
        self.viewer.refresh()



# result type -> ViserRecorder handler; the results the viewer does not show have none
_HANDLERS = {
    TrackingResult: ViserRecorder._tracking,
    KeyframeResult: ViserRecorder._keyframe,
    MapResult: ViserRecorder._map,
    GraphResult: ViserRecorder._graph,
    LoopResult: ViserRecorder._loop,
    TimingResult: ViserRecorder._timing,
}

class TrailView:
    """The first n positions of an EstimateTrail (frames, or keyframes by id) as the trail stands when drawn: a
    few bytes in the store instead of a copy of the trajectory."""

    def __init__(self, trail: EstimateTrail, n: int, keyframes: bool = False, rows: tuple[int, ...] | None = None):
        self.trail, self.n, self.keyframes, self.rows = trail, n, keyframes, rows

    def __len__(self) -> int:
        return self.n if self.rows is None else len(self.rows)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        p = self.trail.cached_keyframe_positions() if self.keyframes else self.trail.cached_positions()
        p = p[:self.n] if self.rows is None else p[list(self.rows)]  # rows: some frames only (poses by the lidar)
        return np.asarray(p, dtype or np.float32)


def serve_until_interrupted(viewer: ViserViewer, what: str) -> None:
    """Keep the viewer up until Ctrl-C or SIGTERM (plvo view), then close it: quitting is not an error, so the
    signal is held from before the address is printed until the viewer is closed (no KeyboardInterrupt)."""
    with deferred_signals("") as held:
        held.what = None
        print(f"{what}: http://127.0.0.1:{viewer.port} - Ctrl-C to quit", file=sys.stderr)
        while not held.seen:
            time.sleep(0.2)
        viewer.close()
