"""The Rerun sink: a Recorder that writes every stage to a .rrd file (and optionally serves it), and the entity table.

All entity paths are in `ENTITIES`, the one table of what is logged where. Timelines: `frame` (the dataset's frame
number) and `sensor_time` (seconds). Calibration and ground truth are static. Images are JPEG, scans thinned to a
fixed budget, the per-keyframe debug layers logged on keyframes only. Which frames get the detail layers at all is
the recording level's (plvo_app.recording_levels): every entity of level "summary" is written at full length, those
of level "detail" on the level's detail frames only (all frames at `--record full`), so that a whole sequence stays
a file a person can attach to a bug report. Detail that stops is cleared (a Clear at the first frame without it), so
a viewer never shows a stale image as the current one. Every keyframe also gets its scan and image thinned to a few
kB (summary level: world/lidar/thin/*, world/camera/image/keyframe), so that a replay shows the road on every frame
(latest-at: its keyframe's); the scan as points (level "full") is written at `--record full` only. On close the
recording gets the list of its detail frames and why ("detail", and the property plvo_detail the viewers read).
Scalars and the camera pose are buffered and sent as columns every 200 frames (and on close): one `rr.log` costs
~0.2 ms, and a frame has ~30 of them.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import rerun as rr

from plvo.depth.extract import DepthDebug
from plvo.geometry.camera import backproject, in_image, project
from plvo.geometry.se3 import transform_points
from plvo.recording import RunInfo
from plvo.results import (
    EdgeKind,
    GraphResult,
    KeyframeResult,
    LoopResult,
    MapResult,
    MetricsResult,
    TimingResult,
    TrackingResult,
)
from plvo.types import DepthPriors, FeatureMatches, FeatureSet, Frame
from plvo_app.recording_levels import DetailOptions, DetailPolicy
from plvo_app.recording_levels import Lazy as _Lazy
from plvo_app.recording_levels import WarningCapture as _WarningCapture
from plvo_app.rrd_blueprint import blueprint
from plvo_app.rrd_compact import compact as compact_file
from plvo_app.rrd_sink import RrdFileSink
from plvo_app.run_identity import INPUT_HASH, INPUT_IMAGE, INPUT_SCAN, encode_inputs, file_digest, machine
from plvo_app.scene_common import (
    CYAN,
    DEPTH_FAR,
    DEPTH_NEAR,
    GREEN,
    GREY,
    MAGENTA,
    ORANGE,
    RED,
    EstimateTrail,
    RangeFaces,
    depth_colors,
    gt_in_estimate_world,
    inlier_colors,
    thin,
    zeta_colors,
)

log = logging.getLogger(__name__)


class Entity(NamedTuple):
    path: str
    archetype: str
    what: str
    when: str  # "static", "frame" (every frame), "keyframe", "back end" (each back-end step), "event"
    level: str = "detail"  # "summary": at full length in every level; "detail": on the level's detail frames;
    # "full": at the full level only; "inputs": only in the --embed-inputs window


ENTITIES: dict[str, Entity] = {
    e.path: e
    for e in [
        Entity("world", "ViewCoordinates", "RDF: OpenCV camera convention (x right, y down, z forward)", "static",
               "summary"),
        Entity("world/camera", "Transform3D", "current estimated camera pose T_world_cam", "frame", "summary"),
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
        Entity("world/camera/image/keyframe", "Transform3D (static scale), EncodedImage",
               "the keyframe's image at 1/thin_image_scale size, JPEG, scaled up to the pinhole's pixels and drawn "
               "under the full image: the camera panel between detail frames", "keyframe", "summary"),
        Entity("world/lidar", "Transform3D", "lidar pose T_world_velo at the keyframe", "keyframe", "summary"),
        Entity("world/lidar/scan", "Points3D", "the keyframe scan, thinned, in the lidar frame; at the full level "
               "only: at the others the thin scan of the same keyframe stands for it (3700 of its 4000 points on "
               "KITTI, 3 kB instead of 60)", "keyframe", "full"),
        *[Entity(f"world/lidar/thin/{k}", "Transform3D and Pinhole (static), EncodedDepthImage",
                 f"the keyframe scan thinned for every level: depth image {k} of scene_common.RangeFaces (a 16-bit "
                 "PNG), drawn by Rerun as points", "keyframe", "summary") for k in range(RangeFaces().n)],
        Entity("world/depth/points", "Points3D", "point depth priors of the keyframe", "keyframe"),
        Entity("world/depth/lines", "LineStrips3D", "fitted 3D lines of the keyframe", "keyframe"),
        Entity("world/depth/planes", "Mesh3D", "fitted patch planes of the keyframe's point priors", "keyframe"),
        Entity("world/map/points", "Points3D", "point landmarks of the local window after bundle adjustment",
               "back end", "summary"),
        Entity("world/map/lines", "LineStrips3D", "line landmarks of the local window after bundle adjustment",
               "back end", "summary"),
        Entity("world/keyframes", "Points3D", "keyframe positions (refined by the back end)", "keyframe", "summary"),
        Entity("world/graph", "LineStrips3D", "factor-graph edges: zeta red (0) to green (exp(-2) or more); loops "
               "magenta. The whole graph: each back-end step at the full level and on detail frames, else every "
               "summary_every_keyframes keyframes and on close (it grows with the run); covisibility edges with "
               "the detail only", "back end", "summary"),
        Entity("world/graph/recent", "LineStrips3D", "the edges among the last summary_every_keyframes keyframes, "
               "each back-end step the whole graph is not written", "back end", "summary"),
        Entity("world/loops", "LineStrips3D", "accepted loop edges", "event", "summary"),
        Entity("world/trajectory/est", "LineStrips3D", "estimated trajectory, every frame through its keyframe's "
               "refined pose", "keyframe", "summary"),
        Entity("world/trajectory/gt", "LineStrips3D", "ground truth (white) in the estimate's world (its first "
               "frame)", "static", "summary"),
        Entity("metrics", "Scalars", "metrics/time/<stage> ms; metrics/{features,tracking,depth,map,backend,loop}/"
               "<count>", "frame", "summary"),
        Entity(INPUT_IMAGE, "AnyValues png", "the frame's image as PNG (lossless), for plvo reproduce", "frame",
               "inputs"),
        Entity(INPUT_SCAN, "AnyValues scan, time", "the scan's float32 bytes and the frame time", "frame", "inputs"),
        Entity("log", "TextLog", "decisions: initialised, keyframe and why, tracking lost and re-initialised, loops "
               "accepted or rejected and why", "event", "summary"),
        Entity("detail", "TextDocument (static)", "the frames with full detail and why, written on close (also as "
               "the property plvo_detail: windows, JSON [[first, end, why], ...])", "static", "summary"),
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
    "graph": "world/graph", "graph_recent": "world/graph/recent", "loops": "world/loops",
    "est": "world/trajectory/est", "gt": "world/trajectory/gt", "image_kf": "world/camera/image/keyframe",
    "thin": "world/lidar/thin", "detail": "detail",
}
assert set(E.values()) - {E["thin"]} <= set(ENTITIES)



@dataclass(frozen=True)
class RerunOptions:
    jpeg_quality: int = 40  # KITTI images are noisy: 55 -> 40 saves ~20 % and still reads well
    scan_max_points: int = 4000  # the 3D scan (full level), thinned by stride (a KITTI scan has ~120k)
    overlay_max_points: int = 1500  # the scan projected into the image
    trajectory_max_points: int = 1000
    # Scalars and camera poses are sent as columns this often (and on close): each send is a chunk of each of ~60
    # series, ~1 kB of schema apiece; every 25 frames that was 2.4 kB a frame, more than the data.
    scalar_flush_frames: int = 200
    detail: DetailOptions = DetailOptions()  # the recording level: which frames get the detail entities
    # Outside detail frames the map at each keyframe is thinned to this (a KITTI window has ~3000 points, 31 kB): a
    # hint of where the landmarks are, every keyframe's thin scan showing the scene (100 points and 25 lines were
    # 3.3 MB of a 4541-frame run on the synthetic town, these 1.8)
    map_summary_points: int = 50
    map_summary_lines: int = 12
    # Outside detail frames the keyframes and the estimate (they grow with the run) are redrawn this often
    summary_every_keyframes: int = 20
    graph_summary_edges: int = 500  # and the whole graph then thinned to this (loops all kept)
    # Every thin_every_keyframes-th keyframe (every one), at every level: its scan as depth images (the number of
    # faces is ENTITIES') and its image at 1/thin_image_scale size, JPEG quality thin_image_quality. Sized by the
    # default level's budget, 25 MB for a whole KITTI 00 (4541 frames; plvo_app.level_sizes): ~3.2 kB of scan and
    # ~2.3 kB of image a KITTI keyframe (2.4 and 2.3 on the synthetic town), estimated at 22.4 MB from KITTI 04 and
    # 23.7 from the town's 300 frames (at its rate 1665 keyframes; every event window used). Every keyframe as every
    # second one was (quality 40, the faces' depth at 0.1 m) came to ~29 MB on the town; of that, the faces' 0.2 m
    # steps past 5 m and the PNGs' run-length strategy took 0.5 MB, quality 35 0.3 (hard to tell from 40 at the
    # viewer's 320 pixels; 30 shows blocks), the 3D scan written at the full level only 2.6 (the thin one stands
    # for it) and the map thinned to 50 points 1.6. (Every keyframe at 1/4 and 1.5 degrees, ~10 kB, came to ~34 MB.)
    thin_scan: RangeFaces = RangeFaces()
    thin_image_scale: int = 5
    thin_image_quality: int = 35
    thin_every_keyframes: int = 1
    embed_inputs: tuple[int, int] | None = None  # frames [A, B) whose raw inputs are embedded (plvo reproduce)
    compact_on_close: bool | None = None  # merge the chunks on close (plvo_app.rrd_compact); None: unless "full"


def _segments_2d(seg: np.ndarray) -> np.ndarray:
    return np.asarray(seg, dtype=np.float32).reshape(-1, 2, 2)


def _points2d(xy: np.ndarray, colors: list | None, radius_ui: float, inliers: np.ndarray | None = None) -> rr.Points2D:
    """Pixels as Points2D: one colour, or green/red by `inliers`."""
    return rr.Points2D(np.asarray(xy, np.float32), colors=colors if inliers is None else inlier_colors(inliers),
                       radii=rr.Radius.ui_points(radius_ui))


def _strips2d(seg: np.ndarray, colors: list | None, radius_ui: float, inliers: np.ndarray | None = None
              ) -> rr.LineStrips2D:
    """(N,4) segments as LineStrips2D: one colour, or green/red by `inliers`."""
    return rr.LineStrips2D(_segments_2d(seg), colors=colors if inliers is None else inlier_colors(inliers),
                           radii=rr.Radius.ui_points(radius_ui))


def _transform(T: np.ndarray) -> rr.Transform3D:
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


def _new_stream() -> rr.RecordingStream:
    # Chunks batched over 2 s rather than 0.2 s: the ~40 small entities of a frame otherwise cost ~16 kB of chunk
    # headers a frame. Not longer: the batcher's tick is also how late a failed write (a full disk) is seen; the
    # summary and default levels are compacted on close (rrd_compact), which merges the chunks anyway. close()
    # flushes, so Ctrl-C loses nothing.
    return rr.RecordingStream("plvo", batcher_config=rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=2),
                                                                          flush_num_bytes=4 << 20))


def _set_aside(path: Path, suffix: str) -> Path:
    """Move the file at `path` to the first free of <stem><suffix>, <stem><suffix>-2... beside it (never over a
    file) -> where it went."""
    n = 1
    while True:
        target = path.with_name(f"{path.stem}{suffix}{'' if n == 1 else f'-{n}'}{path.suffix}")
        try:
            os.link(path, target)
        except FileExistsError:
            n += 1
            continue
        except OSError:  # a file system without hard links: renamed where the name is free (checked just before)
            if target.exists():
                n += 1
                continue
            os.rename(path, target)
            return target
        os.unlink(path)
        return target


class RerunRecorder:
    """Writes a run to `path` (.rrd, streamed as it goes, readable even if the run is cut short).

    stream: an existing RecordingStream (tests, or one also served over gRPC); otherwise one is made and saved.
    """

    def __init__(self, path: str | Path | None, options: RerunOptions | None = None,
                 stream: rr.RecordingStream | None = None, next_free: bool = False):
        self.path = None if path is None else Path(path)
        self.opt = options or RerunOptions()
        self.rec = stream or _new_stream()
        # Written from Python (plvo_app/rrd_sink.py), not by rec.save: a full disk raises RecordingError at the step
        # it happens, and the file is cut back to its last complete message, still readable.
        self._sink = None if self.path is None else RrdFileSink(self.rec, self.path, default_blueprint=blueprint(),
                                                                next_free=next_free)
        if self._sink is not None:
            self.path = self._sink.path  # next_free: path-2, -3... when path was taken
        self.before_restart: Path | None = None  # the recording of the frames before a restart (on_restart)
        self._fresh()

    def _fresh(self) -> None:
        """The state of a recording of no frame yet."""
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
        self._last_step_end: float | None = None  # perf_counter at the end of the last step (slow frames)
        self._closed = False
        self._policy = DetailPolicy(self.opt.detail)
        self._shown: dict[str, str] = {}  # detail entity -> its cadence, written since it was last cleared
        self._kf_frame = -1  # the frame of the last keyframe
        self._kfs_since_summary = 0
        self._kfs_since_graph = 1 << 30  # the first graph is written whole
        self._last_graph: tuple[int, GraphResult] | None = None  # not yet written whole: written on close
        self._poses_buf: tuple[list[int], list[float], list[np.ndarray]] = ([], [], [])
        self._warnings = _WarningCapture()
        self._input_files: dict[int, tuple[str, str]] = {}
        self._hashes: dict[int, tuple[str, str]] = {}
        self._detail_frames: set[int] = set()  # frames a detail entity was written at
        self._n_kf = 0
        self._thin_size: tuple[int, int] | None = None

    # ---- Recorder protocol -------------------------------------------------------------------------------
    def on_run_start(self, info: RunInfo) -> None:
        rec = self.rec
        rec.send_recording_name(info.name)
        rec.send_property("plvo", rr.AnyValues(
            version=info.version, git_revision=info.git_revision, command_line=info.command_line,
            config=info.extra.get("config_toml", repr(info.config)), sequence=info.sequence,
            frames=f"{info.frame_indices[0]}:{info.frame_indices[-1] + 1}" if info.frame_indices else "",
            record_level=self.opt.detail.level,
        ))
        ds = info.extra.get("dataset")
        if ds:  # what plvo reproduce needs to find and check the inputs again
            rec.send_property("plvo_dataset", rr.AnyValues(**{k: json.dumps(v) if isinstance(v, (dict, list)) else v
                                                              for k, v in ds.items()}))
        rec.send_property("plvo_machine", rr.AnyValues(**machine()))
        self._input_files = dict(info.extra.get("input_files", {}))
        logging.getLogger("plvo").addHandler(self._warnings)
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        c = info.calib
        rec.log(E["image"], rr.Pinhole(image_from_camera=c.K, resolution=[c.width, c.height],
                                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=1.0), static=True)
        self._log_thin_statics(c.K, c.width, c.height)
        gt = gt_in_estimate_world(info)
        if gt is not None:
            rec.log(E["gt"], rr.LineStrips3D([gt[:, :3, 3].astype(np.float32)], colors=[(235, 235, 235)],
                                             radii=rr.Radius.ui_points(1.5)), static=True)

    def on_restart(self, info: RunInfo) -> None:
        """The frames so far are superseded: their recording is closed, stamped "restarted" and kept beside as
        <name>-before-restart.rrd (what the run saw before it knew better), and this path gets a new recording of
        the run that counts, which says why in its `plvo_restart` property and decision log. A stream handed in
        (served, tests) carries on: the run's frames are logged again over the first ones."""
        why = info.extra.get("restart", {})
        if self._sink is not None and self.path is not None:
            path = self.path
            self.set_status("restarted", int(why.get("frames_before", 0)))
            self.close()
            if path.exists():
                self.before_restart = _set_aside(path, "-before-restart")
            self.rec = _new_stream()
            self._sink = RrdFileSink(self.rec, path, default_blueprint=blueprint())
        else:  # the frames' buffered series are dropped, the warnings so far logged
            self._drain_warnings()
            logging.getLogger("plvo").removeHandler(self._warnings)
        self._fresh()
        self.on_run_start(info)
        self.rec.send_property("plvo_restart", rr.AnyValues(
            **{k: "" if v is None else v for k, v in why.items()},
            before=str(self.before_restart or "")))

    def on_frame(self, frame: Frame) -> None:
        rec = self.rec
        self._frame, self._features, self._tracking = frame, None, None
        self._at = int(frame.index)
        self._times[self._at] = float(frame.time)
        self._set_time(self._at)
        files = self._input_files.get(self._at)
        if files is not None:  # the dataset just read them: hashing hits the page cache (~0.15 ms a frame)
            self._hashes[self._at] = (file_digest(files[0])[:HASH_HEX], file_digest(files[1])[:HASH_HEX])
        emb = self.opt.embed_inputs
        if emb is not None and emb[0] <= self._at < emb[1]:
            png, scan = encode_inputs(frame)
            rec.log(INPUT_IMAGE, rr.AnyValues(png=[png]))
            rec.log(INPUT_SCAN, rr.AnyValues(scan=[scan], time=[float(frame.time)]))
        shown = frame.image if frame.color is None else cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR)  # colour source
        if self._policy.want(self._at):  # else the JPEG is made only if an event wants this frame
            self._log(E["image"], self._jpeg(shown))
        else:
            self._policy.defer(self._at, (E["image"], _Lazy(self._jpeg, shown)))

    def _jpeg(self, image: np.ndarray) -> rr.EncodedImage | None:
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.opt.jpeg_quality])
        return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg") if ok else None

    def on_stage(self, frame_index: int, result: Any) -> None:
        self._drain_warnings()
        # Along the MRO: a stage may hand a richer subclass (the tracker's FrontendResult).
        handler = next((_HANDLERS[c] for c in type(result).__mro__ if c in _HANDLERS), None)
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
        """Stamp the recording as complete or interrupted (a static property: the last one wins). A run cut short
        (Ctrl-C, an error) stopped inside frame `frames_done`'s step: the pose and scalars its stages had buffered
        are dropped, so that the recording's per-frame series end with the frames done, as its status says."""
        if status != "complete":
            self._drop_buffered_from(int(frames_done))
        self.rec.send_property("plvo_run", rr.AnyValues(status=status, frames_done=frames_done))

    def _drop_buffered_from(self, frame: int) -> None:
        for buf in (*self._scalars_buf.values(), self._poses_buf):
            # an interrupted step may have appended to some of a buffer's columns only: the rows all of them have
            n = min(len(column) for column in buf)
            keep = [k for k, f in enumerate(buf[0][:n]) if f < frame]
            for column in buf:
                column[:] = [column[k] for k in keep]

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        logging.getLogger("plvo").removeHandler(self._warnings)
        self._drain_warnings()
        self._dirty = True  # the final estimate, with what the workers refined in System.finish()
        self._log_dirty(force=True)
        if self._last_graph is not None:  # the final graph, whole
            self._at = self._last_graph[0]
            self._set_time(self._at)
            self._log_graph(self._last_graph[1], whole=True)
        self._flush_scalars()
        self._log_detail_list()
        if self._hashes:
            frames = sorted(self._hashes)
            self.rec.send_property("plvo_inputs", rr.AnyValues(
                frames=json.dumps(frames), hash=INPUT_HASH, image_hash=[self._hashes[f][0] for f in frames],
                scan_hash=[self._hashes[f][1] for f in frames], times=[self._times[f] for f in frames]))
        if self._sink is None:
            self.rec.flush()
            return
        self._sink.close()  # raises RecordingError on a failed write; the file is then kept as it is
        compact = self.opt.compact_on_close
        if compact or (compact is None and not self._policy.everything):
            compact_file(self.path)

    def _log_detail_list(self) -> None:
        """Where the detail is and why: a document for Rerun's panel, the property for the viewers (plvo view)."""
        runs = self._policy.detail_runs(self._detail_frames)
        opt = self.opt.detail
        says = {"summary": "detail only in the --detail windows",
                "default": f"detail on 1 in {opt.keyframe_stride} keyframes and around events (at most "
                           f"{opt.max_event_windows} windows)",
                "full": "detail on every frame"}[opt.level]
        k = max(1, self.opt.thin_every_keyframes)
        lines = [f"# Full detail\n\nRecording level **{opt.level}**: {says}; "
                 f"{'every keyframe' if k == 1 else f'1 in {k} keyframes'} has its scan and image thinned.\n",
                 "| frames | why |", "|---|---|"]
        lines += [f"| {a}{'' if b == a + 1 else f'-{b - 1}'} | {why} |" for a, b, why in runs]
        if not runs:
            lines.append("| none | |")
        missed = [(f, why) for f, why in self._policy.events
                  if not any(a <= f < b for a, b, _ in runs)]
        if missed:
            lines.append(f"\n{len(missed)} events without detail (past the cap, or known after their frames were "
                         "dropped): " + ", ".join(f"{why} at {f}" for f, why in missed[:50]))
        self.rec.log(E["detail"], rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True)
        self.rec.send_property("plvo_detail", rr.AnyValues(level=opt.level, windows=json.dumps(
            [[int(a), int(b), why] for a, b, why in runs])))

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
        frames, times, poses = self._poses_buf
        if frames:
            T = np.asarray(poses)
            self.rec.send_columns(E["camera"], indexes=[rr.TimeColumn("frame", sequence=frames),
                                                        rr.TimeColumn("sensor_time", duration=times)],
                                  columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]))
        self._poses_buf = ([], [], [])

    # ---- detail: written now, held back for an event, or cleared -----------------------------------------
    def _log(self, path: str, archetype: Any) -> None:
        """Write `archetype` (or what a Lazy makes) to `path` at the current frame, if the recording level wants it
        there; else hold it back, a Lazy unmade (an entity of level "full" below the full level: dropped)."""
        if archetype is None:
            return
        level = ENTITIES[path].level
        if level == "full" and not self._policy.everything:
            return
        if level == "detail" and not self._policy.want(self._at):
            self._policy.defer(self._at, (path, archetype))
            return
        archetype = archetype() if isinstance(archetype, _Lazy) else archetype
        if archetype is None:
            return
        self.rec.log(path, archetype)
        if ENTITIES[path].level == "detail":
            self._shown[path] = ENTITIES[path].when
            self._detail_frames.add(self._at)

    def _write_held(self, frames: list[int]) -> None:
        """Frames that became detail (a stride keyframe, an event): write what was held back for them."""
        held = self._policy.take(frames)
        for f, (path, archetype) in held:
            self._set_time(f)
            archetype = archetype() if isinstance(archetype, _Lazy) else archetype
            if archetype is not None:
                self.rec.log(path, archetype)
                if ENTITIES[path].level == "detail":
                    self._shown[path] = ENTITIES[path].when
                    self._detail_frames.add(f)
        if held:
            self._set_time(self._at)

    def _event(self, why: str) -> None:
        self._write_held(self._policy.event(self._at, why))

    def _clear_stale(self, frame: int) -> None:
        """At a frame without detail: clear the per-frame detail shown before (and the per-keyframe detail on a
        keyframe), so that latest-at does not show an old image as this frame's."""
        if not self._shown or self._policy.want(frame):
            return
        for path, when in list(self._shown.items()):
            if when == "frame" or frame == self._kf_frame:
                # the image's entity also holds the static Pinhole, which a Clear may wrongly hide in the viewer
                # (rerun-io/rerun#11919): empty the image's own components instead
                self.rec.log(path, rr.EncodedImage.cleared() if path == E["image"] else rr.Clear(recursive=False))
                del self._shown[path]

    def _drain_warnings(self) -> None:
        """Warnings of the pipeline (e.g. a discarded optimisation) go to the log and open a detail window."""
        while self._warnings.records:
            record = self._warnings.records.popleft()
            self._text(f"frame {self._at}: {record.name}: {record.getMessage()}", rr.TextLogLevel.WARN)
            self._event(f"warning {record.name}")

    def _text(self, text: str, level: str = rr.TextLogLevel.INFO) -> None:
        self.rec.log("log", rr.TextLog(text, level=level))

    def _log_dirty(self, force: bool = False) -> None:
        if not self._dirty:
            return
        # Early in a run, when they are small, redrawn more often (1 in n/4 keyframes): a replay shows the trajectory
        # from its first seconds on, not from the 20th keyframe (~+100 kB over a 4541-frame run)
        every = min(self.opt.summary_every_keyframes, max(1, len(self._trail.kf_pose) // 4))
        if not (force or self._policy.everything or self._policy.want(self._at) or self._kfs_since_summary >= every):
            return
        self._dirty = False
        self._kfs_since_summary = 0
        kfs = self._trail.keyframe_positions()
        if not (self._policy.everything or self._policy.want(self._at)):
            kfs = kfs[thin(len(kfs), self.opt.trajectory_max_points)]
        if len(kfs):
            self.rec.log(E["keyframes"], rr.Points3D(kfs.astype(np.float32), colors=[ORANGE],
                                                     radii=rr.Radius.ui_points(5)))
        est = self._trail.positions().astype(np.float32)
        if len(est) >= 2:
            est = np.vstack([est[thin(len(est), self.opt.trajectory_max_points)], est[-1:]])
            self.rec.log(E["est"], rr.LineStrips3D([est], colors=[GREEN], radii=rr.Radius.ui_points(2)))

    # ---- stage handlers ----------------------------------------------------------------------------------
    def features(self, fs: FeatureSet) -> None:
        self._features = fs
        # made only for frames that are written: most frames' detail is held back and never written, and making
        # Rerun's archetypes was ~40 % of the recorder's time in the tracking thread
        self._log(E["orb"], _Lazy(_points2d, fs.keypoints, [GREY], 2))
        self._log(E["lsd_merged"], _Lazy(_strips2d, fs.segments, [CYAN], 1.5))
        self._scalars("features", {"points": fs.n_points, "lines": fs.n_lines, "raw_segments": len(fs.raw_segments)})

    def matches(self, m: FeatureMatches) -> None:
        self._scalars("matching", {"points": len(m.points), "lines": len(m.lines)})

    def tracking(self, t: TrackingResult) -> None:
        self._tracking = t
        self._T_world_cam = np.asarray(t.T_world_cam, dtype=float)
        frames, times, poses = self._poses_buf
        frames.append(self._at)
        times.append(self._times.get(self._at, 0.0))
        poses.append(self._T_world_cam)
        self._trail.on_tracking(t.frame_index, self._T_world_cam)
        counts = {"point_matches": t.n_point_matches, "line_matches": t.n_line_matches,
                  "point_inliers": len(t.point_inliers), "line_inliers": len(t.line_inliers), "lost": int(not t.ok)}
        uv = getattr(t, "point_uv", None)  # the tracker's FrontendResult: its 3D-2D matches with their verdicts
        if uv is not None:
            segs = np.asarray(t.line_segments)
            self._log(E["tracked_points"], _Lazy(_points2d, uv, None, 3.5, inliers=t.point_inlier))
            self._log(E["tracked_lines"], _Lazy(_strips2d, segs, None, 2.5, inliers=t.line_inlier))
            counts.update(point_landmarks=len(uv), line_landmarks=len(segs), new_points=t.n_new_points,
                          new_lines=t.n_new_lines)
        source = getattr(t, "source", "camera")  # where the pose came from (plvo.tracking.lidar_check.SOURCES)
        counts.update(pose_by_lidar=int(source == "lidar"),
                      pose_lidar_seeded=int(source == "camera, seeded by the lidar"))
        self._scalars("tracking", counts)
        status = getattr(t, "status", "reinitialised" if not t.ok else "tracked")
        if status == "reinitialised" or not t.ok:
            self._text(t.message or f"frame {t.frame_index}: tracking lost", rr.TextLogLevel.WARN)
            self._event("tracking lost")
        elif source != "camera":
            self._text(f"frame {t.frame_index}: pose by the {source}: {t.message}", rr.TextLogLevel.WARN)
            self._event("camera checked against the lidar")
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
        self._kf_frame = int(kf.frame_index)
        self._kfs_since_summary += 1
        self._kfs_since_graph += 1
        self._write_held(self._policy.keyframe(self._at))
        fs = self._features
        if fs is not None:  # raw LSD output: on keyframes only (~11 kB a frame otherwise)
            self._log(E["lsd_raw"], rr.LineStrips2D(_segments_2d(fs.raw_segments), colors=[RED],
                                                       radii=rr.Radius.ui_points(1)))
        self._log_scan()

    def _log_thin_statics(self, K: np.ndarray, width: int, height: int) -> None:
        """What the thin scan and image share across keyframes, once: the faces' pinholes and how their depth
        images are drawn, the small image's scale up to the camera's pixels (drawn under the full image)."""
        rec, faces = self.rec, self.opt.thin_scan
        w, h = faces.size
        for k in range(faces.n):
            path = f"{E['thin']}/{k}"
            rec.log(path, _transform(np.block([[faces.R_velo_face(k), np.zeros((3, 1))], [np.zeros((1, 3)), 1]])),
                    rr.Pinhole(image_from_camera=faces.K, resolution=[w, h], camera_xyz=rr.ViewCoordinates.RDF,
                               image_plane_distance=0.2, line_width=0.5), static=True)
            # near red to far blue as the scan's depth_colors: the range reversed turns Rerun's turbo round
            rec.log(path, rr.EncodedDepthImage.from_fields(
                media_type="image/png", meter=1.0 / faces.unit, colormap=rr.components.Colormap.Turbo,
                point_fill_ratio=0.12,
                depth_range=[DEPTH_FAR / faces.unit, DEPTH_NEAR / faces.unit]), static=True)
        s = max(1, self.opt.thin_image_scale)
        self._thin_size = (max(1, round(width / s)), max(1, round(height / s)))
        rec.log(E["image_kf"], rr.Transform3D(scale=[width / self._thin_size[0], height / self._thin_size[1], 1.0]),
                rr.EncodedImage.from_fields(draw_order=-20.0, media_type="image/jpeg"), static=True)

    def _log_thin(self, shown: np.ndarray | None) -> None:
        """The keyframe's thin scan and image (every level, every thin_every_keyframes-th keyframe: every one)."""
        frame = self._frame
        n, self._n_kf = self._n_kf, self._n_kf + 1
        if frame is None or n % max(1, self.opt.thin_every_keyframes):
            return
        for k, png in enumerate(self.opt.thin_scan.encode(frame.scan[:, :3])):
            self.rec.log(f"{E['thin']}/{k}", rr.EncodedDepthImage.from_fields(blob=png))  # the rest is static
        if shown is not None and self._thin_size is not None:
            small = cv2.resize(shown, self._thin_size, interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, self.opt.thin_image_quality,
                                                   cv2.IMWRITE_JPEG_OPTIMIZE, 1])  # its own tables: -170 bytes
            if ok:
                self.rec.log(E["image_kf"], rr.EncodedImage.from_fields(blob=buf.tobytes()))

    def _log_scan(self) -> None:
        frame = self._frame
        if frame is None or self._T_world_cam is None:
            return
        scan = frame.scan[thin(len(frame.scan), self.opt.scan_max_points), :3]
        self._log(E["lidar"], _transform(self._T_world_cam @ frame.calib.T_cam_velo))
        self._log_thin(frame.image if frame.color is None else cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR))
        self._log(E["scan"], _Lazy(lambda: rr.Points3D(scan.astype(np.float32), radii=rr.Radius.ui_points(1.5),
                                                       colors=depth_colors(np.linalg.norm(scan, axis=1)))))
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
        self._log(E["lidar2d"], rr.Points2D(np.asarray(uv)[s].astype(np.float32), colors=depth_colors(z[s]),
                                               radii=rr.Radius.ui_points(1.5)))

    def depth(self, d: DepthPriors) -> None:
        self._point_valid = np.asarray(d.point_valid)
        self._scalars("depth", {"point_priors": int(np.sum(d.point_valid)), "line_priors": int(np.sum(d.line_valid))})
        if self._T_world_cam is None:
            return
        T = self._T_world_cam  # the priors are in this keyframe's camera frame; drawn where the camera is
        lines = np.asarray(d.line_endpoints, float)[d.line_valid].reshape(-1, 3)
        self._log(E["depth_lines"], rr.LineStrips3D(transform_points(T, lines).reshape(-1, 2, 3).astype(
            np.float32), colors=[CYAN]))
        fs = self._features
        if fs is not None and len(fs.keypoints) == len(d.point_depth):
            ok = d.point_valid
            pts = transform_points(T, backproject(self._frame.calib.K, np.asarray(fs.keypoints, float)[ok],
                                                  d.point_depth[ok]))
            self._log(E["depth_points"], rr.Points3D(pts.astype(np.float32), colors=[GREEN],
                                                        radii=rr.Radius.ui_points(3)))

    def depth_debug(self, dbg: DepthDebug) -> None:
        """plvo.depth.extract.DepthDebug: projected scan, searched patches, fitted planes (camera frame, pixels)."""
        self._overlay_pending = False
        self._log_overlay(np.asarray(dbg.scan_uv), np.asarray(dbg.scan_depth))
        boxes = np.asarray(dbg.point_boxes, np.float32).reshape(-1, 4)
        valid = self._point_valid if self._point_valid is not None and len(self._point_valid) == len(boxes) \
            else np.zeros(len(boxes), bool)
        self._log(E["patches"], rr.Boxes2D(mins=boxes[:, :2], sizes=boxes[:, 2:] - boxes[:, :2],
                                              colors=inlier_colors(valid)))
        bands = np.asarray(dbg.line_bands, np.float32).reshape(-1, 4, 2)
        self._log(E["line_patches"], rr.LineStrips2D(np.concatenate([bands, bands[:, :1]], axis=1), colors=[CYAN]))
        self._scalars("time/depth", dict(dbg.timings_ms))
        quads = np.asarray(dbg.plane_quads, float).reshape(-1, 4, 3)
        quads = quads[np.all(np.isfinite(quads), axis=(1, 2))]
        if self._T_world_cam is not None and len(quads):
            verts = transform_points(self._T_world_cam, quads.reshape(-1, 3)).astype(np.float32)
            base = 4 * np.arange(len(quads))[:, None]
            tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.uint32)
            self._log(E["planes"], rr.Mesh3D(vertex_positions=verts, triangle_indices=tris, albedo_factor=GREEN))

    def graph(self, g: GraphResult) -> None:
        poses = np.asarray(g.T_world_cam, float)
        before = self._trail.kf_pose
        moves = [np.linalg.norm(T[:3, 3] - before[int(k)][:3, 3]) for k, T in zip(g.keyframe_ids, poses)
                 if int(k) in before]
        if moves and max(moves) > self.opt.detail.large_correction_m:
            self._text(f"frame {self._at}: the back end moved a keyframe by {max(moves):.2f} m",
                       rr.TextLogLevel.WARN)
            self._event("large correction")
        self._trail.on_graph(g.keyframe_ids, poses)  # drawn at the next keyframe (and on close)
        whole = self._policy.everything or self._policy.want(self._at) or \
            self._kfs_since_graph >= self.opt.summary_every_keyframes
        self._log_graph(g, whole)
        self._scalars("backend", {"scale": g.scale, "edges": len(g.edges)})

    def _log_graph(self, g: GraphResult, whole: bool) -> None:
        """The whole graph grows with the run: written whole only now and then (see ENTITIES), else its recent
        edges, so that a long run's recording grows linearly."""
        poses = np.asarray(g.T_world_cam, float)
        self._last_graph = None if whole else (self._at, g)
        if whole and len(g.edges):
            self._kfs_since_graph = 0
        elif len(g.edges):
            ids = np.asarray(g.keyframe_ids)
            recent = ids[np.asarray(g.edges)].min(axis=1) > ids.max() - self.opt.summary_every_keyframes
            kind = np.asarray(g.edge_kind)
            keep = recent & (kind != EdgeKind.COVISIBILITY)
            self.rec.log(E["graph_recent"], rr.LineStrips3D(
                poses[:, :3, 3][np.asarray(g.edges)[keep]].astype(np.float32),
                colors=zeta_colors(np.asarray(g.zeta)[keep], kind[keep]), radii=rr.Radius.ui_points(2.5)))
            return
        if len(g.edges):
            kind = np.asarray(g.edge_kind)

            def strips(keep: np.ndarray) -> rr.LineStrips3D:
                return rr.LineStrips3D(poses[:, :3, 3][np.asarray(g.edges)[keep]].astype(np.float32),
                                       colors=zeta_colors(np.asarray(g.zeta)[keep], kind[keep]),
                                       radii=rr.Radius.ui_points(2.5))

            everything = np.ones(len(kind), bool)
            if self._policy.want(self._at):
                self.rec.log(E["graph"], strips(everything))
            else:  # the odometry edges (at most graph_summary_edges, by stride) with their zeta and every loop;
                # the covisibility edges and the rest with the detail
                summary = np.zeros(len(kind), bool)
                odometry = np.flatnonzero(kind != EdgeKind.COVISIBILITY)
                summary[odometry[thin(len(odometry), self.opt.graph_summary_edges)]] = True
                summary |= kind == EdgeKind.LOOP
                self.rec.log(E["graph"], strips(summary))
                if not summary.all():
                    self._policy.defer(self._at, (E["graph"], _Lazy(strips, everything)))

    def map(self, m: MapResult) -> None:
        pts, lines = np.asarray(m.points, np.float32), np.asarray(m.lines, np.float32)

        def points(p: np.ndarray) -> rr.Points3D:
            return rr.Points3D(p, colors=[(150, 150, 160)], radii=rr.Radius.ui_points(2))

        def strips(ln: np.ndarray) -> rr.LineStrips3D:
            return rr.LineStrips3D(ln, colors=[CYAN])

        if self._policy.want(self._at):
            self.rec.log(E["map_points"], points(pts))
            self.rec.log(E["map_lines"], strips(lines))
        else:  # the map at every keyframe, thinned; the full snapshot, made only if an event wants this frame
            self.rec.log(E["map_points"], points(pts[thin(len(pts), self.opt.map_summary_points)]))
            self.rec.log(E["map_lines"], strips(lines[thin(len(lines), self.opt.map_summary_lines)]))
            self._policy.defer(self._at, (E["map_points"], _Lazy(points, pts)))
            self._policy.defer(self._at, (E["map_lines"], _Lazy(strips, lines)))
        self._scalars("map", {"points": len(m.points), "lines": len(m.lines)})

    def loop(self, lr: LoopResult) -> None:
        verdict = "accepted" if lr.accepted else "rejected"
        self._text(f"loop keyframe {lr.query_keyframe} -> {lr.match_keyframe} {verdict} (score {lr.score:.3f}, "
                   f"{lr.n_inliers} inliers): {lr.reason}",
                   rr.TextLogLevel.INFO if lr.accepted else rr.TextLogLevel.DEBUG)
        if lr.accepted or lr.n_inliers >= self.opt.detail.loop_min_inliers:  # not each bag-of-words near miss
            self._event(f"loop {verdict}")
        kf = self._trail.kf_pose
        if lr.accepted and lr.query_keyframe in kf and lr.match_keyframe in kf:
            self._loops.append(np.array([kf[lr.query_keyframe][:3, 3], kf[lr.match_keyframe][:3, 3]], np.float32))
            self.rec.log(E["loops"], rr.LineStrips3D(self._loops, colors=[MAGENTA], radii=rr.Radius.ui_points(3)))

    def timing(self, t: TimingResult) -> None:
        """The last result of a step: the keyframes and the estimate are logged here, once a step."""
        self._scalars("time", {name: 1e3 * s for name, s in t.seconds.items()})
        self._drain_warnings()
        # A slow frame is one that took long to arrive: the time since the last step ended, not the step's own time,
        # which leaves out what other threads did for it (its features are extracted ahead, in the prefetching one)
        now = time.perf_counter()
        interval = float(t.seconds.get("total", t.total)) if self._last_step_end is None else now - self._last_step_end
        self._last_step_end = now
        if self._policy.timing(self._at, interval):
            self._text(f"frame {self._at}: slow frame ({1e3 * interval:.0f} ms since the last)", rr.TextLogLevel.WARN)
            self._event("slow frame")
        if self._overlay_pending and self._frame is not None:
            self._overlay_pending = False
            self._log_scan_overlay(self._frame)
        self._log_dirty()
        self._clear_stale(self._at)
        self._policy.end_frame(self._at)
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


HASH_HEX = 24  # digest prefix kept a file (96 bits): 2 x 4541 full ones would be 0.6 MB of a 25 MB budget

# result type -> RerunRecorder handler
_HANDLERS: dict[type, Callable[[RerunRecorder, Any], None]] = {
    FeatureSet: RerunRecorder.features,
    FeatureMatches: RerunRecorder.matches,
    DepthPriors: RerunRecorder.depth,
    DepthDebug: RerunRecorder.depth_debug,
    KeyframeResult: RerunRecorder.keyframe,
    TrackingResult: RerunRecorder.tracking,
    GraphResult: RerunRecorder.graph,
    MapResult: RerunRecorder.map,
    LoopResult: RerunRecorder.loop,
    TimingResult: RerunRecorder.timing,
    MetricsResult: RerunRecorder.metrics,
}
