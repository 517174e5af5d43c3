"""The Rerun sink: a Recorder that writes every stage to a .rrd file (and optionally serves it), and the entity table.

All entity paths are in `ENTITIES`, the one table of what is logged where. Timelines: `frame` (the dataset's frame
number) and `sensor_time` (seconds). Calibration and ground truth are static. Images are JPEG, scans thinned to a
fixed budget, the per-keyframe debug layers logged on keyframes only, so that a whole KITTI sequence stays a file a
person can attach to a bug report. Scalars are buffered and sent as columns every few frames (and on close): one
`rr.log` costs ~0.2 ms, and a frame has ~30 of them.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from plvo.geometry.camera import backproject, in_image, project
from plvo.geometry.se3 import transform_points
from plvo.recording import RunInfo
from plvo.results import GraphResult, KeyframeResult, LoopResult, MapResult, MetricsResult, TimingResult
from plvo.results import TrackingResult
from plvo.types import DepthPriors, FeatureMatches, FeatureSet, Frame
from plvo_app.rrd_sink import RrdFileSink
from plvo_app.scene_common import (CYAN, GREEN, GREY, MAGENTA, ORANGE, RED, EstimateTrail, depth_colors,
                                   gt_in_estimate_world, inlier_colors, thin, zeta_colors)

log = logging.getLogger(__name__)


class Entity(NamedTuple):
    path: str
    archetype: str
    what: str
    when: str  # "static", "frame" (every frame), "keyframe", "back end" (each back-end step), "event"


ENTITIES: dict[str, Entity] = {
    e.path: e
    for e in [
        Entity("world", "ViewCoordinates", "RDF: OpenCV camera convention (x right, y down, z forward)", "static"),
        Entity("world/camera", "Transform3D", "current estimated camera pose T_world_cam", "frame"),
        Entity("world/camera/image", "Pinhole (static), EncodedImage", "JPEG image and intrinsics", "frame"),
        Entity("world/camera/image/orb", "Points2D", "all ORB keypoints (grey)", "frame"),
        Entity("world/camera/image/tracked_points", "Points2D",
               "keypoints matched to point landmarks: PnP inliers green, outliers red", "frame"),
        Entity("world/camera/image/tracked_lines", "LineStrips2D",
               "segments matched to line landmarks: PnL inliers green, outliers red", "frame"),
        Entity("world/camera/image/lsd_merged", "LineStrips2D", "LSD segments after chaining and merging", "frame"),
        Entity("world/camera/image/lsd_raw", "LineStrips2D", "LSD segments before chaining and merging", "keyframe"),
        Entity("world/camera/image/lidar", "Points2D", "scan projected into the image, coloured by depth", "keyframe"),
        Entity("world/camera/image/patches", "Boxes2D", "point patches searched for depth (green: prior found)",
               "keyframe"),
        Entity("world/camera/image/line_patches", "LineStrips2D", "bands searched around segments for depth",
               "keyframe"),
        Entity("world/lidar", "Transform3D", "lidar pose T_world_velo at the keyframe", "keyframe"),
        Entity("world/lidar/scan", "Points3D", "the keyframe scan, thinned, in the lidar frame", "keyframe"),
        Entity("world/depth/points", "Points3D", "point depth priors of the keyframe", "keyframe"),
        Entity("world/depth/lines", "LineStrips3D", "fitted 3D lines of the keyframe", "keyframe"),
        Entity("world/depth/planes", "Mesh3D", "fitted patch planes of the keyframe's point priors", "keyframe"),
        Entity("world/map/points", "Points3D", "point landmarks of the local window after bundle adjustment",
               "back end"),
        Entity("world/map/lines", "LineStrips3D", "line landmarks of the local window after bundle adjustment",
               "back end"),
        Entity("world/keyframes", "Points3D", "keyframe positions (refined by the back end)", "keyframe"),
        Entity("world/graph", "LineStrips3D", "factor-graph edges: zeta red (0) to green (exp(-2) or more); loops "
               "magenta", "back end"),
        Entity("world/loops", "LineStrips3D", "accepted loop edges", "event"),
        Entity("world/trajectory/est", "LineStrips3D", "estimated trajectory, every frame through its keyframe's "
               "refined pose", "keyframe"),
        Entity("world/trajectory/gt", "LineStrips3D", "ground truth (white) in the estimate's world (its first "
               "frame)", "static"),
        Entity("metrics", "Scalars", "metrics/time/<stage> ms; metrics/{features,tracking,depth,map,backend,loop}/"
               "<count>", "frame"),
        Entity("log", "TextLog", "decisions: initialised, keyframe and why, tracking lost and re-initialised, loops "
               "accepted or rejected and why", "event"),
    ]
}
# Short names used below; every path is a key of ENTITIES (checked at import).
E = {
    "camera": "world/camera", "image": "world/camera/image", "orb": "world/camera/image/orb",
    "tracked_points": "world/camera/image/tracked_points", "tracked_lines": "world/camera/image/tracked_lines",
    "lsd_raw": "world/camera/image/lsd_raw", "lsd_merged": "world/camera/image/lsd_merged",
    "lidar2d": "world/camera/image/lidar", "patches": "world/camera/image/patches",
    "line_patches": "world/camera/image/line_patches", "planes": "world/depth/planes", "lidar": "world/lidar",
    "scan": "world/lidar/scan", "depth_points": "world/depth/points", "depth_lines": "world/depth/lines",
    "map_points": "world/map/points", "map_lines": "world/map/lines", "keyframes": "world/keyframes",
    "graph": "world/graph", "loops": "world/loops", "est": "world/trajectory/est", "gt": "world/trajectory/gt",
}
assert set(E.values()) <= set(ENTITIES)



@dataclass(frozen=True)
class RerunOptions:
    jpeg_quality: int = 40  # KITTI images are noisy: 55 -> 40 saves ~20 % and still reads well
    scan_max_points: int = 4000  # the 3D scan, thinned by stride (a KITTI scan has ~120k)
    overlay_max_points: int = 1500  # the scan projected into the image
    trajectory_max_points: int = 1000
    scalar_flush_frames: int = 25  # scalars are sent as columns this often (and on close)


def blueprint() -> rrb.Blueprint:
    """3D world on the left; the camera image with overlays, time series and the decision log on the right."""
    plots = rrb.Tabs(
        rrb.TimeSeriesView(name="tracking", origin="metrics/tracking"),
        rrb.TimeSeriesView(name="timings (ms)", origin="metrics/time"),
        rrb.TimeSeriesView(name="back end", origin="metrics/backend"),
        rrb.TimeSeriesView(name="other counts", origin="metrics", contents=[
            "+ $origin/**", "- /metrics/time/**", "- /metrics/tracking/**", "- /metrics/backend/**"]),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="3D world", origin="world"),
            rrb.Vertical(rrb.Spatial2DView(name="camera", origin="world/camera/image"), plots,
                         rrb.TextLogView(name="log", origin="log"), row_shares=[3, 2, 1]),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


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
        # Chunks batched over 2 s rather than 0.2 s: the ~40 small entities of a frame otherwise cost ~16 kB of chunk
        # headers a frame; close() flushes, so Ctrl-C loses nothing.
        self.rec = stream or rr.RecordingStream("plvo", batcher_config=rr.ChunkBatcherConfig(
            flush_tick=timedelta(seconds=2), flush_num_bytes=8 << 20))
        # Written from Python (plvo_app/rrd_sink.py), not by rec.save: a full disk raises RecordingError at the step
        # it happens, and the file is cut back to its last complete message, still readable.
        self._sink = None if self.path is None else RrdFileSink(self.rec, self.path, default_blueprint=blueprint())
        self._frame: Frame | None = None
        self._T_world_cam: np.ndarray | None = None
        self._trail = EstimateTrail()
        self._dirty = False  # a keyframe was made: the keyframes and the estimate are logged at the step's end
        self._loops: list[np.ndarray] = []
        self._features: FeatureSet | None = None  # this frame's, for depth, tracking and the keyframe's raw LSD
        self._tracking: Any = None  # this frame's tracking result
        self._point_valid: np.ndarray | None = None  # of the last DepthPriors, for the patch colours
        self._overlay_pending = False
        self._at = -1  # the frame the result being handled belongs to
        self._times: dict[int, float] = {}
        self._scalars_buf: dict[str, tuple[list[int], list[float], list[float]]] = defaultdict(lambda: ([], [], []))
        self._frames_since_flush = 0
        self._closed = False

    # ---- Recorder protocol -------------------------------------------------------------------------------
    def on_run_start(self, info: RunInfo) -> None:
        rec = self.rec
        rec.send_recording_name(info.name)
        rec.send_property("plvo", rr.AnyValues(
            version=info.version, git_revision=info.git_revision, command_line=info.command_line,
            config=info.extra.get("config_toml", repr(info.config)), sequence=info.sequence,
            frames=f"{info.frame_indices[0]}:{info.frame_indices[-1] + 1}" if info.frame_indices else "",
        ))
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        c = info.calib
        rec.log(E["image"], rr.Pinhole(image_from_camera=c.K, resolution=[c.width, c.height],
                                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=1.0), static=True)
        gt = gt_in_estimate_world(info)
        if gt is not None:
            rec.log(E["gt"], rr.LineStrips3D([gt[:, :3, 3].astype(np.float32)], colors=[(235, 235, 235)],
                                             radii=rr.Radius.ui_points(1.5)), static=True)

    def on_frame(self, frame: Frame) -> None:
        rec = self.rec
        self._frame, self._features, self._tracking = frame, None, None
        self._at = int(frame.index)
        self._times[self._at] = float(frame.time)
        self._set_time(self._at)
        shown = frame.image if frame.color is None else cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR)  # colour source
        ok, buf = cv2.imencode(".jpg", shown, [cv2.IMWRITE_JPEG_QUALITY, self.opt.jpeg_quality])
        if ok:
            rec.log(E["image"], rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))

    def on_stage(self, frame_index: int, result: Any) -> None:
        # By class name along the MRO: a stage may hand a richer subclass (the tracker's FrontendResult).
        handler = next((_HANDLERS[c.__name__] for c in type(result).__mro__ if c.__name__ in _HANDLERS), None)
        if handler is None:
            log.debug("no Rerun handler for %s", type(result).__name__)
            return
        # A worker's result (back end, loop closer) arrives a few frames late: log it at its own frame, so that
        # the recording says which keyframe it belongs to whatever the threads' timing.
        current = self._frame.index if self._frame is not None else frame_index
        self._at = int(frame_index)
        if frame_index != current:
            self._set_time(frame_index)
        try:
            handler(self, result)
        finally:
            if frame_index != current:
                self._at = int(current)
                self._set_time(current)

    def _set_time(self, frame_index: int) -> None:
        self.rec.set_time("frame", sequence=int(frame_index))
        if frame_index in self._times:
            self.rec.set_time("sensor_time", duration=self._times[frame_index])

    def set_status(self, status: str, frames_done: int) -> None:
        """Stamp the recording as complete or interrupted (a static property: the last one wins)."""
        self.rec.send_property("plvo_run", rr.AnyValues(status=status, frames_done=frames_done))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._dirty = True  # the final estimate, with what the workers refined in System.finish()
        self._log_dirty()
        self._flush_scalars()
        if self._sink is not None:
            self._sink.close()
        else:
            self.rec.flush()

    # ---- helpers -----------------------------------------------------------------------------------------
    def _scalars(self, prefix: str, values: dict[str, float]) -> None:
        if self._at < 0:
            return
        f, t = self._at, self._times.get(self._at, 0.0)
        for name, value in values.items():
            frames, times, vals = self._scalars_buf[f"metrics/{prefix}/{name}"]
            frames.append(f)
            times.append(t)
            vals.append(float(value))

    def _flush_scalars(self) -> None:
        for path, (frames, times, vals) in self._scalars_buf.items():
            if frames:
                self.rec.send_columns(path, indexes=[rr.TimeColumn("frame", sequence=frames),
                                                     rr.TimeColumn("sensor_time", duration=times)],
                                      columns=rr.Scalars.columns(scalars=np.asarray(vals)))
        self._scalars_buf.clear()
        self._frames_since_flush = 0

    def _text(self, text: str, level: str = rr.TextLogLevel.INFO) -> None:
        self.rec.log("log", rr.TextLog(text, level=level))

    def _log_dirty(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        kfs = self._trail.keyframe_positions()
        if len(kfs):
            self.rec.log(E["keyframes"], rr.Points3D(kfs.astype(np.float32), colors=[ORANGE],
                                                     radii=rr.Radius.ui_points(5)))
        est = self._trail.positions().astype(np.float32)
        if len(est) >= 2:
            est = np.vstack([est[thin(len(est), self.opt.trajectory_max_points)], est[-1:]])
            self.rec.log(E["est"], rr.LineStrips3D([est], colors=[GREEN], radii=rr.Radius.ui_points(2)))

    # ---- stage handlers ----------------------------------------------------------------------------------
    def features(self, fs: FeatureSet) -> None:
        rec = self.rec
        self._features = fs
        rec.log(E["orb"], rr.Points2D(np.asarray(fs.keypoints, np.float32), colors=[GREY],
                                      radii=rr.Radius.ui_points(2)))
        rec.log(E["lsd_merged"], rr.LineStrips2D(_segments_2d(fs.segments), colors=[CYAN],
                                                 radii=rr.Radius.ui_points(1.5)))
        self._scalars("features", {"points": fs.n_points, "lines": fs.n_lines, "raw_segments": len(fs.raw_segments)})

    def matches(self, m: FeatureMatches) -> None:
        self._scalars("matching", {"points": len(m.points), "lines": len(m.lines)})

    def tracking(self, t: TrackingResult) -> None:
        self._tracking = t
        self._T_world_cam = np.asarray(t.T_world_cam, dtype=float)
        self.rec.log(E["camera"], _transform(self._T_world_cam))
        self._trail.on_tracking(t.frame_index, self._T_world_cam)
        counts = {"point_matches": t.n_point_matches, "line_matches": t.n_line_matches,
                  "point_inliers": len(t.point_inliers), "line_inliers": len(t.line_inliers), "lost": int(not t.ok)}
        uv = getattr(t, "point_uv", None)  # the tracker's FrontendResult: its 3D-2D matches with their verdicts
        if uv is not None:
            segs = np.asarray(t.line_segments)
            self.rec.log(E["tracked_points"], rr.Points2D(np.asarray(uv, np.float32), colors=inlier_colors(
                t.point_inlier), radii=rr.Radius.ui_points(3.5)))
            self.rec.log(E["tracked_lines"], rr.LineStrips2D(_segments_2d(segs), colors=inlier_colors(
                t.line_inlier), radii=rr.Radius.ui_points(2.5)))
            counts.update(point_landmarks=len(uv), line_landmarks=len(segs), new_points=t.n_new_points,
                          new_lines=t.n_new_lines)
        self._scalars("tracking", counts)
        status = getattr(t, "status", "reinitialised" if not t.ok else "tracked")
        if status == "reinitialised" or not t.ok:
            self._text(t.message or f"frame {t.frame_index}: tracking lost", rr.TextLogLevel.WARN)
        elif status == "initialised":
            self._text(f"frame {t.frame_index}: initialised from lidar depth ({getattr(t, 'n_new_points', 0)} point "
                       f"and {getattr(t, 'n_new_lines', 0)} line landmarks)")

    def keyframe(self, kf: KeyframeResult) -> None:
        T = kf.T_world_cam if kf.T_world_cam is not None else self._T_world_cam
        if T is not None:
            self._trail.on_keyframe(kf.keyframe_id, kf.frame_index, T)
            self._dirty = True
        t = self._tracking
        new = f": {t.n_new_points} new point and {t.n_new_lines} new line landmarks" \
            if t is not None and hasattr(t, "n_new_points") else ""
        self._text(f"frame {kf.frame_index}: keyframe {kf.keyframe_id} ({kf.reason}){new}")
        fs = self._features
        if fs is not None:  # raw LSD output: on keyframes only (~11 kB a frame otherwise)
            self.rec.log(E["lsd_raw"], rr.LineStrips2D(_segments_2d(fs.raw_segments), colors=[RED],
                                                       radii=rr.Radius.ui_points(1)))
        self._log_scan()

    def _log_scan(self) -> None:
        frame = self._frame
        if frame is None or self._T_world_cam is None:
            return
        scan = frame.scan[thin(len(frame.scan), self.opt.scan_max_points), :3]
        self.rec.log(E["lidar"], _transform(self._T_world_cam @ frame.calib.T_cam_velo))
        self.rec.log(E["scan"], rr.Points3D(scan.astype(np.float32), colors=depth_colors(np.linalg.norm(scan, axis=1)),
                                            radii=rr.Radius.ui_points(1.5)))
        self._overlay_pending = True  # the DepthDebug brings the projected scan; else it is made at the step's end

    def _log_scan_overlay(self, frame: Frame) -> None:
        """The projected scan when the depth stage gave no DepthDebug (the no-depth-priors ablation)."""
        c = frame.calib
        pts = transform_points(c.T_cam_velo, frame.scan[thin(len(frame.scan), 4 * self.opt.overlay_max_points), :3])
        uv, z = project(c.K, pts)
        keep = in_image(uv, c.width, c.height) & (z > 0.5)
        self._log_overlay(uv[keep], z[keep])

    def _log_overlay(self, uv: np.ndarray, z: np.ndarray) -> None:
        s = thin(len(uv), self.opt.overlay_max_points)
        self.rec.log(E["lidar2d"], rr.Points2D(np.asarray(uv)[s].astype(np.float32), colors=depth_colors(z[s]),
                                               radii=rr.Radius.ui_points(1.5)))

    def depth(self, d: DepthPriors) -> None:
        self._point_valid = np.asarray(d.point_valid)
        self._scalars("depth", {"point_priors": int(np.sum(d.point_valid)), "line_priors": int(np.sum(d.line_valid))})
        if self._T_world_cam is None:
            return
        T = self._T_world_cam  # the priors are in this keyframe's camera frame; drawn where the camera is
        lines = np.asarray(d.line_endpoints, float)[d.line_valid].reshape(-1, 3)
        self.rec.log(E["depth_lines"], rr.LineStrips3D(transform_points(T, lines).reshape(-1, 2, 3).astype(
            np.float32), colors=[CYAN]))
        fs = self._features
        if fs is not None and len(fs.keypoints) == len(d.point_depth):
            ok = d.point_valid
            pts = transform_points(T, backproject(self._frame.calib.K, np.asarray(fs.keypoints, float)[ok],
                                                  d.point_depth[ok]))
            self.rec.log(E["depth_points"], rr.Points3D(pts.astype(np.float32), colors=[GREEN],
                                                        radii=rr.Radius.ui_points(3)))

    def depth_debug(self, dbg: Any) -> None:
        """plvo.depth.extract.DepthDebug: projected scan, searched patches, fitted planes (camera frame, pixels)."""
        self._overlay_pending = False
        self._log_overlay(np.asarray(dbg.scan_uv), np.asarray(dbg.scan_depth))
        boxes = np.asarray(dbg.point_boxes, np.float32).reshape(-1, 4)
        valid = self._point_valid if self._point_valid is not None and len(self._point_valid) == len(boxes) \
            else np.zeros(len(boxes), bool)
        self.rec.log(E["patches"], rr.Boxes2D(mins=boxes[:, :2], sizes=boxes[:, 2:] - boxes[:, :2],
                                              colors=inlier_colors(valid)))
        bands = np.asarray(dbg.line_bands, np.float32).reshape(-1, 4, 2)
        self.rec.log(E["line_patches"], rr.LineStrips2D(np.concatenate([bands, bands[:, :1]], axis=1), colors=[CYAN]))
        self._scalars("time/depth", dict(dbg.timings_ms))
        quads = np.asarray(dbg.plane_quads, float).reshape(-1, 4, 3)
        quads = quads[np.all(np.isfinite(quads), axis=(1, 2))]
        if self._T_world_cam is not None and len(quads):
            verts = transform_points(self._T_world_cam, quads.reshape(-1, 3)).astype(np.float32)
            base = 4 * np.arange(len(quads))[:, None]
            tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.uint32)
            self.rec.log(E["planes"], rr.Mesh3D(vertex_positions=verts, triangle_indices=tris, albedo_factor=GREEN))

    def graph(self, g: GraphResult) -> None:
        poses = np.asarray(g.T_world_cam, float)
        self._trail.on_graph(g.keyframe_ids, poses)  # drawn at the next keyframe (and on close)
        if len(g.edges):
            strips = poses[:, :3, 3][np.asarray(g.edges)].astype(np.float32)
            self.rec.log(E["graph"], rr.LineStrips3D(strips, colors=zeta_colors(g.zeta, g.edge_kind),
                                                     radii=rr.Radius.ui_points(2.5)))
        self._scalars("backend", {"scale": g.scale, "edges": len(g.edges)})

    def map(self, m: MapResult) -> None:
        self.rec.log(E["map_points"], rr.Points3D(np.asarray(m.points, np.float32), colors=[(150, 150, 160)],
                                                  radii=rr.Radius.ui_points(2)))
        self.rec.log(E["map_lines"], rr.LineStrips3D(np.asarray(m.lines, np.float32), colors=[CYAN]))
        self._scalars("map", {"points": len(m.points), "lines": len(m.lines)})

    def loop(self, lr: LoopResult) -> None:
        verdict = "accepted" if lr.accepted else "rejected"
        self._text(f"loop keyframe {lr.query_keyframe} -> {lr.match_keyframe} {verdict} (score {lr.score:.3f}, "
                   f"{lr.n_inliers} inliers): {lr.reason}", rr.TextLogLevel.INFO if lr.accepted else rr.TextLogLevel.DEBUG)
        kf = self._trail.kf_pose
        if lr.accepted and lr.query_keyframe in kf and lr.match_keyframe in kf:
            self._loops.append(np.array([kf[lr.query_keyframe][:3, 3], kf[lr.match_keyframe][:3, 3]], np.float32))
            self.rec.log(E["loops"], rr.LineStrips3D(self._loops, colors=[MAGENTA], radii=rr.Radius.ui_points(3)))

    def timing(self, t: TimingResult) -> None:
        """The last result of a step: the keyframes and the estimate are logged here, once a step."""
        self._scalars("time", {name: 1e3 * s for name, s in t.seconds.items()})
        if self._overlay_pending and self._frame is not None:
            self._overlay_pending = False
            self._log_scan_overlay(self._frame)
        self._log_dirty()
        self._frames_since_flush += 1
        if self._frames_since_flush >= self.opt.scalar_flush_frames:
            self._flush_scalars()
        if self._sink is not None:
            self._sink.pump()  # raises the writer thread's first failed write, if any

    def metrics(self, m: MetricsResult) -> None:
        groups: dict[str, dict[str, float]] = defaultdict(dict)
        for name, value in m.values.items():
            if name.endswith("_ms"):
                groups["time"][name[:-3].removeprefix("backend_")] = value
            elif name.startswith("loop_"):
                groups["loop"][name[5:]] = value
            else:
                groups["backend"][name] = value
        for prefix, values in groups.items():
            self._scalars(prefix, values)


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
