"""Write a KITTI twin: a synthetic sequence driven along a KITTI pose file, in the KITTI odometry layout.

Beside the town's files (see plvo_synth.generate) a twin's gt/ holds, per frame NNNNNN:
  gt/movers/NNNNNN.png         uint16 mover id of each cam0 pixel (0: none), at the frame's time
  gt/lidar_movers/NNNNNN.npy   (N,) uint16 mover id of each return of velodyne/NNNNNN.bin (0: the static world)
  gt/shadow_edges/NNNNNN.png   uint8 255 where a cast shadow's edge lies on one smooth surface (see twin.render)
  gt/depth/NNNNNN.npy          cam0 z-depth (m, inf: sky), with write_depth
  gt/boxes.jsonl               one line a frame: every mover within BOX_RANGE_M, its box size and its pose
                               T_world_body at the sweep's start, the frame's time and the sweep's end
                               (t - 0.05, t, t + 0.05 s), its 2D box in cam0 and its pixel and return counts
  gt/scene.json                settings, the followed file and range, lidar model, sun, exposure gains, zones; for
                               a realistic twin (twin.realism) also its calibration, the extrinsic error and time
                               offset drawn, the lidar's per-beam biases and whether its scans are compensated
The poses file equals the followed rows (re-based on frame A when the range starts later, see twin.follow); the
sensors realism degrades never touch it. A twin of KITTI odometry NN has sequence NN's calibration and image size
(IDEAL: 00-02's for all); its calib.txt states the extrinsic with the rig's seeded error, the true one renders.
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
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from plvo.errors import SynthError
from plvo_synth import sensors
from plvo_synth.generate import check_sequence_name, check_target, write_resumable
from plvo_synth.kitti_calib import CALIB_00_02, KittiCalibration, odometry_calibration
from plvo_synth.mesh import EDGE_GEOMETRIC, EDGE_TEXTURE
from plvo_synth.textures import build_atlas
from plvo_synth.twin.follow import FollowedPath, PoseInterpolator, load_followed
from plvo_synth.twin.layout import ZONES, Layout
from plvo_synth.twin.lidars import SWEEP_S, LidarEffects, lidar_model
from plvo_synth.twin.realism import REALISTIC, Realism
from plvo_synth.twin.render import TwinRenderer
from plvo_synth.twin.scenery import build_world
from plvo_synth.twin.traffic import Traffic

log = logging.getLogger(__name__)

TWIN_VERSION = 1  # bump when a twin's files for the same settings change (invalidates caches)
# a twin's scene.json names its maker so: the module's name when the format was made, kept so that twins already
# generated are known as twins (plvo_synth.twin.batch) wherever the generator lives
TWIN_GENERATOR = "plvo.data.synth.twin"
RENDER_THREADS = 2
BOX_RANGE_M = 100.0
TRAFFIC_EVERY_M = 60.0  # default traffic: one mover per this much path (at least MIN_TRAFFIC)
MIN_TRAFFIC = 4


@dataclass(frozen=True)
class TwinSettings:
    """What determines a twin. follow: KITTI pose file (or a raw drive's folder, see twin.raw_drive); frames: 'A:B'
    or None (all); traffic: movers (None: one per TRAFFIC_EVERY_M of path, 0: none); lidar: a model of
    twin.lidars.LIDAR_MODELS; realism: the sensors' imperfections (twin.realism)."""

    follow: str
    frames: str | None = None
    seed: int = 0
    traffic: int | None = None
    lidar: str = "hdl64"
    write_depth: bool = False
    realism: Realism = REALISTIC

    def check(self) -> None:
        lidar_model(self.lidar)
        if not isinstance(self.realism, Realism):
            raise SynthError(f"realism: expected a twin.realism.Realism, got {self.realism!r}")
        self.realism.check()
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2**32:
            raise SynthError(f"seed: expected an integer in [0, 2^32), got {self.seed!r}")
        if self.traffic is not None and (not isinstance(self.traffic, (int, np.integer))
                                         or not 0 <= self.traffic <= 2000):
            raise SynthError(f"--traffic {self.traffic!r}: expected a number of cars from 0 to 2000")

    def as_json(self) -> dict:
        """The settings as scene.json records them (and as their hash keys a stage): an ideal twin's without the
        realism, as twins were described before it existed, so those stay current for --ideal."""
        out = asdict(self)
        if self.realism.is_ideal:
            del out["realism"]
        return out


def world_seed(seed: int, sequence: str) -> int:
    return int(np.random.SeedSequence([int(seed), int(sequence)]).generate_state(1)[0])


def rig_seed(seed: int, calibration: str) -> int:
    """Seed of the rig's errors: one per calibration (a recording day's), as a real rig's calibration is."""
    key = [int(seed), *calibration.encode()]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


@dataclass
class Twin:
    """Everything a twin's frames are rendered from (built once, before any frame). T_cam_velo: the true extrinsic
    (the sensors' rendering), T_cam_velo_stated: the one the twin's calibration files state; time_offset_s: the
    lidar's reference instant after the camera's (in the twin's clock, which runs FRAME_DT a frame); compensated:
    scans motion-compensated; sweep_s: a sweep's (and a frame's) duration in real seconds."""

    path: FollowedPath
    layout: Layout
    traffic: Traffic
    renderer: TwinRenderer
    counts: dict
    seed: int
    calib: KittiCalibration = CALIB_00_02
    realism: Realism = REALISTIC
    T_cam_velo: np.ndarray = field(default_factory=lambda: sensors.T_CAM_VELO.copy())
    T_cam_velo_stated: np.ndarray = field(default_factory=lambda: sensors.T_CAM_VELO.copy())
    time_offset_s: float = 0.0
    compensated: bool = False
    sweep_s: float = SWEEP_S

    @property
    def extrinsic_error(self) -> np.ndarray:
        """(4,4) E with T_cam_velo_stated = E @ T_cam_velo."""
        return self.T_cam_velo_stated @ np.linalg.inv(self.T_cam_velo)

    def realism_json(self) -> dict:
        """What scene.json records of a realistic twin's sensors: its calibration, the extrinsic error and time
        offset drawn, the lidar's beam biases and what a scan holds."""
        E = self.extrinsic_error
        rotvec = Rotation.from_matrix(E[:3, :3]).as_rotvec()
        fx = self.renderer.lidar_effects
        return {
            "calibration": {"name": self.calib.name, "image_size": [self.calib.width, self.calib.height],
                            "T_cam_velo_true": np.round(self.T_cam_velo, 12).tolist(),
                            "T_cam_velo_stated": np.round(self.T_cam_velo_stated, 12).tolist()},
            "rig": {"extrinsic_error": {"rotation_vector_deg": np.round(np.degrees(rotvec), 6).tolist(),
                                        "rotation_deg": round(float(np.degrees(np.linalg.norm(rotvec))), 6),
                                        "translation_m": np.round(E[:3, 3], 6).tolist(),
                                        "T_stated_true_cam": np.round(E, 12).tolist()},
                    "time_offset_s": self.realism.rig.time_offset_s,
                    "time_offset": "the lidar faces forward this long after the camera exposes; no file states it"},
            "lidar_effects": fx.as_json() if fx is not None else None,
        }


def build_twin(settings: TwinSettings, sequence: str, path: FollowedPath | None = None,
               calib: KittiCalibration | None = None, seed_key: str | None = None, raw_drive: bool = False,
               sweep_s: float = SWEEP_S) -> Twin:
    """The twin of `sequence` along settings.follow, or along `path` (a raw drive's, with its day's `calib`,
    world seed from seed_key and a sweep of sweep_s real seconds)."""
    settings.check()
    path = path if path is not None else load_followed(settings.follow, settings.frames)
    realism = settings.realism
    if calib is None:
        calib = odometry_calibration(sequence) if realism.rig.calibration == "own" else CALIB_00_02
    seed = world_seed(settings.seed, seed_key if seed_key is not None else sequence)
    layout = Layout(path.context_road, path.file_road, path.file_speed, seed, path.context_real)
    town, n_ground, counts = build_world(layout, seed, realism.scenery)
    road = path.road_points()
    length = float(np.linalg.norm(np.diff(road, axis=0), axis=1).sum())
    n_movers = settings.traffic if settings.traffic is not None else max(MIN_TRAFFIC, int(length / TRAFFIC_EVERY_M))
    traffic = Traffic(layout, path.context_road, path.context_first, path.n_frames, int(n_movers), seed)
    model = lidar_model(settings.lidar)
    effects = None if realism.lidar.is_ideal else LidarEffects(model, realism.lidar, seed)
    renderer = TwinRenderer(town, n_ground, layout, traffic, model, build_atlas(seed), seed, calib, effects,
                             ground=realism.scenery.ground)
    T_cam_velo = calib.T_cam_velo
    E = realism.rig.extrinsic_error(rig_seed(settings.seed, calib.name))
    log.info("twin %s: %d frames, %.0f m, %d triangles, %d movers, %s", sequence, path.n_frames, length,
             len(town.triangles), len(traffic.movers), counts)
    # the twin's clock runs FRAME_DT a frame: a real offset is scaled as the sweep is
    offset = realism.rig.time_offset_s * SWEEP_S / sweep_s
    return Twin(path, layout, traffic, renderer, counts, seed, calib, realism, T_cam_velo, E @ T_cam_velo, offset,
                realism.compensated(raw_drive), sweep_s)


def _box_2d(ids: np.ndarray, mover_id: int) -> tuple[list[int] | None, int]:
    v, u = np.nonzero(ids == mover_id)
    if not len(u):
        return None, 0
    return [int(u.min()), int(v.min()), int(u.max()) + 1, int(v.max()) + 1], int(len(u))


def _boxes(twin: Twin, i: int, ids: np.ndarray, lidar_ids: np.ndarray, T_world_town: np.ndarray) -> dict:
    t = i * sensors.FRAME_DT
    ref = t + twin.time_offset_s
    times = np.array([ref - 0.5 * SWEEP_S, t, ref + 0.5 * SWEEP_S])
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


def lidar_json(twin: Twin) -> dict:
    """scene.json's lidar: the model, and for a realistic twin what its scans hold. `sweep_s` is the time a scan's
    returns span as delivered (0 for a compensated scan: every return at the reference instant, so that readers
    do not deskew it again), rotation_s the sweep's duration, elevation_offset_deg the vertical-angle error a reader
    takes out as for KITTI's own scans."""
    out = twin.renderer.lidar.as_json()
    if twin.realism.is_ideal:
        return out
    fx = twin.renderer.lidar_effects
    out.update({"rotation_s": twin.sweep_s, "motion_compensated": twin.compensated,
                "elevation_offset_deg": fx.realism.elevation_offset_deg if fx is not None else 0.0,
                "range_noise_m": fx.range_noise_m if fx is not None else out["range_noise_m"]})
    if twin.compensated:
        out.update({"sweep_s": 0.0, "timing": "motion-compensated: every return in the sensor frame at the sweep's "
                                              "reference instant (the lidar facing forward)"})
    else:
        out.update({"sweep_s": twin.sweep_s,
                    "timing": "t = reference instant + rotation_s * (-azimuth / 2 pi), azimuth = atan2(y, x) in "
                              "(-pi, pi]; each return in the sensor frame at its own time"})
    return out


def write_ground_truth(gt: Path, settings: TwinSettings, twin: Twin, gains: list[float],
                        extra: dict | None = None) -> None:
    T_world_town = np.linalg.inv(twin.path.T_town_world)
    town = twin.renderer.town
    e = town.edges.reshape(-1, 3) @ T_world_town[:3, :3].T + T_world_town[:3, 3]
    np.save(gt / "edges.npy", e.reshape(-1, 2, 3))
    np.save(gt / "edge_kind.npy", town.edge_kind)
    zones = np.bincount(twin.layout.zone[twin.layout.on_path], minlength=len(ZONES)) * 0.5
    scene = {
        "generator": TWIN_GENERATOR, "twin_version": TWIN_VERSION, "settings": settings.as_json(),
        "follow": {"file": twin.path.source, "first_frame": twin.path.first, "n_frames": twin.path.n_frames,
                   "poses": "the followed rows verbatim" if twin.path.first == 0 else
                   "the followed rows re-based on the first frame: inv(T_A) @ T_i"},
        "frames": {"dt_s": sensors.FRAME_DT},
        "camera": {"exposure_gains": [round(g, 6) for g in gains], "auto_exposure": True,
                   "height_above_ground_m": [round(float(h), 4) for h in camera_heights(twin)],
                   "nominal_height_m": sensors.CAMERA_HEIGHT_M},
        "lidar": lidar_json(twin),
        "world": {"seed": twin.seed, "T_town_world": twin.path.T_town_world.tolist(),
                  "sun_town": twin.renderer.sun.tolist(), "n_triangles": int(len(town.triangles)),
                  "objects": twin.counts, "zones_m": {z.name: float(v) for z, v in zip(ZONES, zones)},
                  "crossings": int(len(twin.layout.crossings))},
        "traffic": twin.traffic.describe(),
        "edges": {"frame": "world (the poses file's)", "kind": {"geometric": EDGE_GEOMETRIC, "texture": EDGE_TEXTURE}},
        "depth": {"written": settings.write_depth, "kind": "cam0 z-depth in metres at the frame's time, inf: sky"},
    }
    if not twin.realism.is_ideal:
        scene["realism"] = twin.realism_json()
    scene.update(extra or {})
    (gt / "scene.json").write_text(json.dumps(scene, indent=1, sort_keys=True, default=lambda v: v.item()))


@dataclass(frozen=True)
class FrameFiles:
    """Where a twin's per-frame files go: images, scans and gt/ (the odometry layout's or a raw drive's), each
    named by its frame number in `digits` digits."""

    images: Path
    scans: Path
    gt: Path
    digits: int = 6

    def name(self, i: int) -> str:
        return f"{i:0{self.digits}d}"

    def make(self, write_depth: bool) -> None:
        subs = [self.images, self.scans] + [self.gt / s for s in ("movers", "lidar_movers", "shadow_edges")]
        for sub in subs + ([self.gt / "depth"] if write_depth else []):
            sub.mkdir(parents=True, exist_ok=True)


def write_twin(root: Path, sequence: str, settings: TwinSettings,
               progress: Callable[[int, int], None] | None = None, twin: Twin | None = None) -> None:
    """Render every file of one twin into `root` (its stage, not yet visible to readers), skipping the frames a
    stopped run already finished there (marked in root/.frames)."""
    twin = twin or build_twin(settings, sequence)
    seq = root / "sequences" / sequence
    files = FrameFiles(seq / "image_0", seq / "velodyne", seq / "gt")
    files.make(settings.write_depth)
    (root / "poses").mkdir(parents=True, exist_ok=True)
    n = twin.path.n_frames
    (seq / "calib.txt").write_text(stated_calib_text(twin))
    (seq / "times.txt").write_text("".join(f"{k * sensors.FRAME_DT:.6e}\n" for k in range(n)))
    (root / "poses" / f"{sequence}.txt").write_text(twin.path.pose_file_text())
    gains = render_frames(root / ".frames", twin, settings, files, sequence, progress)
    write_ground_truth(files.gt, settings, twin, gains)


def render_frames(done_dir: Path, twin: Twin, settings: TwinSettings, files: FrameFiles, label: str,
                  progress: Callable[[int, int], None] | None = None) -> list[float]:
    """Render and write every frame's files and gt/boxes.jsonl -> each frame's exposure gain. A frame is complete
    when its marker in done_dir is there (written after its files): a stopped run resumes from those."""
    n = twin.path.n_frames
    T_town_cam = twin.path.T_town_cam
    poses = PoseInterpolator(T_town_cam)
    T_world_town = np.linalg.inv(twin.path.T_town_world)
    gains = [0.0] * n
    boxes: list[dict | None] = [None] * n
    done_dir.mkdir(exist_ok=True)
    for marker in done_dir.glob("*.json"):
        i = int(marker.stem)
        if i < n:
            kept = json.loads(marker.read_text())
            gains[i], boxes[i] = kept["gain"], kept["boxes"]
    todo = [i for i in range(n) if boxes[i] is None]
    if len(todo) < n:
        log.info("twin %s: resuming, %d of %d frames already written", label, n - len(todo), n)

    def frame(i: int) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([twin.seed, 5, i]))
        effects_rng = np.random.default_rng(np.random.SeedSequence([twin.seed, 7, i]))
        t = i * sensors.FRAME_DT
        image, depth, ids, edges, gains[i] = twin.renderer.render_twin(T_town_cam[i], t, rng, twin.realism.camera,
                                                                       poses, twin.seed)
        scan, lidar_ids = twin.renderer.scan_twin(poses, t + twin.time_offset_s, twin.T_cam_velo, rng, effects_rng,
                                                  twin.compensated)
        name = files.name(i)
        if not cv2.imwrite(str(files.images / f"{name}.png"), image):
            raise SynthError(f"{files.images / name}.png: cannot write the image")
        scan.astype(np.float32).tofile(files.scans / f"{name}.bin")
        cv2.imwrite(str(files.gt / "movers" / f"{name}.png"), ids)
        np.save(files.gt / "lidar_movers" / f"{name}.npy", lidar_ids)
        cv2.imwrite(str(files.gt / "shadow_edges" / f"{name}.png"), edges.astype(np.uint8) * 255)
        if settings.write_depth:
            np.save(files.gt / "depth" / f"{name}.npy", depth)
        boxes[i] = _boxes(twin, i, ids, lidar_ids, T_world_town)
        marker = done_dir / f"{i:06d}.json"
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
    (files.gt / "boxes.jsonl").write_text("".join(json.dumps(b) + "\n" for b in boxes))
    return gains


def stated_calib_text(twin: Twin) -> str:
    """calib.txt as the twin states it: its calibration, Tr carrying the rig's extrinsic error."""
    if np.array_equal(twin.T_cam_velo_stated, twin.T_cam_velo):
        return twin.calib.odometry_text
    return twin.calib.odometry_text_with(twin.T_cam_velo_stated)


def check_twin_request(out_root: Path, sequence: str, settings: TwinSettings, overwrite: bool = False) -> None:
    """Raise SynthError (naming the file, range or setting) if the twin cannot or must not be written."""
    check_sequence_name(sequence)
    settings.check()
    load_followed(settings.follow, settings.frames)
    check_target(out_root, sequence, overwrite, how="--overwrite")


def settings_key(sequence: str, settings: TwinSettings) -> str:
    """Hash of what determines a twin's files (names its stage, so a stage of other settings is not resumed)."""
    text = json.dumps([TWIN_VERSION, sequence, settings.as_json()], sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()


def generate_twin(out_root: str | Path, sequence: str, settings: TwinSettings,
                  progress: Callable[[int, int], None] | None = None, overwrite: bool = False) -> Path:
    """Write twin NN under out_root (KITTI odometry layout), staged beside it and renamed in when complete; a stage
    of the same settings left by a stopped run is carried on."""
    out_root = Path(out_root)
    check_twin_request(out_root, sequence, settings, overwrite)
    key = settings_key(sequence, settings)
    write_resumable(out_root, sequence, ".twin-", key[:12],
                    lambda stage: write_twin(stage, sequence, settings, progress))
    return out_root
