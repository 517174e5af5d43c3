"""Write a KITTI twin: a synthetic sequence driven along a KITTI pose file, in the KITTI odometry layout.

Beside the town's files (see plvo.data.synth.generate) a twin's gt/ holds, per frame NNNNNN:
  gt/movers/NNNNNN.png         uint16 mover id of each cam0 pixel (0: none), at the frame's time
  gt/lidar_movers/NNNNNN.npy   (N,) uint16 mover id of each return of velodyne/NNNNNN.bin (0: the static world)
  gt/shadow_edges/NNNNNN.png   uint8 255 where a cast shadow's edge lies on one smooth surface (see twin.render)
  gt/depth/NNNNNN.npy          cam0 z-depth (m, inf: sky), with write_depth
  gt/boxes.jsonl               one line a frame: every mover within BOX_RANGE_M, its box size and its pose
                               T_world_body at the sweep's start, the frame's time and the sweep's end
                               (t - 0.05, t, t + 0.05 s), its 2D box in cam0 and its pixel and return counts
  gt/scene.json                settings, the followed file and range, lidar model, sun, exposure gains, zones
The poses file equals the followed rows (re-based on frame A when the range starts later, see twin.follow).
A twin is written in a staging folder named by its settings and moved in when complete; a run that is stopped
leaves that folder, and the next run with the same settings renders only the frames it lacks (a long twin takes
an hour or more).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from plvo.data.synth import sensors
from plvo.data.synth.generate import check_sequence_name, check_target, write_resumable
from plvo.data.synth.mesh import EDGE_GEOMETRIC, EDGE_TEXTURE
from plvo.data.synth.textures import build_atlas
from plvo.data.synth.twin.follow import FollowedPath, PoseInterpolator, load_followed
from plvo.data.synth.twin.layout import ZONES, Layout
from plvo.data.synth.twin.lidars import SWEEP_S, lidar_model
from plvo.data.synth.twin.render import TwinRenderer
from plvo.data.synth.twin.scenery import build_world
from plvo.data.synth.twin.traffic import Traffic
from plvo.errors import SynthError

log = logging.getLogger(__name__)

TWIN_VERSION = 1  # bump when a twin's files for the same settings change (invalidates caches)
RENDER_THREADS = 2
BOX_RANGE_M = 100.0
TRAFFIC_EVERY_M = 60.0  # default traffic: one mover per this much path (at least MIN_TRAFFIC)
MIN_TRAFFIC = 4


@dataclass(frozen=True)
class TwinSettings:
    """What determines a twin. follow: KITTI pose file; frames: 'A:B' or None (all); traffic: movers (None: one
    per TRAFFIC_EVERY_M of path, 0: none); lidar: a model of twin.lidars.LIDAR_MODELS."""

    follow: str
    frames: str | None = None
    seed: int = 0
    traffic: int | None = None
    lidar: str = "hdl64"
    write_depth: bool = False

    def check(self) -> None:
        lidar_model(self.lidar)
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2**32:
            raise SynthError(f"seed: expected an integer in [0, 2^32), got {self.seed!r}")
        if self.traffic is not None and (not isinstance(self.traffic, (int, np.integer))
                                         or not 0 <= self.traffic <= 2000):
            raise SynthError(f"--traffic {self.traffic!r}: expected a number of cars from 0 to 2000")


def world_seed(seed: int, sequence: str) -> int:
    return int(np.random.SeedSequence([int(seed), int(sequence)]).generate_state(1)[0])


@dataclass
class Twin:
    """Everything a twin's frames are rendered from (built once, before any frame)."""

    path: FollowedPath
    layout: Layout
    traffic: Traffic
    renderer: TwinRenderer
    counts: dict
    seed: int


def build_twin(settings: TwinSettings, sequence: str) -> Twin:
    settings.check()
    path = load_followed(settings.follow, settings.frames)
    seed = world_seed(settings.seed, sequence)
    layout = Layout(path.context_road, path.file_road, path.file_speed, seed, path.context_real)
    town, n_ground, counts = build_world(layout, seed)
    road = path.road_points()
    length = float(np.linalg.norm(np.diff(road, axis=0), axis=1).sum())
    n_movers = settings.traffic if settings.traffic is not None else max(MIN_TRAFFIC, int(length / TRAFFIC_EVERY_M))
    traffic = Traffic(layout, path.context_road, path.context_first, path.n_frames, int(n_movers), seed)
    renderer = TwinRenderer(town, n_ground, layout, traffic, lidar_model(settings.lidar), build_atlas(seed), seed)
    log.info("twin %s: %d frames, %.0f m, %d triangles, %d movers, %s", sequence, path.n_frames, length,
             len(town.triangles), len(traffic.movers), counts)
    return Twin(path, layout, traffic, renderer, counts, seed)


def _box_2d(ids: np.ndarray, mover_id: int):
    v, u = np.nonzero(ids == mover_id)
    if not len(u):
        return None, 0
    return [int(u.min()), int(v.min()), int(u.max()) + 1, int(v.max()) + 1], int(len(u))


def _boxes(twin: Twin, i: int, ids: np.ndarray, lidar_ids: np.ndarray, T_world_town: np.ndarray) -> dict:
    t = i * sensors.FRAME_DT
    times = np.array([t - 0.5 * SWEEP_S, t, t + 0.5 * SWEEP_S])
    cam = twin.path.T_town_cam[i, :3, 3]
    movers = []
    for m in twin.traffic.movers:
        T, alive = twin.traffic.pose(m, times)
        if not alive[1] or np.linalg.norm(T[1, :3, 3] - cam) > BOX_RANGE_M:
            continue
        box2d, pixels = _box_2d(ids, m.id)
        Tw = T_world_town[None] @ T
        movers.append({
            "id": m.id, "kind": m.kind, "size_lwh_m": list(twin.traffic.size(m)),
            "T_world_body": {k: [round(float(x), 6) for x in Tw[j, :3].ravel()] for j, k in
                             enumerate(("sweep_start", "frame", "sweep_end"))},
            "box2d_uv": box2d, "pixels": pixels, "lidar_returns": int((lidar_ids == m.id).sum()),
        })
    return {"frame": i, "time_s": round(t, 6), "movers": movers}


def camera_heights(twin: Twin) -> np.ndarray:
    """(N,) cam0's height above the twin's ground at each frame: 1.65 m but where KITTI's ground truth puts two
    passes over one place at different heights (the ground follows the lower one, see twin.layout)."""
    cam = twin.path.T_town_cam[:, :3, 3]
    return cam[:, 2] - twin.layout.height(cam[:, :2])


def _write_ground_truth(gt: Path, settings: TwinSettings, twin: Twin, gains: list[float]) -> None:
    T_world_town = np.linalg.inv(twin.path.T_town_world)
    town = twin.renderer.town
    e = town.edges.reshape(-1, 3) @ T_world_town[:3, :3].T + T_world_town[:3, 3]
    np.save(gt / "edges.npy", e.reshape(-1, 2, 3))
    np.save(gt / "edge_kind.npy", town.edge_kind)
    zones = np.bincount(twin.layout.zone[twin.layout.on_path], minlength=len(ZONES)) * 0.5
    scene = {
        "generator": "plvo.data.synth.twin", "twin_version": TWIN_VERSION, "settings": asdict(settings),
        "follow": {"file": twin.path.source, "first_frame": twin.path.first, "n_frames": twin.path.n_frames,
                   "poses": "the followed rows verbatim" if twin.path.first == 0 else
                   "the followed rows re-based on the first frame: inv(T_A) @ T_i"},
        "frames": {"dt_s": sensors.FRAME_DT},
        "camera": {"exposure_gains": [round(g, 6) for g in gains], "auto_exposure": True,
                   "height_above_ground_m": [round(float(h), 4) for h in camera_heights(twin)],
                   "nominal_height_m": sensors.CAMERA_HEIGHT_M},
        "lidar": twin.renderer.lidar.as_json(),
        "world": {"seed": twin.seed, "T_town_world": twin.path.T_town_world.tolist(),
                  "sun_town": twin.renderer.sun.tolist(), "n_triangles": int(len(town.triangles)),
                  "objects": twin.counts, "zones_m": {z.name: float(v) for z, v in zip(ZONES, zones)},
                  "crossings": int(len(twin.layout.crossings))},
        "traffic": twin.traffic.describe(),
        "edges": {"frame": "world (the poses file's)", "kind": {"geometric": EDGE_GEOMETRIC, "texture": EDGE_TEXTURE}},
        "depth": {"written": settings.write_depth, "kind": "cam0 z-depth in metres at the frame's time, inf: sky"},
    }
    (gt / "scene.json").write_text(json.dumps(scene, indent=1, sort_keys=True, default=lambda v: v.item()))


def write_twin(root: Path, sequence: str, settings: TwinSettings,
               progress: Callable[[int, int], None] | None = None, twin: Twin | None = None) -> None:
    """Render every file of one twin into `root` (its stage, not yet visible to readers), skipping the frames a
    stopped run already finished there (marked in root/.frames)."""
    twin = twin or build_twin(settings, sequence)
    seq = root / "sequences" / sequence
    subs = ["image_0", "velodyne", "gt/movers", "gt/lidar_movers", "gt/shadow_edges"]
    if settings.write_depth:
        subs.append("gt/depth")
    for sub in subs:
        (seq / sub).mkdir(parents=True, exist_ok=True)
    (root / "poses").mkdir(parents=True, exist_ok=True)
    n = twin.path.n_frames
    (seq / "calib.txt").write_text(sensors.KITTI_CALIB_00_TEXT)
    (seq / "times.txt").write_text("".join(f"{k * sensors.FRAME_DT:.6e}\n" for k in range(n)))
    (root / "poses" / f"{sequence}.txt").write_text(twin.path.pose_file_text())
    T_town_cam = twin.path.T_town_cam
    poses = PoseInterpolator(T_town_cam)
    T_world_town = np.linalg.inv(twin.path.T_town_world)
    gains = [0.0] * n
    boxes: list[dict | None] = [None] * n
    # A frame is complete when its marker is there (written after its files): a stopped run resumes from those.
    done_dir = root / ".frames"
    done_dir.mkdir(exist_ok=True)
    for marker in done_dir.glob("*.json"):
        i = int(marker.stem)
        if i < n:
            kept = json.loads(marker.read_text())
            gains[i], boxes[i] = kept["gain"], kept["boxes"]
    todo = [i for i in range(n) if boxes[i] is None]
    if len(todo) < n:
        log.info("twin %s: resuming, %d of %d frames already written", sequence, n - len(todo), n)

    def frame(i: int) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([twin.seed, 5, i]))
        t = i * sensors.FRAME_DT
        image, depth, ids, edges, gains[i] = twin.renderer.render_twin(T_town_cam[i], t, rng)
        scan, lidar_ids = twin.renderer.scan_twin(poses, t, sensors.T_CAM_VELO, rng)
        name = f"{i:06d}"
        if not cv2.imwrite(str(seq / "image_0" / f"{name}.png"), image):
            raise SynthError(f"{seq / 'image_0' / name}.png: cannot write the image")
        scan.astype(np.float32).tofile(seq / "velodyne" / f"{name}.bin")
        cv2.imwrite(str(seq / "gt" / "movers" / f"{name}.png"), ids)
        np.save(seq / "gt" / "lidar_movers" / f"{name}.npy", lidar_ids)
        cv2.imwrite(str(seq / "gt" / "shadow_edges" / f"{name}.png"), edges.astype(np.uint8) * 255)
        if settings.write_depth:
            np.save(seq / "gt" / "depth" / f"{name}.npy", depth)
        boxes[i] = _boxes(twin, i, ids, lidar_ids, T_world_town)
        marker = done_dir / f"{name}.json"
        marker.with_suffix(".part").write_text(json.dumps({"gain": gains[i], "boxes": boxes[i]}))
        marker.with_suffix(".part").replace(marker)

    with ThreadPoolExecutor(max_workers=RENDER_THREADS) as pool:
        pending = []
        done = n - len(todo)
        if done and progress is not None:
            progress(done, n)
        for i in todo:
            pending.append(pool.submit(frame, i))
            if len(pending) > RENDER_THREADS:
                pending.pop(0).result()
                done += 1
                if progress is not None:
                    progress(done, n)
        for job in pending:
            job.result()
            done += 1
            if progress is not None:
                progress(done, n)
    shutil.rmtree(done_dir)
    (seq / "gt" / "boxes.jsonl").write_text("".join(json.dumps(b) + "\n" for b in boxes))
    _write_ground_truth(seq / "gt", settings, twin, gains)


def check_twin_request(out_root: Path, sequence: str, settings: TwinSettings, overwrite: bool = False) -> None:
    """Raise SynthError (naming the file, range or setting) if the twin cannot or must not be written."""
    check_sequence_name(sequence)
    settings.check()
    load_followed(settings.follow, settings.frames)
    check_target(out_root, sequence, overwrite, how="--overwrite")


def generate_twin(out_root, sequence: str, settings: TwinSettings,
                  progress: Callable[[int, int], None] | None = None, overwrite: bool = False) -> Path:
    """Write twin NN under out_root (KITTI odometry layout), staged beside it and renamed in when complete; a stage
    of the same settings left by a stopped run is carried on."""
    out_root = Path(out_root)
    check_twin_request(out_root, sequence, settings, overwrite)
    key = hashlib.sha1(json.dumps([TWIN_VERSION, sequence, asdict(settings)], sort_keys=True).encode()).hexdigest()
    write_resumable(out_root, sequence, ".twin-", key[:12],
                    lambda stage: write_twin(stage, sequence, settings, progress))
    return out_root
