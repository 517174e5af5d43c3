"""A fake run for the app tests: frames, calibration and one result of every kind, without any dataset."""

from __future__ import annotations

import dataclasses

import numpy as np

from plvo.depth.extract import DepthDebug
from plvo.geometry.se3 import exp
from plvo.recording import RunInfo
from plvo.results import (
    EdgeKind,
    GraphResult,
    KeyframeReason,
    KeyframeResult,
    KeyframeWhy,
    LoopResult,
    MapResult,
    MetricsResult,
    TimingResult,
)
from plvo.tracking.frontend import FrontendResult
from plvo.types import Calibration, DepthPriors, FeatureSet, Frame

K = np.array([[700.0, 0, 600], [0, 700, 180], [0, 0, 1]])
T_CAM_VELO = np.array([[0, -1, 0, 0], [0, 0, -1, -0.08], [1, 0, 0, -0.27], [0, 0, 0, 1]], float)
CALIB = Calibration(K=K, T_cam_velo=T_CAM_VELO, width=1200, height=360)
LOST_FRAME = 4  # tracking is lost and re-initialised here (a keyframe)



def _why(lost: bool) -> KeyframeWhy:
    return KeyframeWhy(KeyframeReason.LOST) if lost else KeyframeWhy(KeyframeReason.INTERVAL, "3 frames")

def pose(i: int) -> np.ndarray:
    """A curving drive: 1 m forward a frame and a yaw that grows, so rotations are far from symmetric."""
    return exp(np.array([0.2 * i, 0.0, 1.0 * i, 0.1, 0.03 * i, 0.05]))


def keyframe_frames(n: int, every: int = 3) -> list[int]:
    return sorted({i for i in range(n) if i % every == 0} | ({LOST_FRAME} if n > LOST_FRAME else set()))


def frame(i: int, rng: np.random.Generator) -> Frame:
    image = (rng.random((360, 1200)) * 60 + 100).astype(np.uint8)
    image[100:260, 200 + 20 * i: 400 + 20 * i] = 240
    scan = np.concatenate([rng.uniform(-30, 30, (5000, 3)) * [1, 1, 0.05], rng.random((5000, 1))], 1)
    return Frame(i, 0.1 * i, image, scan.astype(np.float32), CALIB, pose(i))


def features(rng: np.random.Generator, n: int = 50) -> FeatureSet:
    kp = rng.uniform([0, 0], [1200, 360], (n, 2))
    seg = np.concatenate([kp[:10], kp[:10] + 60], 1)
    raw = np.concatenate([seg, seg + 1])
    return FeatureSet(kp, np.zeros(n, int), np.zeros(n), np.ones(n), np.zeros((n, 32), np.uint8), seg,
                      np.zeros((10, 32), np.uint8), raw, tuple(np.array([j, j + 10]) for j in range(10)), (1200, 360))


def tracking(i: int, fs: FeatureSet, is_kf: bool) -> FrontendResult:
    """20 landmark matches of which the even ones are inliers, 4 line matches with 3 inliers; lost at LOST_FRAME."""
    lost, first = i == LOST_FRAME, i == 0
    p_in = np.arange(20) % 2 == 0
    l_in = np.array([True, True, True, False])
    if lost or first:
        p_in, l_in = np.zeros(0, bool), np.zeros(0, bool)
    status = "initialised" if first else "reinitialised" if lost else "tracked"
    msg = f"frame {i}: tracking lost (too few matches); re-initialised from the current lidar depth" if lost else "ok"
    return FrontendResult(i, pose(i), 40, 8, np.flatnonzero(p_in), np.flatnonzero(l_in), is_kf, not lost, msg,
                          status=status, keyframe_reason=_why(lost) if is_kf else None,
                          point_uv=fs.keypoints[:len(p_in)], point_landmark=np.arange(len(p_in)), point_inlier=p_in,
                          line_segments=fs.segments[:len(l_in)], line_landmark=np.arange(len(l_in)),
                          line_inlier=l_in, n_new_points=30 if is_kf else 0, n_new_lines=5 if is_kf else 0)


def depth(n_points: int = 50) -> DepthPriors:
    d = np.full(n_points, 10.0)
    reason = np.zeros(n_points, int)
    reason[::2] = 1
    lines = np.tile(np.array([[0, 0, 10], [1, 0, 10]], float), (10, 1, 1))
    return DepthPriors(d, reason, np.zeros(n_points), np.full(n_points, 5), np.full((n_points, 4), np.nan),
                       lines, np.zeros(10, int), np.zeros(10), np.full(10, 8))


def depth_debug(rng: np.random.Generator, n_points: int = 50) -> DepthDebug:
    uv = rng.uniform([0, 0], [1200, 360], (800, 2))
    boxes = np.concatenate([uv[:n_points] - 5, uv[:n_points] + 5], 1)
    quads = np.tile(np.array([[-1, -1, 10], [1, -1, 10], [1, 1, 10], [-1, 1, 10]], float), (n_points, 1, 1))
    quads[1::2] = np.nan
    bands = np.tile(np.array([[0, 0], [60, 0], [60, 6], [0, 6]], float), (10, 1, 1))
    return DepthDebug(uv, rng.uniform(3, 60, 800), boxes, bands, quads, np.zeros(n_points), np.zeros(10),
                      np.zeros(10), {"projection": 2.0, "points": 3.0})


def run_info(n: int) -> RunInfo:
    gt = np.array([pose(i) for i in range(n)])
    return RunInfo("fake_run", "fake", CALIB, tuple(range(n)), gt, {"orb": {"n_features": 50}}, "0.1.0", "abc123",
                   "plvo-viz --seq fake", {"config_toml": "[orb]\nn_features = 50\n"})


def restart_info(n: int, at_frame: int) -> RunInfo:
    """What System.restart tells the recorders: the run's info with why it starts again."""
    info = run_info(n)
    return dataclasses.replace(info, extra={**info.extra, "restart": {
        "at_frame": at_frame, "frames_before": at_frame + 1, "reason": "camera-lidar time offset",
        "time_offset_s": 0.098, "sigma_s": 0.0013}})


def drive(recorder, n: int = 9, every: int = 3, backend_lag: int = 1, start: bool = True) -> None:
    """Feed `recorder` n frames as plvo.runtime.system.System does: keyframes every `every` frames (and at LOST_FRAME),
    the back end's results `backend_lag` frames late (at the keyframe's frame index), a loop at the end.
    start: begin with on_run_start (not after an on_restart, which stands for it)."""
    rng = np.random.default_rng(0)
    if start:
        recorder.on_run_start(run_info(n))
    kfs = keyframe_frames(n, every)
    pending: list[tuple[int, object]] = []
    for i in range(n):
        recorder.on_frame(frame(i, rng))
        fs = features(rng)
        recorder.on_stage(i, fs)
        is_kf = i in kfs
        recorder.on_stage(i, tracking(i, fs, is_kf))
        if is_kf:
            k = kfs.index(i)
            recorder.on_stage(i, KeyframeResult(i, k, pose(i), _why(i == LOST_FRAME)))
            recorder.on_stage(i, depth())
            recorder.on_stage(i, depth_debug(rng))
            poses = np.array([pose(f) for f in kfs[:k + 1]])
            edges = np.array([[j, j + 1] for j in range(k)], int).reshape(-1, 2)
            pts = rng.uniform(-20, 20, (200 * (k + 1), 3))
            pending += [(i, GraphResult(i, np.arange(k + 1), poses, edges, np.full(len(edges), EdgeKind.ODOMETRY),
                                        np.linspace(0, 0.2, len(edges)), 1.0)),
                        (i, MapResult(i, pts, pts[:30].reshape(-1, 2, 3))),
                        (i, MetricsResult(i, {"scale_factor": 1.0, "backend_bundle_adjustment_ms": 5.0,
                                              "loop_candidates": 0.0}))]
        due = [(f, r) for f, r in pending if f <= i - backend_lag]
        pending = [(f, r) for f, r in pending if f > i - backend_lag]
        for f, r in due:
            recorder.on_stage(f, r)
        recorder.on_stage(i, TimingResult(i, {"features": 0.05, "total": 0.08}))
    last, k = n - 1, len(kfs) - 1
    for f, r in pending:  # System.finish(): the workers' last results
        recorder.on_stage(f, r)
    recorder.on_stage(kfs[-1], LoopResult(kfs[-1], k, 0, True, 0.5, 40, np.eye(4), "verified"))
    recorder.on_stage(kfs[-1], GraphResult(kfs[-1], np.arange(k + 1), np.array([pose(f) for f in kfs]),
                                           np.array([[k, 0]]), np.array([EdgeKind.LOOP]), np.array([np.nan])))
    assert last >= kfs[-1]


def long_pose(i: int) -> np.ndarray:
    return exp(np.array([0.0, 0.0, 1.0 * i, 0.0, 0.002 * i, 0.0]))


def write_long_recording(path, n: int = 4541, every: int = 3) -> None:
    """A whole-sequence recording with the entities and cadence plvo-viz writes (a pose and a small image every
    frame, a scan, map and graph every `every` frames, the estimate every 20 keyframes), made in seconds by
    logging directly rather than by running anything."""
    import cv2
    import rerun as rr

    from plvo_app.rrd_blueprint import blueprint

    rng = np.random.default_rng(1)
    rec = rr.RecordingStream("plvo", recording_id="long")
    rec.save(path, default_blueprint=blueprint())
    rec.send_property("plvo", rr.AnyValues(sequence="long"))
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    rec.log("world/camera/image", rr.Pinhole(image_from_camera=K, resolution=[1200, 360]), static=True)
    poses = np.array([long_pose(i) for i in range(n)])
    rec.log("world/trajectory/gt", rr.LineStrips3D([poses[:, :3, 3].astype(np.float32)]), static=True)
    frames = list(range(n))
    rec.send_columns("world/camera", indexes=[rr.TimeColumn("frame", sequence=frames)],
                     columns=rr.Transform3D.columns(translation=poses[:, :3, 3], mat3x3=poses[:, :3, :3]))
    base = (rng.random((90, 300)) * 255).astype(np.uint8)
    jpegs = []
    for i in range(n):
        img = base.copy()
        cv2.putText(img, str(i), (10, 60), cv2.FONT_HERSHEY_SIMPLEX, 2, 255, 3)
        jpegs.append(cv2.imencode(".jpg", img)[1].tobytes())
    rec.send_columns("world/camera/image", indexes=[rr.TimeColumn("frame", sequence=frames)],
                     columns=rr.EncodedImage.columns(blob=jpegs, media_type=["image/jpeg"] * n))
    for i in range(0, n, every):
        rec.set_time("frame", sequence=i)
        if True:
            k = i // every
            rec.log("world/lidar", rr.Transform3D(translation=poses[i][:3, 3], mat3x3=poses[i][:3, :3]))
            rec.log("world/lidar/scan", rr.Points3D(rng.uniform(-30, 30, (1000, 3)).astype(np.float32)))
            rec.log("world/map/points", rr.Points3D((poses[i][:3, 3] + rng.uniform(-20, 20, (800, 3)))
                                                    .astype(np.float32)))
            kf = poses[max(0, i - 10 * every):i + 1:every, :3, 3].astype(np.float32)
            rec.log("world/graph", rr.LineStrips3D(np.stack([kf[:-1], kf[1:]], 1) if len(kf) > 1 else []))
            rec.log("log", rr.TextLog(f"frame {i}: keyframe {k} (interval)"))
            if k % 20 == 0:
                rec.log("world/trajectory/est", rr.LineStrips3D([poses[:i + 1, :3, 3].astype(np.float32)]))
                rec.log("world/keyframes", rr.Points3D(poses[:i + 1:every, :3, 3].astype(np.float32)))
    rec.flush()
    rec.disconnect()
