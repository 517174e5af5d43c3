"""The twin of a KITTI raw drive: driven along the drive's own oxts trajectory, written in KITTI's raw layout.

  ROOT/DATE/calib_{cam_to_cam,imu_to_velo,velo_to_cam}.txt    the day's calibration (velo_to_cam with the rig's error)
  ROOT/DATE/DATE_drive_NNNN_sync/image_00/data/NNNNNNNNNN.png + timestamps.txt
  ROOT/DATE/DATE_drive_NNNN_sync/velodyne_points/data/NNNNNNNNNN.bin + timestamps{,_start,_end}.txt
  ROOT/DATE/DATE_drive_NNNN_sync/oxts/data/NNNNNNNNNN.txt + timestamps.txt, dataformat.txt
  ROOT/DATE/DATE_drive_NNNN_sync/gt/                         as a twin's gt/ (twin.generate), plus poses.txt: cam0
                                                             T_world_cam of each frame, frame 0 the world

read as the real drive is (plvo.data.kitti.KittiRaw, pykitti.raw). Frames A:B of the drive are written as frames
0.. of the twin; the world is built along every oxts record.

Timing. The drive's oxts records are the 100 Hz GPS/INS samples nearest each camera timestamp (KITTI: "a worst-case
time difference of 5 ms"), so against a frame clock their positions jitter by the car's speed times up to +-5 ms
(+-5 cm at 11 m/s, repeating every three frames as the 0.1035 s frame period beats against 10 ms). Each record's
pose is exact at its own timestamp: the twin's path is a smoothing spline through the records at their own times
(each coordinate and the unwrapped roll, pitch and yaw against time, cut-off about SMOOTH_HZ), read at a regular
frame clock (the drive's mean velodyne period, ~0.1035 s). That removes the timing jitter and the GPS/INS noise
above the cut-off; the twin's truth is that path exactly (the written oxts reproduce it through pykitti's
conversion, the calibration written included). The camera exposes when the lidar faces forward (KITTI triggers it
so), at each frame's instant; the lidar's true reference instant is later by the rig's time offset, which no file
states. The timestamps written are the frame clock: image_00, oxts and velodyne_points at the frame's instant, the
sweep from half a period before to half after (the real drive's image stamps lag its velodyne stamps by 17 ms,
taken for the images' transfer and not reproduced).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import logging
import os
import re
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.spatial.transform import Rotation

from plvo.errors import SynthError
from plvo_synth import sensors
from plvo_synth.kitti_calib import (
    RAW_CALIB_FILES,
    KittiCalibration,
    parse_calib_text,
    raw_day_calibration,
    rigid,
)
from plvo_synth.twin.follow import FollowedPath, followed, parse_range
from plvo_synth.twin.generate import (
    FrameFiles,
    Twin,
    TwinSettings,
    build_twin,
    render_frames,
    settings_key,
    write_ground_truth,
)

log = logging.getLogger(__name__)

RAW_DRIVE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_(\d{4})(?:_sync)?$")
EARTH_RADIUS_M = 6378137.0  # pykitti's
SMOOTH_HZ = 1.0  # the car's motion is kept below this, the oxts' noise above it is removed
GRAVITY = 9.81
_OXTS_FIELDS = 30


@dataclass(frozen=True)
class RawDrive:
    """A real raw drive's records: date, number, the drive's folder, its oxts packets (F,30) at their timestamps
    (F,) s of day, its velodyne timestamps (F,) s of day (NaN where the file has none), and the day's calib texts."""

    date: str
    number: str
    folder: Path
    packets: np.ndarray
    oxts_times: np.ndarray
    velodyne_times: np.ndarray
    calib_texts: dict

    @property
    def name(self) -> str:
        return f"{self.date}_drive_{self.number}"

    @property
    def frame_period_s(self) -> float:
        """The lidar's period (s), a least-squares line through the velodyne timestamps."""
        k = np.flatnonzero(np.isfinite(self.velodyne_times))
        return float(np.polyfit(k, self.velodyne_times[k], 1)[0])

    def frame_times(self) -> np.ndarray:
        """(F,) s of day: the regular frame clock that best fits the velodyne timestamps."""
        k = np.flatnonzero(np.isfinite(self.velodyne_times))
        slope, start = np.polyfit(k, self.velodyne_times[k], 1)
        return start + slope * np.arange(len(self.packets))


def parse_drive_name(drive: str) -> tuple[str, str]:
    m = RAW_DRIVE.match(str(drive))
    if m is None:
        raise SynthError(f"raw drive {drive!r}: expected a name like 2011_09_26_drive_0009")
    return m.group(1), m.group(2)


def _stamps(path: Path, n: int | None = None, blanks: bool = False) -> np.ndarray:
    """KITTI timestamps file -> (N,) seconds of the day (NaN for a blank line where `blanks`)."""
    if not path.is_file():
        raise SynthError(f"{path}: timestamps file not found")
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            if not blanks:
                raise SynthError(f"{path}:{lineno}: empty timestamp")
            out.append(np.nan)
            continue
        m = re.fullmatch(r"\d{4}-\d{2}-\d{2} (\d{2}):(\d{2}):(\d{2}(?:\.\d+)?)", line.strip())
        if m is None:
            raise SynthError(f"{path}:{lineno}: not a timestamp like 2011-09-26 13:08:24.957314930: {line.strip()!r}")
        out.append(int(m.group(1)) * 3600 + int(m.group(2)) * 60 + float(m.group(3)))
    if n is not None and len(out) < n:
        raise SynthError(f"{path}: {len(out)} timestamps for {n} records")
    return np.asarray(out[:n] if n is not None else out)


def read_drive(root: str | Path, drive: str) -> RawDrive:
    """The real drive ROOT/DATE/DATE_drive_NNNN_sync: every oxts record, its timestamps and the day's calibration;
    SynthError names the file that is missing or wrong."""
    date, number = parse_drive_name(drive)
    folder = Path(root) / date / f"{date}_drive_{number}_sync"
    oxts_dir = folder / "oxts" / "data"
    files = sorted(oxts_dir.glob("*.txt")) if oxts_dir.is_dir() else []
    if not files:
        raise SynthError(f"{oxts_dir}: no oxts records (*.txt)")
    packets = []
    for k, f in enumerate(files):
        if f.stem != f"{k:010d}":
            raise SynthError(f"{oxts_dir / f'{k:010d}.txt'}: missing oxts record {k}")
        fields = f.read_text().split()
        try:
            values = [float(x) for x in fields]
        except ValueError:
            values = []
        if len(values) != _OXTS_FIELDS or not np.all(np.isfinite(values)):
            raise SynthError(f"{f}: expected one line of {_OXTS_FIELDS} numbers, got {len(fields)} fields")
        packets.append(values)
    n = len(packets)
    oxts_times = _stamps(folder / "oxts" / "timestamps.txt", n)
    velodyne_times = _stamps(folder / "velodyne_points" / "timestamps.txt", n, blanks=True)
    if np.isfinite(velodyne_times).sum() < 2:
        raise SynthError(f"{folder / 'velodyne_points' / 'timestamps.txt'}: fewer than two timestamps")
    texts = {}
    for name in RAW_CALIB_FILES:
        path = Path(root) / date / name
        if not path.is_file():
            raise SynthError(f"{path}: calibration file not found")
        texts[name] = path.read_text()
    return RawDrive(date, number, folder, np.asarray(packets), oxts_times, velodyne_times, texts)


def T_velo_imu(calib: KittiCalibration) -> np.ndarray:
    return rigid(parse_calib_text(dict(calib.raw_files)["calib_imu_to_velo.txt"]))


def mercator(packets: np.ndarray, scale: float) -> np.ndarray:
    """(F,30) packets -> (F,3) pykitti's Mercator x, y and altitude (m)."""
    lat, lon, alt = packets[:, 0], packets[:, 1], packets[:, 2]
    tx = scale * lon * np.pi * EARTH_RADIUS_M / 180.0
    ty = scale * EARTH_RADIUS_M * np.log(np.tan((90.0 + lat) * np.pi / 360.0))
    return np.column_stack([tx, ty, alt])


def euler_zyx(R: np.ndarray) -> np.ndarray:
    """(K,3,3) rotations R = Rz(yaw) Ry(pitch) Rx(roll) (pykitti's oxts convention) -> (K,3) roll, pitch, yaw."""
    return Rotation.from_matrix(R).as_euler("ZYX")[:, ::-1]


def smooth_path(drive: RawDrive) -> tuple[Callable[[np.ndarray], np.ndarray], float]:
    """-> T_w_imu(t) for times t (s of day): the oxts records' poses (pykitti's frame: Mercator from the first
    record's latitude, origin at the first record) smoothed against their own timestamps, and the Mercator
    scale."""
    scale = float(np.cos(np.radians(drive.packets[0, 0])))
    xyz = mercator(drive.packets, scale)
    xyz -= xyz[0]
    rpy = np.unwrap(drive.packets[:, 3:6], axis=0)
    t = drive.oxts_times - drive.oxts_times[0]
    # a smoothing spline's response is 1 / (1 + lam w^4 / dt): half at w = (dt / lam)^(1/4)
    dt_mean = float(np.mean(np.diff(t))) if len(t) > 1 else sensors.FRAME_DT
    lam = dt_mean / (2.0 * np.pi * SMOOTH_HZ) ** 4
    if len(t) < 5:
        raise SynthError(f"{drive.folder / 'oxts'}: {len(t)} oxts records, at least 5 needed")
    splines = [make_smoothing_spline(t, v, lam=lam) for v in np.column_stack([xyz, rpy]).T]

    def pose(times: np.ndarray) -> np.ndarray:
        tt = np.asarray(times, np.float64) - drive.oxts_times[0]
        v = np.column_stack([s(tt) for s in splines])
        T = np.tile(np.eye(4), (len(tt), 1, 1))
        T[:, :3, :3] = Rotation.from_euler("ZYX", v[:, [5, 4, 3]]).as_matrix()
        T[:, :3, 3] = v[:, :3]
        return T

    return pose, scale


@dataclass(frozen=True)
class RawTwinPlan:
    """A raw drive's twin before rendering: the drive, its day's calibration, the frame clock (F,) s of day, the
    physical cam0 poses (F,4,4) at those instants in the smoothed oxts frame, and the followed path (cam0 of record
    0 the world) cut to the frames asked."""

    drive: RawDrive
    calib: KittiCalibration
    frame_times: np.ndarray
    T_w_cam: np.ndarray
    path: FollowedPath


def plan_raw_twin(root: str | Path, drive_name: str, frames: str | None) -> RawTwinPlan:
    drive = read_drive(root, drive_name)
    calib = raw_day_calibration(drive.date, drive.calib_texts)
    times = drive.frame_times()
    pose, _ = smooth_path(drive)
    T_cam0_imu = calib.T_cam_velo @ T_velo_imu(calib)
    T_w_cam = pose(times) @ np.linalg.inv(T_cam0_imu)
    T_kitti_cam = np.linalg.inv(T_w_cam[0])[None] @ T_w_cam
    parse_range(frames, len(T_w_cam), str(drive.folder / "oxts"))
    path = followed(T_kitti_cam, str(drive.folder / "oxts"), frames)
    return RawTwinPlan(drive, calib, times, T_w_cam, path)


def oxts_lines(plan: RawTwinPlan, T_cam_velo_stated: np.ndarray) -> list[str]:
    """The oxts record of each frame of the twin: pykitti turns them into poses T_w_imu that, with the calibration
    the twin states, give back the twin's cam0 poses exactly; velocities, accelerations and angular rates from
    the smoothed path; accuracy, status and mode fields as the real record nearest in time has them."""
    a = plan.path.first
    idx = np.arange(a, a + plan.path.n_frames)
    T_cam0_imu = T_cam_velo_stated @ T_velo_imu(plan.calib)
    W = plan.T_w_cam[idx] @ T_cam0_imu
    real = plan.drive.packets[idx]
    lat0 = float(f"{real[0, 0]:.12f}")
    lon0 = float(f"{real[0, 1]:.12f}")
    alt0 = float(f"{real[0, 2]:.6f}")
    scale = np.cos(np.radians(lat0))
    rel = W[:, :3, 3] - W[0, :3, 3]
    ty0 = scale * EARTH_RADIUS_M * np.log(np.tan((90.0 + lat0) * np.pi / 360.0))
    lat = np.degrees(2.0 * np.arctan(np.exp((ty0 + rel[:, 1]) / (scale * EARTH_RADIUS_M)))) - 90.0
    lon = lon0 + rel[:, 0] / (scale * np.pi * EARTH_RADIUS_M / 180.0)
    alt = alt0 + rel[:, 2]
    rpy = euler_zyx(W[:, :3, :3])
    # rates from the path through the written poses, by central differences on the frame clock
    t = plan.frame_times[idx]
    v = np.gradient(W[:, :3, 3], t, axis=0) if len(t) > 1 else np.zeros((len(t), 3))
    acc = np.gradient(v, t, axis=0) if len(t) > 2 else np.zeros((len(t), 3))
    rot = Rotation.from_matrix(W[:, :3, :3])
    if len(t) > 1:
        step = (rot[:-1].inv() * rot[1:]).as_rotvec() / np.diff(t)[:, None]  # body rates between frames
        omega = np.vstack([step[:1], 0.5 * (step[1:] + step[:-1]), step[-1:]]) if len(step) > 1 else \
            np.vstack([step, step])
    else:
        omega = np.zeros((1, 3))
    R = W[:, :3, :3]
    yaw = rpy[:, 2]
    level = np.stack([np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)]),
                      np.column_stack([-np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)])], axis=1)  # (K,2,3) f, l
    v_fl = np.einsum("kij,kj->ki", level, v)
    force = acc + np.array([0.0, 0.0, GRAVITY])  # what an accelerometer measures
    a_body = np.einsum("kji,kj->ki", R, force)
    a_fl = np.einsum("kij,kj->ki", level, force)
    w_level = np.einsum("kij,kjl,kl->ki", level, R, omega)
    lines = []
    for k in range(len(idx)):
        values = [f"{lat[k]:.12f}", f"{lon[k]:.12f}", f"{alt[k]:.9f}", *(f"{x:.12f}" for x in rpy[k]),
                  f"{v[k, 1]:.9f}", f"{v[k, 0]:.9f}", f"{v_fl[k, 0]:.9f}", f"{v_fl[k, 1]:.9f}", f"{v[k, 2]:.9f}",
                  *(f"{x:.9f}" for x in a_body[k]), *(f"{x:.9f}" for x in a_fl[k]), f"{force[k, 2]:.9f}",
                  *(f"{x:.9f}" for x in omega[k]), *(f"{x:.9f}" for x in w_level[k]),
                  f"{(R[k] @ omega[k])[2]:.9f}",
                  *(f"{x:.6g}" for x in real[k, 23:25]), *(str(int(x)) for x in real[k, 25:30])]
        lines.append(" ".join(values) + "\n")
    return lines


def stamp(seconds_of_day: float, date: str) -> str:
    """Seconds of the day -> KITTI's 'YYYY-MM-DD HH:MM:SS.nnnnnnnnn'."""
    ns = int(round(seconds_of_day * 1e9))
    s, frac = divmod(ns, 10**9)
    day = dt.datetime.strptime(date, "%Y_%m_%d") + dt.timedelta(seconds=s)
    return f"{day:%Y-%m-%d %H:%M:%S}.{frac:09d}"


def raw_settings_label(drive: str) -> str:
    return f"raw drive {drive}"


def write_raw_twin(stage: Path, plan: RawTwinPlan, settings: TwinSettings,
                   progress: Callable[[int, int], None] | None = None, twin: Twin | None = None) -> None:
    """Render the raw twin into `stage` (DATE/... as under the root), resuming a stopped run's frames there."""
    drive = plan.drive
    twin = twin or build_raw_twin(plan, settings)
    day = stage / drive.date
    folder = day / f"{drive.name}_sync"
    files = FrameFiles(folder / "image_00" / "data", folder / "velodyne_points" / "data", folder / "gt", digits=10)
    files.make(settings.write_depth)
    (folder / "oxts" / "data").mkdir(parents=True, exist_ok=True)
    for name, text in twin.calib.raw_texts_with(twin.T_cam_velo_stated).items():
        (day / name).write_text(text)
    idx = np.arange(plan.path.first, plan.path.first + plan.path.n_frames)
    t = plan.frame_times[idx]
    half = 0.5 * drive.frame_period_s
    for sub, times in (("image_00", t), ("oxts", t), ("velodyne_points", t)):
        (folder / sub / "timestamps.txt").write_text("".join(stamp(x, drive.date) + "\n" for x in times))
    for suffix, shift in (("_start", -half), ("_end", half)):
        (folder / "velodyne_points" / f"timestamps{suffix}.txt").write_text(
            "".join(stamp(x + shift, drive.date) + "\n" for x in t))
    for k, line in enumerate(oxts_lines(plan, twin.T_cam_velo_stated)):
        (folder / "oxts" / "data" / f"{k:010d}.txt").write_text(line)
    fmt = drive.folder / "oxts" / "dataformat.txt"
    if fmt.is_file():
        shutil.copyfile(fmt, folder / "oxts" / "dataformat.txt")
    (files.gt / "poses.txt").write_text(plan.path.pose_file_text() if plan.path.first == 0 else
                                        _pose_rows(plan.path.T_world_cam))
    gains = render_frames(stage / ".frames", twin, settings, files, drive.name, progress)
    write_ground_truth(files.gt, settings, twin, gains, {
        "raw_drive": {"drive": drive.name, "source": str(drive.folder), "first_record": plan.path.first,
                      "frame_period_s": drive.frame_period_s, "smooth_hz": SMOOTH_HZ,
                      "truth": "gt/poses.txt: cam0 T_world_cam, frame 0 the world; the oxts give the same through "
                               "pykitti with the calibration written"}})


def _pose_rows(T: np.ndarray) -> str:
    return "".join(" ".join(f"{x:.9e}" for x in row[:3].ravel()) + "\n" for row in T)


def build_raw_twin(plan: RawTwinPlan, settings: TwinSettings) -> Twin:
    return build_twin(settings, plan.drive.number, plan.path, plan.calib, seed_key=plan.drive.number,
                      raw_drive=True, sweep_s=plan.drive.frame_period_s)


@contextlib.contextmanager
def _locked(stage: Path) -> Iterator[None]:
    """An exclusive flock on stage/.lock for the block; SynthError if another process holds it."""
    fd = os.open(stage / ".lock", os.O_CREAT | os.O_RDWR, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SynthError(f"{stage}: another process is writing this raw twin there") from None
        yield
    finally:
        os.close(fd)


def check_raw_target(out_root: Path, plan: RawTwinPlan, overwrite: bool) -> None:
    out_root = Path(out_root)
    if out_root.exists() and not out_root.is_dir():
        raise SynthError(f"--out {out_root}: exists and is not a directory")
    target = out_root / plan.drive.date / f"{plan.drive.name}_sync"
    if Path(plan.drive.folder).resolve() == target.resolve():
        raise SynthError(f"--out {out_root}: would write the twin over the real drive {plan.drive.folder}")
    if target.exists() and not overwrite:
        raise SynthError(f"{target}: exists already (pass --overwrite to replace it)")


def check_raw_request(out_root: str | Path, root: str | Path, drive_name: str, settings: TwinSettings,
                      overwrite: bool = False) -> RawTwinPlan:
    """The raw twin's plan, or SynthError naming the file, range or setting that is wrong; writes nothing."""
    settings.check()
    plan = plan_raw_twin(root, drive_name, settings.frames)
    check_raw_target(Path(out_root), plan, overwrite)
    return plan


def generate_raw_twin(out_root: str | Path, root: str | Path, drive_name: str, settings: TwinSettings,
                      progress: Callable[[int, int], None] | None = None, overwrite: bool = False,
                      plan: RawTwinPlan | None = None) -> Path:
    """Write the twin of raw drive `drive_name` (found under `root`) under out_root in KITTI's raw layout, staged
    beside it and moved in when complete (a stopped run's stage of the same settings is carried on); the day's
    calib_*.txt under out_root/DATE are written or must say the same. plan: check_raw_request's, if made."""
    out_root = Path(out_root)
    plan = plan or check_raw_request(out_root, root, drive_name, settings, overwrite)
    twin = build_raw_twin(plan, settings)
    day = out_root / plan.drive.date
    wanted = twin.calib.raw_texts_with(twin.T_cam_velo_stated)
    for name, text in wanted.items():
        path = day / name
        if path.is_file() and path.read_text() != text and not overwrite:
            raise SynthError(f"{path}: holds another calibration than this twin's (another seed or realism wrote "
                             "this day; pass --overwrite to replace it)")
    stage = out_root / f".rawtwin-{plan.drive.name}-partial-{settings_key(plan.drive.name, settings)[:12]}"
    out_root.mkdir(parents=True, exist_ok=True)
    for other in out_root.glob(f".rawtwin-{plan.drive.name}-partial-*"):
        if other != stage and other.is_dir():  # a stage of other settings is never carried on
            shutil.rmtree(other, ignore_errors=True)
    stage.mkdir(exist_ok=True)
    with _locked(stage):
        write_raw_twin(stage, plan, settings, progress, twin)
        day.mkdir(parents=True, exist_ok=True)
        for name in wanted:
            os.replace(stage / plan.drive.date / name, day / name)
        target = day / f"{plan.drive.name}_sync"
        if target.exists():
            target.rename(stage / "old-drive")
        (stage / plan.drive.date / f"{plan.drive.name}_sync").rename(target)  # last: a drive is always complete
    shutil.rmtree(stage, ignore_errors=True)
    return out_root
