"""The Rerun sink: a Recorder that writes every stage to a .rrd file (and optionally serves it), and the entity table.

All entity paths are in `ENTITIES`, the one table of what is logged where. Timelines: `frame` (the dataset's frame
number) and `sensor_time` (seconds). Calibration and ground truth are static. Images are JPEG, scans thinned to a
fixed budget, so that a whole KITTI sequence stays a file a person can attach to a bug report.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from plvo.errors import RecordingError
from plvo.recording import RunInfo
from plvo.results import EDGE_LOOP, GraphResult, KeyframeResult, LoopResult, MapResult, MetricsResult, TimingResult
from plvo.results import TrackingResult
from plvo.types import DepthPriors, FeatureMatches, FeatureSet, Frame

log = logging.getLogger(__name__)


class Entity(NamedTuple):
    path: str
    archetype: str
    what: str


ENTITIES: dict[str, Entity] = {
    e.path: e
    for e in [
        Entity("world", "ViewCoordinates", "static; RDF: OpenCV camera convention (x right, y down, z forward)"),
        Entity("world/camera", "Transform3D", "current camera pose T_world_cam, every frame"),
        Entity("world/camera/image", "Pinhole (static), EncodedImage", "JPEG image and intrinsics"),
        Entity("world/camera/image/orb", "Points2D", "ORB keypoints; tracked ones green"),
        Entity("world/camera/image/lsd_raw", "LineStrips2D", "LSD segments before chaining and merging"),
        Entity("world/camera/image/lsd_merged", "LineStrips2D", "LSD segments after chaining and merging"),
        Entity("world/camera/image/lidar", "Points2D", "keyframe scan projected into the image, coloured by depth"),
        Entity("world/camera/image/patches", "Boxes2D", "point patches searched for depth (green: prior found)"),
        Entity("world/camera/image/line_patches", "LineStrips2D", "bands searched around line features for depth"),
        Entity("world/lidar", "Transform3D", "lidar pose T_world_velo at the last keyframe"),
        Entity("world/lidar/scan", "Points3D", "the keyframe scan, thinned, in the lidar frame"),
        Entity("world/depth/points", "Points3D", "point depth priors of the last keyframe"),
        Entity("world/depth/lines", "LineStrips3D", "fitted 3D lines of the last keyframe"),
        Entity("world/depth/planes", "Mesh3D", "fitted patch planes of the point priors of the last keyframe"),
        Entity("world/map/points", "Points3D", "point landmarks after bundle adjustment"),
        Entity("world/map/lines", "LineStrips3D", "line landmarks after bundle adjustment"),
        Entity("world/keyframes", "Points3D", "keyframe positions"),
        Entity("world/graph", "LineStrips3D", "factor-graph edges coloured by information zeta"),
        Entity("world/loops", "LineStrips3D", "accepted loop edges"),
        Entity("world/trajectory/est", "LineStrips3D", "estimated trajectory (at keyframes)"),
        Entity("world/trajectory/gt", "LineStrips3D", "ground-truth trajectory, static"),
        Entity("metrics", "Scalars", "metrics/time/<stage> ms, metrics/<stage>/<count>"),
        Entity("log", "TextLog", "decisions: keyframes, tracking lost, loops accepted or rejected and why"),
    ]
}
# Short names used below; every path is a key of ENTITIES (checked at import).
E = {
    "camera": "world/camera", "image": "world/camera/image", "orb": "world/camera/image/orb",
    "lsd_raw": "world/camera/image/lsd_raw", "lsd_merged": "world/camera/image/lsd_merged",
    "lidar2d": "world/camera/image/lidar", "patches": "world/camera/image/patches",
    "line_patches": "world/camera/image/line_patches", "planes": "world/depth/planes", "lidar": "world/lidar",
    "scan": "world/lidar/scan", "depth_points": "world/depth/points", "depth_lines": "world/depth/lines",
    "map_points": "world/map/points", "map_lines": "world/map/lines", "keyframes": "world/keyframes",
    "graph": "world/graph", "loops": "world/loops", "est": "world/trajectory/est", "gt": "world/trajectory/gt",
}
assert set(E.values()) <= set(ENTITIES)

GREY, GREEN, RED, ORANGE, CYAN = (170, 170, 170), (40, 220, 60), (230, 50, 50), (255, 150, 20), (40, 200, 230)


@dataclass(frozen=True)
class RerunOptions:
    jpeg_quality: int = 55
    scan_max_points: int = 6000  # the 3D scan, thinned by stride (a KITTI scan has ~120k)
    overlay_max_points: int = 2500  # the scan projected into the image
    trajectory_max_points: int = 2000


def blueprint() -> rrb.Blueprint:
    """3D world on the left; the camera image with overlays, time series and the decision log on the right."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="3D world", origin="world"),
            rrb.Vertical(
                rrb.Spatial2DView(name="camera", origin="world/camera/image"),
                rrb.Tabs(
                    rrb.TimeSeriesView(name="timings (ms)", origin="metrics/time"),
                    rrb.TimeSeriesView(name="counts", origin="metrics", contents=["+ $origin/**", "- /metrics/time/**"]),
                ),
                rrb.TextLogView(name="log", origin="log"),
                row_shares=[3, 2, 1],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def thin(n: int, budget: int) -> slice:
    """A stride slice keeping at most `budget` of `n` items."""
    return slice(None, None, max(1, -(-n // max(1, budget))))


def depth_colors(z: np.ndarray, near: float = 2.0, far: float = 50.0) -> np.ndarray:
    """(N,) depths -> (N,3) uint8 colours, near red to far blue (turbo)."""
    t = np.clip((np.log(np.maximum(z, near)) - np.log(near)) / (np.log(far) - np.log(near)), 0, 1)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return lut[(255 * (1 - t)).astype(np.uint8)]


def _segments_2d(seg: np.ndarray) -> np.ndarray:
    return np.asarray(seg, dtype=np.float32).reshape(-1, 2, 2)


def _transform(T: np.ndarray) -> rr.Transform3D:
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


class RerunRecorder:
    """Writes a run to `path` (.rrd, streamed as it goes, readable even if the run is cut short).

    stream: an existing RecordingStream (tests, or one also served over gRPC); otherwise one is made and saved.
    """

    def __init__(self, path: str | Path | None, options: RerunOptions | None = None,
                 stream: rr.RecordingStream | None = None):
        self.path = None if path is None else Path(path)
        self.opt = options or RerunOptions()
        self.rec = stream or rr.RecordingStream("plvo")
        if self.path is not None:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self.rec.save(self.path, default_blueprint=blueprint())
            except (OSError, RuntimeError) as exc:
                raise RecordingError(f"{self.path}: cannot write the recording ({exc})") from None
        self._frame: Frame | None = None
        self._T_world_cam: np.ndarray | None = None
        self._pose_from_gt = False
        self._est: list[np.ndarray] = []
        self._keyframes: dict[int, np.ndarray] = {}
        self._loops: list[np.ndarray] = []
        self._point_valid: np.ndarray | None = None  # of the last DepthPriors, for the debug overlays
        self._have_depth_debug = False  # then the projected scan comes from the depth stage, not from here
        self._keypoints: np.ndarray | None = None  # (N,2) of the frame's FeatureSet, for depth and tracking
        self._closed = False

    # ---- Recorder protocol -------------------------------------------------------------------------------
    def on_run_start(self, info: RunInfo) -> None:
        rec = self.rec
        rec.send_recording_name(info.name)
        self._pose_from_gt = not info.extra.get("has_odometry", True)
        rec.send_property("plvo", rr.AnyValues(
            version=info.version, git_revision=info.git_revision, command_line=info.command_line,
            config=info.extra.get("config_toml", repr(info.config)), sequence=info.sequence,
            frames=f"{info.frame_indices[0]}:{info.frame_indices[-1] + 1}" if info.frame_indices else "",
            camera_pose_source="ground truth (no odometry yet)" if self._pose_from_gt else "estimate",
        ))
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        c = info.calib
        rec.log(E["image"], rr.Pinhole(image_from_camera=c.K, resolution=[c.width, c.height],
                                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=1.0), static=True)
        if info.gt_T_world_cam is not None and len(info.gt_T_world_cam):
            gt = np.asarray(info.gt_T_world_cam)[:, :3, 3].astype(np.float32)
            rec.log(E["gt"], rr.LineStrips3D([gt], colors=[ORANGE], radii=rr.Radius.ui_points(1.5)), static=True)
        if self._pose_from_gt:
            rec.log("log", rr.TextLog("odometry is not implemented yet: the camera is placed at ground truth",
                                      level=rr.TextLogLevel.WARN), static=True)

    def on_frame(self, frame: Frame) -> None:
        rec = self.rec
        self._frame = frame
        rec.set_time("frame", sequence=int(frame.index))
        rec.set_time("sensor_time", duration=float(frame.time))
        ok, buf = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, self.opt.jpeg_quality])
        if ok:
            rec.log(E["image"], rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
        if self._pose_from_gt and frame.gt_T_world_cam is not None:
            self._set_camera(frame.gt_T_world_cam)

    def on_stage(self, frame_index: int, result: Any) -> None:
        # By class name along the MRO: a stage may hand a richer subclass (the tracker's FrontendResult).
        handler = next((_HANDLERS[c.__name__] for c in type(result).__mro__ if c.__name__ in _HANDLERS), None)
        if handler is None:
            log.debug("no Rerun handler for %s", type(result).__name__)
            return
        handler(self, result)

    def set_status(self, status: str, frames_done: int) -> None:
        """Stamp the recording as complete or interrupted (a static property: the last one wins)."""
        self.rec.send_property("plvo_run", rr.AnyValues(status=status, frames_done=frames_done))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.rec.flush()
        if self.path is not None:
            self.rec.disconnect()

    # ---- helpers -----------------------------------------------------------------------------------------
    def _set_camera(self, T_world_cam: np.ndarray) -> None:
        self._T_world_cam = np.asarray(T_world_cam, dtype=float)
        self.rec.log(E["camera"], _transform(self._T_world_cam))

    def _scalars(self, prefix: str, values: dict[str, float]) -> None:
        for name, value in values.items():
            self.rec.log(f"metrics/{prefix}/{name}", rr.Scalars(float(value)))

    def _text(self, text: str, level: str = rr.TextLogLevel.INFO) -> None:
        self.rec.log("log", rr.TextLog(text, level=level))

    # ---- stage handlers ----------------------------------------------------------------------------------
    def features(self, fs: FeatureSet) -> None:
        rec = self.rec
        self._keypoints = np.asarray(fs.keypoints, float)
        rec.log(E["orb"], rr.Points2D(np.asarray(fs.keypoints, np.float32), colors=[GREY], radii=rr.Radius.ui_points(2)))
        rec.log(E["lsd_raw"], rr.LineStrips2D(_segments_2d(fs.raw_segments), colors=[RED], radii=rr.Radius.ui_points(1)))
        rec.log(E["lsd_merged"], rr.LineStrips2D(_segments_2d(fs.segments), colors=[CYAN],
                                                 radii=rr.Radius.ui_points(2)))
        self._scalars("features", {"points": fs.n_points, "lines": fs.n_lines, "raw_segments": len(fs.raw_segments)})

    def matches(self, m: FeatureMatches) -> None:
        self._scalars("matching", {"points": len(m.points), "lines": len(m.lines)})

    def depth(self, d: DepthPriors) -> None:
        frame = self._frame
        self._point_valid = np.asarray(d.point_valid)
        self._scalars("depth", {"point_priors": int(np.sum(d.point_valid)), "line_priors": int(np.sum(d.line_valid))})
        lines = np.asarray(d.line_endpoints, np.float32)[d.line_valid]
        self.rec.log(E["depth_lines"], rr.LineStrips3D(lines, colors=[CYAN]))
        if frame is None or not len(d.point_depth):
            return
        # The points were fitted in this keyframe's camera frame; draw them in the world where the camera is.
        uv = self._keypoints
        if uv is not None and len(uv) == len(d.point_depth) and self._T_world_cam is not None:
            from plvo.geometry.camera import backproject
            from plvo.geometry.se3 import transform_points

            ok = d.point_valid
            pts = transform_points(self._T_world_cam, backproject(frame.calib.K, uv[ok], d.point_depth[ok]))
            self.rec.log(E["depth_points"], rr.Points3D(pts.astype(np.float32), colors=[GREEN],
                                                        radii=rr.Radius.ui_points(3)))

    def depth_debug(self, dbg: Any) -> None:
        """plvo.depth.extract.DepthDebug: projected scan, searched patches, fitted planes (camera frame, pixels)."""
        self._have_depth_debug = True
        uv, z = np.asarray(dbg.scan_uv), np.asarray(dbg.scan_depth)
        s = thin(len(uv), self.opt.overlay_max_points)
        self.rec.log(E["lidar2d"], rr.Points2D(uv[s].astype(np.float32), colors=depth_colors(z[s]),
                                               radii=rr.Radius.ui_points(1.5)))
        boxes = np.asarray(dbg.point_boxes, np.float32)
        valid = self._point_valid if self._point_valid is not None and len(self._point_valid) == len(boxes) \
            else np.zeros(len(boxes), bool)
        colors = np.where(valid[:, None], np.array(GREEN, np.uint8), np.array(RED, np.uint8))
        self.rec.log(E["patches"], rr.Boxes2D(mins=boxes[:, :2], sizes=boxes[:, 2:] - boxes[:, :2], colors=colors))
        bands = np.asarray(dbg.line_bands, np.float32)
        self.rec.log(E["line_patches"], rr.LineStrips2D(np.concatenate([bands, bands[:, :1]], axis=1), colors=[CYAN]))
        self._scalars("time/depth", dict(dbg.timings_ms))
        quads = np.asarray(dbg.plane_quads, float)
        quads = quads[np.all(np.isfinite(quads), axis=(1, 2))]
        if self._T_world_cam is not None and len(quads):
            from plvo.geometry.se3 import transform_points

            verts = transform_points(self._T_world_cam, quads.reshape(-1, 3)).astype(np.float32)
            base = 4 * np.arange(len(quads))[:, None]
            tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.uint32)
            self.rec.log(E["planes"], rr.Mesh3D(vertex_positions=verts, triangle_indices=tris,
                                                vertex_colors=np.tile(np.array(GREEN, np.uint8), (len(verts), 1))))

    def keyframe(self, kf: KeyframeResult) -> None:
        if kf.T_world_cam is not None:
            self._keyframes[kf.keyframe_id] = np.asarray(kf.T_world_cam)[:3, 3]
        elif self._T_world_cam is not None:
            self._keyframes[kf.keyframe_id] = self._T_world_cam[:3, 3]
        self._text(f"keyframe {kf.keyframe_id}: {kf.reason}")
        self._log_keyframes()
        self._log_scan()
        self._log_est()

    def _log_keyframes(self) -> None:
        if self._keyframes:
            pos = np.array(list(self._keyframes.values()), np.float32)
            self.rec.log(E["keyframes"], rr.Points3D(pos, colors=[ORANGE], radii=rr.Radius.ui_points(5)))

    def _log_scan(self) -> None:
        frame = self._frame
        if frame is None or self._T_world_cam is None:
            return
        scan = frame.scan[thin(len(frame.scan), self.opt.scan_max_points), :3]
        self.rec.log(E["lidar"], _transform(self._T_world_cam @ frame.calib.T_cam_velo))
        self.rec.log(E["scan"], rr.Points3D(scan.astype(np.float32), colors=depth_colors(np.linalg.norm(scan, axis=1)),
                                            radii=rr.Radius.ui_points(1.5)))
        if not self._have_depth_debug:
            self._log_scan_overlay(frame)

    def _log_scan_overlay(self, frame: Frame) -> None:
        from plvo.geometry.camera import in_image, project
        from plvo.geometry.se3 import transform_points

        c = frame.calib
        pts = transform_points(c.T_cam_velo, frame.scan[thin(len(frame.scan), 4 * self.opt.overlay_max_points), :3])
        uv, z = project(c.K, pts)
        keep = in_image(uv, c.width, c.height) & (z > 0.5)
        uv, z = uv[keep], z[keep]
        s = thin(len(uv), self.opt.overlay_max_points)
        self.rec.log(E["lidar2d"], rr.Points2D(uv[s].astype(np.float32), colors=depth_colors(z[s]),
                                               radii=rr.Radius.ui_points(1.5)))

    def _log_est(self) -> None:
        if self._est and not self._pose_from_gt:
            est = np.array(self._est, np.float32)
            est = np.vstack([est[thin(len(est), self.opt.trajectory_max_points)], est[-1:]])
            self.rec.log(E["est"], rr.LineStrips3D([est], colors=[GREEN], radii=rr.Radius.ui_points(2)))

    def tracking(self, t: TrackingResult) -> None:
        self._pose_from_gt = False
        self._set_camera(t.T_world_cam)
        self._est.append(np.asarray(t.T_world_cam)[:3, 3])
        tracked = np.asarray(t.point_inliers, int)
        if self._keypoints is not None and len(tracked):
            n = len(self._keypoints)
            colors = np.tile(np.array(GREY, np.uint8), (n, 1))
            colors[tracked] = GREEN
            self.rec.log(E["orb"], rr.Points2D.from_fields(colors=colors))
        self._scalars("tracking", {"point_matches": t.n_point_matches, "line_matches": t.n_line_matches,
                                   "point_inliers": len(t.point_inliers), "line_inliers": len(t.line_inliers)})
        if not t.ok:
            self._text(f"tracking lost: {t.message}", rr.TextLogLevel.WARN)

    def graph(self, g: GraphResult) -> None:
        pos = np.asarray(g.T_world_cam, float)[:, :3, 3]
        self._keyframes.update({int(k): p for k, p in zip(g.keyframe_ids, pos)})
        self._log_keyframes()
        if len(g.edges):
            strips = pos[np.asarray(g.edges)].astype(np.float32)
            zeta = np.nan_to_num(np.asarray(g.zeta, float), nan=0.0)
            t = zeta / zeta.max() if zeta.size and zeta.max() > 0 else np.zeros(len(strips))
            colors = np.stack([255 * (1 - t), 80 + 175 * t, 60 * np.ones_like(t)], 1).astype(np.uint8)
            colors[np.asarray(g.edge_kind) == EDGE_LOOP] = (255, 0, 255)
            self.rec.log(E["graph"], rr.LineStrips3D(strips, colors=colors))
        self._scalars("backend", {"scale": g.scale})

    def map(self, m: MapResult) -> None:
        self.rec.log(E["map_points"], rr.Points3D(np.asarray(m.points, np.float32), colors=[(230, 230, 230)],
                                                  radii=rr.Radius.ui_points(2)))
        self.rec.log(E["map_lines"], rr.LineStrips3D(np.asarray(m.lines, np.float32), colors=[CYAN]))
        self._scalars("map", {"points": len(m.points), "lines": len(m.lines)})

    def loop(self, lr: LoopResult) -> None:
        verdict = "accepted" if lr.accepted else "rejected"
        self._text(f"loop {lr.query_keyframe}->{lr.match_keyframe} {verdict} (score {lr.score:.3f}, "
                   f"{lr.n_inliers} inliers): {lr.reason}", rr.TextLogLevel.INFO if lr.accepted else rr.TextLogLevel.DEBUG)
        a, b = self._keyframes.get(lr.query_keyframe), self._keyframes.get(lr.match_keyframe)
        if lr.accepted and a is not None and b is not None:
            self._loops.append(np.array([a, b], np.float32))
            self.rec.log(E["loops"], rr.LineStrips3D(self._loops, colors=[(255, 0, 255)], radii=rr.Radius.ui_points(3)))

    def timing(self, t: TimingResult) -> None:
        self._scalars("time", {name: 1e3 * s for name, s in t.seconds.items()})

    def metrics(self, m: MetricsResult) -> None:
        self._scalars("misc", dict(m.values))


_HANDLERS = {
    "FeatureSet": RerunRecorder.features,
    "FeatureMatches": RerunRecorder.matches,
    "DepthPriors": RerunRecorder.depth,
    "DepthDebug": RerunRecorder.depth_debug,
    "KeyframeResult": RerunRecorder.keyframe,
    "TrackingResult": RerunRecorder.tracking,
    "GraphResult": RerunRecorder.graph,
    "MapResult": RerunRecorder.map,
    "LoopResult": RerunRecorder.loop,
    "TimingResult": RerunRecorder.timing,
    "MetricsResult": RerunRecorder.metrics,
}
