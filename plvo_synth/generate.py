"""Write synthetic town sequences in the KITTI odometry layout, with ground truth, atomically and deterministically.

Layout under `out_root` (what pykitti.odometry and plvo.data.kitti read):
  sequences/NN/image_0/NNNNNN.png   8-bit grey, 1241x376, KITTI seq 00's cam0
  sequences/NN/velodyne/NNNNNN.bin  float32 x, y, z, reflectance in the Velodyne frame
  sequences/NN/calib.txt            P0..P3 and Tr, KITTI's seq 00 values;  sequences/NN/times.txt
  poses/NN.txt                      T_world_cam0 (3x4 row-major), world = cam0 of frame 0
  sequences/NN/gt/edges.npy         (E,2,3) straight 3D edges of the town in the world frame; edge_kind.npy (E,)
  sequences/NN/gt/depth/NNNNNN.npy  (H,W) float32 z-depth of cam0 (inf: sky), only with write_depth
  sequences/NN/gt/scene.json        settings, seed, sun, exposure gains, route and still frames
Everything is staged in a hidden directory beside the target and renamed into place when complete.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from plvo.errors import SynthError
from plvo_synth import path as paths
from plvo_synth import sensors
from plvo_synth.mesh import EDGE_GEOMETRIC, EDGE_TEXTURE, Town
from plvo_synth.render import Renderer, sun_direction
from plvo_synth.textures import build_atlas
from plvo_synth.town import build_town

log = logging.getLogger(__name__)

GENERATOR_VERSION = 1  # bump when the output for a seed changes (invalidates caches)
GENERATOR = "plvo.data.synth"  # scene.json's maker: the format's name (the module's when it was made), kept
MAX_ROUTE_M = 20_000.0
MAX_FRAMES = 50_000
EXPOSURE_PERIOD_FRAMES = 40
RENDER_THREADS = 2
ROUTE_LOOKAHEAD_M = 100.0  # the town is built this far past the last frame, for what the camera sees ahead


@dataclass(frozen=True)
class SynthSettings:
    """What determines a sequence's content. Validated by `check()`; raises SynthError naming the setting."""

    n_frames: int = 300
    seed: int = 0
    speed_mps: float = 10.0
    loop: bool = False
    stops: bool = False
    exposure_change: float = 0.0  # amplitude of the relative gain swing between frames (0: constant exposure)
    write_depth: bool = False

    def check(self) -> None:
        if isinstance(self.n_frames, bool) or not isinstance(self.n_frames, (int, np.integer)):
            raise SynthError(f"n_frames: expected an integer, got {self.n_frames!r}")
        if not 2 <= self.n_frames <= MAX_FRAMES:
            raise SynthError(f"n_frames: must be between 2 and {MAX_FRAMES}, got {self.n_frames}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2**32:
            raise SynthError(f"seed: expected an integer in [0, 2^32), got {self.seed!r}")
        for name in ("speed_mps", "exposure_change"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise SynthError(f"{name}: expected a number, got {value!r}")
        if not np.isfinite(self.speed_mps) or not 1.0 <= self.speed_mps <= 30.0:
            raise SynthError(f"speed_mps: must be between 1 and 30 m/s (KITTI: 5-15), got {self.speed_mps}")
        if self.route_length_m > MAX_ROUTE_M:
            raise SynthError(
                f"n_frames x speed_mps: the route would be {self.route_length_m / 1000:.1f} km, "
                f"more than {MAX_ROUTE_M / 1000:.0f} km"
            )
        if not np.isfinite(self.exposure_change) or not 0.0 <= self.exposure_change <= 0.5:
            raise SynthError(f"exposure_change: must be between 0 and 0.5, got {self.exposure_change}")

    @property
    def route_length_m(self) -> float:
        return (self.n_frames - 1) * self.speed_mps * sensors.FRAME_DT


@dataclass(frozen=True)
class Trajectory:
    """Planned motion. T_world_cam: (N,4,4) cam0 poses, world = cam0 of frame 0; T_town_world: (4,4);
    s: (N,) distance driven (m); route: (M,2) street-centre polyline in the town frame; lap_m: loop lap or 0."""

    T_world_cam: np.ndarray
    T_town_world: np.ndarray
    s: np.ndarray
    route: np.ndarray
    lap_m: float


def plan_trajectory(settings: SynthSettings) -> Trajectory:
    """The car's cam0 poses for these settings (no rendering); raises SynthError for impossible settings."""
    settings.check()
    grid = paths.make_grid(settings.seed)
    s = paths.arc_lengths(settings.n_frames, settings.speed_mps, settings.stops)
    needed = float(s[-1]) + ROUTE_LOOKAHEAD_M
    if settings.loop:
        route, lap = paths.loop_route(grid, float(s[-1]))
    else:
        rng = np.random.default_rng(np.random.SeedSequence([settings.seed, 8]))
        route, lap = paths.staircase_route(grid, needed + 60.0, rng), 0.0
    lane = paths.LanePath(route)
    T_town_cam = paths.camera_poses(lane, s)
    T_town_world = T_town_cam[0].copy()
    T_world_cam = np.linalg.inv(T_town_world)[None] @ T_town_cam
    return Trajectory(T_world_cam, T_town_world, s, route, lap)


def exposure_gains(settings: SynthSettings) -> np.ndarray:
    """(N,) camera gain per frame: 1 +- exposure_change, a slow swing with a seeded phase."""
    phase = np.random.default_rng(np.random.SeedSequence([settings.seed, 9])).uniform(0.0, 2.0 * np.pi)
    i = np.arange(settings.n_frames)
    return 1.0 + settings.exposure_change * np.sin(2.0 * np.pi * i / EXPOSURE_PERIOD_FRAMES + phase)


def _write_text_files(seq_dir: Path, poses_file: Path, traj: Trajectory) -> None:
    (seq_dir / "calib.txt").write_text(sensors.KITTI_CALIB_00_TEXT)
    times = np.arange(len(traj.s)) * sensors.FRAME_DT
    (seq_dir / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    rows = traj.T_world_cam[:, :3, :].reshape(len(traj.s), 12)
    poses_file.write_text("".join(" ".join(f"{x:.9e}" for x in row) + "\n" for row in rows))


def _plain(value: np.generic) -> object:
    """JSON fallback for numpy scalars (settings may arrive as numpy integers or floats)."""
    return value.item()


def _write_ground_truth(gt_dir: Path, settings: SynthSettings, traj: Trajectory, town: Town,
                        gains: np.ndarray) -> None:
    T_world_town = np.linalg.inv(traj.T_town_world)
    e = town.edges.reshape(-1, 3) @ T_world_town[:3, :3].T + T_world_town[:3, 3]
    np.save(gt_dir / "edges.npy", e.reshape(-1, 2, 3))
    np.save(gt_dir / "edge_kind.npy", town.edge_kind)
    still = np.flatnonzero(np.diff(traj.s) == 0.0) + 1
    scene = {
        "generator": GENERATOR,
        "generator_version": GENERATOR_VERSION,
        "settings": asdict(settings),
        "frames": {"dt_s": sensors.FRAME_DT, "still_frames": still.tolist(), "distance_m": traj.s.tolist()},
        "camera": {"height_m": sensors.CAMERA_HEIGHT_M, "lane_offset_m": paths.LANE_OFFSET_M,
                   "exposure_gains": [round(float(g), 9) for g in gains]},
        "lidar": {"elevations_deg": sensors.LIDAR_ELEVATIONS_DEG.tolist(),
                  "azimuth_steps": sensors.LIDAR_AZIMUTH_STEPS, "max_range_m": sensors.LIDAR_MAX_RANGE_M,
                  "min_range_m": sensors.LIDAR_MIN_RANGE_M, "range_noise_m": sensors.LIDAR_RANGE_NOISE_M},
        "town": {"T_town_world": traj.T_town_world.tolist(), "route_town_xy": traj.route.tolist(),
                 "loop_lap_m": traj.lap_m, "sun_town": sun_direction(settings.seed).tolist(),
                 "n_triangles": int(len(town.triangles)), "n_edges": int(len(town.edges))},
        "edges": {"frame": "world (cam0 of frame 0)", "kind": {"geometric": EDGE_GEOMETRIC, "texture": EDGE_TEXTURE}},
        "depth": {"written": settings.write_depth, "kind": "cam0 z-depth in metres, inf where no surface"},
    }
    (gt_dir / "scene.json").write_text(json.dumps(scene, indent=1, sort_keys=True, default=_plain))


def _render_frames(stage_seq: Path, settings: SynthSettings, traj: Trajectory, renderer: Renderer,
                   gains: np.ndarray, progress: Callable[[int, int], None] | None, frames: range | None = None) -> None:
    """Render `frames` (all by default) into the sequence folder; progress(done, total) counts over them."""
    T_town_cam = traj.T_town_world[None] @ traj.T_world_cam
    frames = range(settings.n_frames) if frames is None else frames
    total = len(frames)

    def frame(i: int) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([settings.seed, 5, i]))
        image, depth = renderer.render(T_town_cam[i], float(gains[i]), rng)
        scan = renderer.scan(T_town_cam[i] @ sensors.T_CAM_VELO, rng)
        _write_frame(stage_seq, i, image, scan, depth if settings.write_depth else None)

    # Two frames in flight: while one thread is in numpy shading or PNG encoding (which release the GIL), the
    # other's ray cast keeps both cores busy. Each frame has its own random stream, so the order does not matter.
    with ThreadPoolExecutor(max_workers=RENDER_THREADS) as pool:
        pending = []
        for k, i in enumerate(frames):
            pending.append(pool.submit(frame, i))
            if len(pending) > RENDER_THREADS:
                pending.pop(0).result()
                if progress is not None:
                    progress(k + 1 - RENDER_THREADS, total)
        for k, job in enumerate(pending):
            job.result()
            if progress is not None:
                progress(total - len(pending) + k + 1, total)


def _write_frame(seq_dir: Path, i: int, image: np.ndarray, scan: np.ndarray, depth: np.ndarray | None) -> None:
    """A frame's files, each written whole under a hidden name and renamed, the image last: a frame is on disk
    when its image is (a sequence extended in place, plvo_synth.cache, is never read half-written)."""
    name = f"{i:06d}"
    if depth is not None:
        _replace_with(seq_dir / "gt" / "depth" / f"{name}.npy", lambda f: np.save(f, depth.astype(np.float32)))
    _replace_with(seq_dir / "velodyne" / f"{name}.bin", lambda f: f.write(scan.astype(np.float32).tobytes()))
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise SynthError(f"{seq_dir / 'image_0' / name}.png: cannot encode the image")
    _replace_with(seq_dir / "image_0" / f"{name}.png", lambda f: f.write(png.tobytes()))


def _replace_with(path: Path, write: Callable) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise SynthError(f"{path}: cannot write ({exc.strerror or exc})") from None


def rendered_frames(seq_dir: Path) -> int:
    """How many frames, from frame 0 on, a sequence folder holds whole (image and scan)."""
    n = 0
    while (seq_dir / "image_0" / f"{n:06d}.png").is_file() and (seq_dir / "velodyne" / f"{n:06d}.bin").is_file():
        n += 1
    return n


def check_sequence_name(sequence: str) -> None:
    if not isinstance(sequence, str) or not re.fullmatch(r"\d{2}", sequence):
        raise SynthError(f"sequence: expected two digits like '00', got {sequence!r}")


def check_target(out_root: Path, sequence: str, overwrite: bool, how: str = "overwrite=True / --overwrite") -> None:
    """Raise SynthError if out_root cannot hold sequences/NN, or NN is there and overwrite is False (`how`: how
    to pass it, in the message)."""
    out_root = Path(out_root)
    if out_root.exists() and not out_root.is_dir():
        raise SynthError(f"out_root: {out_root} exists and is not a directory")
    target = out_root / "sequences" / sequence
    if target.exists() and not overwrite:
        raise SynthError(f"{target}: sequence {sequence} exists already (pass {how})")


def check_request(out_root: Path, sequence: str, settings: SynthSettings, overwrite: bool = False) -> None:
    """Raise SynthError (naming the setting) if the sequence cannot or must not be written; touches nothing."""
    check_sequence_name(sequence)
    plan_trajectory(settings)
    check_target(out_root, sequence, overwrite)


def _town_of(settings: SynthSettings, traj: Trajectory) -> Town:
    T_town_cam = traj.T_town_world[None] @ traj.T_world_cam
    lane = paths.LanePath(traj.route)
    s_end = float(traj.s[-1]) + ROUTE_LOOKAHEAD_M
    samples = lane.sample(np.arange(0.0, min(s_end, lane.length), 5.0))[:, :2]
    town = build_town(paths.make_grid(settings.seed), np.vstack([samples, T_town_cam[:, :2, 3]]), settings.seed)
    log.info("town: %d triangles, %d edges", len(town.triangles), len(town.edges))
    return town


def write_sequence(root: Path, sequence: str, settings: SynthSettings,
                   progress: Callable[[int, int], None] | None = None, stop: int | None = None) -> None:
    """Render one sequence into `root` (a fresh directory, not yet visible to readers): every text file and the
    ground truth of all its frames, the images and scans of frames 0..stop-1 (all by default; the rest can be
    added later by `extend_sequence`, to the same bits)."""
    traj = plan_trajectory(settings)
    seq_dir = root / "sequences" / sequence
    for sub in ("image_0", "velodyne", "gt/depth" if settings.write_depth else "gt"):
        (seq_dir / sub).mkdir(parents=True, exist_ok=True)
    (root / "poses").mkdir(parents=True, exist_ok=True)
    _write_text_files(seq_dir, root / "poses" / f"{sequence}.txt", traj)
    town = _town_of(settings, traj)
    gains = exposure_gains(settings)
    _write_ground_truth(seq_dir / "gt", settings, traj, town, gains)
    renderer = Renderer(town, build_atlas(settings.seed), settings.seed)
    _render_frames(seq_dir, settings, traj, renderer, gains, progress, range(settings.n_frames if stop is None
                                                                             else min(stop, settings.n_frames)))


def extend_sequence(root: Path, sequence: str, settings: SynthSettings, stop: int,
                    progress: Callable[[int, int], None] | None = None) -> None:
    """Render frames up to stop-1 that a sequence written by `write_sequence(..., stop=...)` lacks, in place."""
    seq_dir = root / "sequences" / sequence
    start, stop = rendered_frames(seq_dir), min(stop, settings.n_frames)
    if start >= stop:
        return
    traj = plan_trajectory(settings)
    renderer = Renderer(_town_of(settings, traj), build_atlas(settings.seed), settings.seed)
    _render_frames(seq_dir, settings, traj, renderer, exposure_gains(settings), progress, range(start, stop))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_stages(folder: Path, prefix: str) -> list[Path]:
    """Remove staging folders `<prefix><pid>-*` in `folder` whose process is gone; returns those removed."""
    removed = []
    for stage in folder.glob(f"{prefix}*"):
        pid = stage.name[len(prefix):].split("-", 1)[0]
        if stage.is_dir() and pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
            shutil.rmtree(stage, ignore_errors=True)
            removed.append(stage)
    return removed


def generate_sequence(out_root: str | Path, sequence: str = "00", n_frames: int = 300, seed: int = 0,
                      speed_mps: float = 10.0, loop: bool = False, stops: bool = False, exposure_change: float = 0.0,
                      write_depth: bool = False, progress: Callable[[int, int], None] | None = None,
                      overwrite: bool = False) -> Path:
    """Write sequence NN of the synthetic town under out_root (KITTI odometry layout); returns out_root.

    progress(done, total) is called after each frame. An existing sequence NN is replaced only with overwrite.
    """
    settings = SynthSettings(n_frames, seed, speed_mps, bool(loop), bool(stops), exposure_change, bool(write_depth))
    out_root = Path(out_root)
    check_request(out_root, sequence, settings, overwrite)
    write_staged(out_root, sequence, ".synth-", lambda stage: write_sequence(stage, sequence, settings, progress))
    return out_root


def write_staged(out_root: Path, sequence: str, prefix: str, write: Callable[[Path], None]) -> None:
    """Run write(stage) into a staging folder beside out_root/sequences and move sequence NN and its poses file in
    when it returns: a sequence folder is complete or absent, and a replaced one is removed only then."""
    out_root.mkdir(parents=True, exist_ok=True)
    remove_stale_stages(out_root, f"{prefix}{sequence}-")
    # The pid in the name: a stage left by a killed run (SIGKILL, power loss) is removed by the next run once its
    # process is gone; SIGTERM and Ctrl-C reach the `finally` below (plvo_app.guards).
    stage = Path(tempfile.mkdtemp(prefix=f"{prefix}{sequence}-{os.getpid()}-", dir=out_root))
    try:
        write(stage)
        _move_in(stage, out_root, sequence)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def write_resumable(out_root: Path, sequence: str, prefix: str, key: str, write: Callable[[Path], None]) -> None:
    """As write_staged, but the staging folder is named by `key` (what determines the files) and kept when write
    fails or the run is stopped, so that the next run with the same key carries on in it (write must skip what is
    already complete there). Stages of other keys for this sequence are removed; a stage another process is
    writing is refused."""
    out_root.mkdir(parents=True, exist_ok=True)
    remove_stale_stages(out_root, f"{prefix}{sequence}-")
    stage = out_root / f"{prefix}{sequence}-partial-{key}"
    for other in out_root.glob(f"{prefix}{sequence}-partial-*"):
        if other != stage and other.is_dir():
            with _stage_lock(other) as free:
                if free:
                    shutil.rmtree(other, ignore_errors=True)
    stage.mkdir(exist_ok=True)
    with _stage_lock(stage) as free:
        if not free:
            raise SynthError(f"{stage}: another process is writing sequence {sequence} there")
        write(stage)
        _move_in(stage, out_root, sequence)
        shutil.rmtree(stage, ignore_errors=True)


@contextlib.contextmanager
def _stage_lock(stage: Path) -> Iterator[bool]:
    """An exclusive flock on stage/.lock for the `with` block, if free: `as` gives whether it was had."""
    fd = os.open(stage / ".lock", os.O_CREAT | os.O_RDWR, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held = True
        except BlockingIOError:
            held = False
        yield held
    finally:
        os.close(fd)  # releases the lock


def _move_in(stage: Path, out_root: Path, sequence: str) -> None:
    """Move stage/sequences/NN and stage/poses/NN.txt into out_root, replacing an older sequence NN last."""
    target = out_root / "sequences" / sequence
    (out_root / "sequences").mkdir(exist_ok=True)
    (out_root / "poses").mkdir(exist_ok=True)
    if target.exists():
        target.rename(stage / "old-sequence")
    os.replace(stage / "poses" / f"{sequence}.txt", out_root / "poses" / f"{sequence}.txt")
    (stage / "sequences" / sequence).rename(target)  # last: a sequence directory is always complete
