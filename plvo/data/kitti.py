"""KITTI odometry and raw layouts, read through pykitti.

Odometry: `root/sequences/NN/{image_0..3, velodyne, calib.txt, times.txt}` and `root/poses/NN.txt`.
Raw: `root/DATE/DATE_drive_NNNN_sync/{image_00..03/data, velodyne_points/data, oxts/data, oxts/timestamps.txt}`,
`velodyne_points/timestamps{_start,,_end}.txt` and `root/DATE/calib_{cam_to_cam, velo_to_cam, imu_to_velo}.txt`;
ground truth from oxts, as cam0 poses relative to the drive's frame 0.

Sweeps: the odometry benchmark's scans are motion-compensated (its readme; CT-ICP and KISS-ICP do not deskew them);
a raw drive's are raw sweeps, each return in the sensor frame at its own time (its readme: "untwist" them), and are
read so (`scans_compensated = False`: registration deskews them). A raw frame's time is the instant its sweep faced
forward, when the cameras were triggered (`velodyne_points/timestamps.txt`, seconds since the drive's frame 0):
regular (102.5-104.6 ms apart on drive 0009), where the oxts stamps, pykitti's, are the nearest 100 Hz records
(80-110 ms apart, 11-38 ms later) and the images' stamps come 16-21 ms later (the capture's latency). Each return's time
(`Frame.scan_time`, relative to the frame's time) follows from its azimuth over the frame's own sweep, whose length
is `timestamps_end - timestamps_start` (101-106 ms on drive 0009, not a nominal 100): clockwise seen from above,
behind at the start and the end, zero facing forward (plvo.lidar.deskew.azimuth_times; KITTI writes timestamps.txt
as the midpoint of start and end). KITTI's readme says the lidar turns counter-clockwise; the scans say clockwise:
deskewed clockwise, raw scans k and k+10 of drive 0009 register with a residual of 0.2167 m rms, undeskewed 0.2187,
deskewed counter-clockwise 0.2235.

pykitti parses calibration, timestamps and oxts and reads the files; this module checks the layout first so that
bad data raises a DatasetError / CalibrationError naming the file and frame instead of a KeyError or IndexError.
Construction lists files and reads headers only; images and scans are read by `__getitem__`.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from plvo.data.calib_check import check_calibration, check_rotation
from plvo.data.dataset import FrameSelection, SelectedFrames, select_frames
from plvo.data.images import read_image_file, split_gray_color
from plvo.data.pointcloud import check_scan_values
from plvo.data.trajectory import read_kitti_poses
from plvo.errors import CalibrationError, DatasetError, TrajectoryError
from plvo.geometry import se3
from plvo.lidar.deskew import azimuth_times
from plvo.types import Calibration, Frame

log = logging.getLogger(__name__)

CAMERAS = (0, 1, 2, 3)  # 0/1 gray left/right, 2/3 colour left/right (converted to gray, colour kept for viewers)
COLOUR_CAMERAS = (2, 3)
RAW_DRIVE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_(\d{4})(?:_sync)?$")
_OXTS_FIELDS = 30
# KITTI's HDL-64E returns sit this far too low in elevation (see plvo.lidar.registration); the synthetic town's
# scans, written in the odometry layout with a gt/scene.json beside them, are exact.
KITTI_LIDAR_ELEVATION_OFFSET_DEG = 0.205
SYNTH_MARKER = Path("gt") / "scene.json"


def _check_camera(camera: int) -> int:
    if camera not in CAMERAS:
        raise DatasetError(f"camera {camera!r}: must be 0 or 1 (gray left/right) or 2 or 3 (colour left/right)")
    return int(camera)


def _numbered_files(directory: Path, suffix: str) -> dict[int, Path]:
    """Files named by a frame number (`000012.png`) in a directory -> {number: path}."""
    if not directory.is_dir():
        return {}
    return {int(p.stem): p for p in directory.glob(f"*{suffix}") if p.stem.isdigit()}


def _name_of(files: dict[int, Path], directory: Path, frame: int, suffix: str) -> Path:
    width = len(next(iter(files.values())).stem) if files else 6
    return directory / f"{frame:0{width}d}{suffix}"


def _hint_other_cameras(images: dict[int, Path], image_dir: Path, camera_dirs: list[Path]) -> None:
    """No images for the chosen camera: say which cameras the sequence does have (colour-only downloads)."""
    if images:
        return
    others = [c for c, d in zip(CAMERAS, camera_dirs) if d != image_dir and _numbered_files(d, ".png")]
    if others:
        raise DatasetError(f"{image_dir}: no images (*.png); this sequence has camera "
                           f"{' and '.join(map(str, others))}: give --camera {others[0]}")


def _check_listing(images: dict[int, Path], image_dir: Path, scans: dict[int, Path], scan_dir: Path) -> int:
    """Number of frames n; raises unless images and scans both exist for exactly the frames 0..n-1."""
    if not images:
        raise DatasetError(f"{image_dir}: no images (*.png)")
    if not scans:
        raise DatasetError(f"{scan_dir}: no scans (*.bin)")
    n = max(len(images), len(scans))
    counts = f"{len(images)} images in {image_dir} but {len(scans)} scans in {scan_dir}: "
    if len(images) == len(scans):
        counts = ""
    for k in range(n):
        if k not in images:
            raise DatasetError(f"{counts}{_name_of(images, image_dir, k, '.png')}: missing image (frame {k})")
        if k not in scans:
            raise DatasetError(f"{counts}{_name_of(scans, scan_dir, k, '.bin')}: missing scan (frame {k})")
    return n


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _gray8_png(path: Path) -> np.ndarray | None:
    """An 8-bit greyscale PNG (KITTI's cameras 0 and 1, the synthetic town) decoded by OpenCV, ~1.5x faster than
    PIL and the same pixels (no conversion either way); None for any other file, which PIL then reads as before."""
    with open(path, "rb") as f:
        data = f.read()
    # IHDR: bit depth at byte 24, colour type at 25 (0: greyscale, no alpha, no palette)
    if len(data) < 26 or not data.startswith(_PNG_SIGNATURE) or data[24] != 8 or data[25] != 0:
        return None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return image if image is not None and image.ndim == 2 and image.dtype == np.uint8 else None


def _png_bit_depth(path: Path) -> int | None:
    """A PNG's bit depth from its header (None: not a PNG or unreadable; the reading then names the fault)."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return None
    return head[24] if len(head) == 26 and head.startswith(_PNG_SIGNATURE) else None


def _check_scan_size(path: Path, frame: int) -> None:
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read scan (frame {frame}): {exc}") from None
    if size % 16:
        raise DatasetError(
            f"{path}: {size} bytes is not a multiple of 16 (float32 x,y,z,reflectance) (frame {frame})"
        )
    if size == 0:
        raise DatasetError(f"{path}: empty scan (frame {frame})")


_RIGID_KEYS = ("Tr", "R")  # odometry's lidar-to-camera; a raw drive's velo-to-cam and imu-to-velo rotations


def _read_calib(path: Path, needed: dict[str, int]) -> dict[str, np.ndarray]:
    """pykitti's calib parser, with every needed key checked for presence, parseability, size and finite values.

    pykitti skips a line it cannot parse, which would then be reported as missing: the needed keys' lines are
    read here first, so that a present but unparseable line is reported as such, with its line number."""
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file not found")
    try:
        text = path.read_text()
        data = _pykitti().utils.read_calib_file(str(path))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot parse calibration ({exc})") from None
    lines: dict[str, tuple[int, str]] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        key, sep, value = line.partition(":")
        if sep and key.strip() in needed:
            lines.setdefault(key.strip(), (lineno, value))
    for key, size in needed.items():
        if key not in lines:
            raise CalibrationError(f"{path}: no '{key}' matrix")
        lineno, value = lines[key]
        bad = next((f for f in value.split() if not _is_number(f)), None)
        if bad is not None:
            raise CalibrationError(f"{path}:{lineno}: '{key}' is not parseable: {bad!r} is not a number")
        matrix = np.asarray([float(f) for f in value.split()])
        if matrix.size != size:
            raise CalibrationError(f"{path}:{lineno}: '{key}' has {matrix.size} numbers, expected {size}")
        if not np.all(np.isfinite(matrix)):
            raise CalibrationError(f"{path}:{lineno}: '{key}' holds NaN or infinite values")
        if key in _RIGID_KEYS:  # before pykitti inverts it ("Singular matrix", naming no file)
            check_rotation(matrix.reshape(3, -1)[:, :3],
                           f"{path}:{lineno}: degenerate calibration: '{key}', the lidar's mounting,")
        data[key] = matrix
    return data


def _image_size(path: Path, frame: int) -> tuple[int, int]:
    try:
        with Image.open(path) as img:  # reads the header only
            return img.size
    except (OSError, UnidentifiedImageError) as exc:
        raise DatasetError(f"{path}: unreadable image (frame {frame}): {exc}") from None


def _calibration(calib: Any, camera: int, width: int, height: int, elevation_offset_deg: float) -> Calibration:
    """pykitti calib namedtuple -> Calibration of the chosen camera (rectified)."""
    T_cam_velo = np.asarray(getattr(calib, f"T_cam{camera}_velo"), dtype=np.float64)
    T_cam0_cam = np.eye(4)
    if camera != 0:  # rectified cameras differ by a translation along x only
        T_cam0_cam = np.asarray(calib.T_cam0_velo, dtype=np.float64) @ np.linalg.inv(T_cam_velo)
    return Calibration(
        K=np.asarray(getattr(calib, f"K_cam{camera}"), dtype=np.float64).copy(),
        T_cam_velo=T_cam_velo,
        width=int(width),
        height=int(height),
        T_cam0_cam=T_cam0_cam,
        lidar_elevation_offset_deg=float(elevation_offset_deg),
    )


class _KittiSequence(SelectedFrames):
    """Shared lazy reading of a selected range of KITTI frames (image + scan files per frame number).

    scans_compensated: the odometry benchmark's scans are delivered motion-compensated (KISS-ICP and CT-ICP do not
    deskew them); a generated sequence's are unless its scene.json says the lidar sweeps (the twins: each return in
    the sensor frame at its own time); a raw drive's are not (KittiRaw)."""

    name: str
    scans_compensated: bool = True

    def _init_frames(
        self,
        sequence: str,
        calib: Calibration,
        frames: tuple[int, ...],
        images: dict[int, Path],
        scans: dict[int, Path],
        times: np.ndarray,
        gt: np.ndarray | None,
        camera: int = 0,
    ) -> None:
        self.sequence = sequence
        self.camera = camera
        self.calib = calib
        self._frames = frames
        self._images = [images[k] for k in frames]
        self._scans = [scans[k] for k in frames]
        self._times = np.asarray(times, dtype=np.float64)
        self._gt = gt
        for k, path in zip(frames, self._scans):
            _check_scan_size(path, k)
        log.info("%s %s: %d frames (%d..%d), %dx%d", self.name, sequence, len(frames), frames[0], frames[-1],
                 calib.width, calib.height)

    def __getitem__(self, i: int) -> Frame:
        """Frame at position i (0..len-1) of the selection; Frame.index is the dataset's frame number."""
        i = self._position(i)
        gt = None if self._gt is None else self._gt[i].copy()
        gray, color = self._load_image(i)
        scan = self._load_scan(i)
        return Frame(
            index=self._frames[i],
            time=float(self._times[i]),
            image=gray,
            scan=scan,
            calib=self.calib,
            gt_T_world_cam=gt,
            color=color,
            scan_time=self._scan_times(i, scan),
            scan_compensated=self.scans_compensated,
        )

    def _load_image(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(grey (H,W), RGB (H,W,3) for the colour cameras 2 and 3 else None)."""
        path, frame = self._images[i], self._frames[i]
        colour = self.camera in COLOUR_CAMERAS
        try:
            image = None if colour else _gray8_png(path)
            if image is None and _png_bit_depth(path) == 16:
                # PIL's "L" conversion clips 16-bit grey to white; read it whole and scale it on purpose (the high
                # byte, as a ROS mono16 image is read)
                image = read_image_file(path, frame)
                if colour and image.ndim == 2:
                    image = np.repeat(image[:, :, None], 3, axis=2)
            if image is None:
                loaded = _pykitti().utils.load_image(str(path), mode="RGB" if colour else "L")
                image = np.asarray(loaded, dtype=np.uint8)
        except FileNotFoundError:
            raise DatasetError(f"{path}: missing image (frame {frame})") from None
        except (OSError, UnidentifiedImageError) as exc:
            raise DatasetError(f"{path}: unreadable image (frame {frame}): {exc}") from None
        if image.shape[:2] != (self.calib.height, self.calib.width):
            raise DatasetError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]}, but the first frame's is "
                f"{self.calib.width}x{self.calib.height} (frame {frame})"
            )
        return split_gray_color(image)

    def load_scan(self, i: int) -> np.ndarray:
        """The scan (N,4) of position i alone, without decoding the image (for lidar-only methods)."""
        return self._load_scan(self._position(i))

    def load_timed_scan(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The scan (N,4) of position i alone and its returns' times (N,) in seconds after the frame's time where the
        layout records its sweeps (a raw drive), else None (as `Frame.scan_time`)."""
        i = self._position(i)
        scan = self._load_scan(i)
        return scan, self._scan_times(i, scan)

    def _scan_times(self, i: int, scan: np.ndarray) -> np.ndarray | None:
        return None

    def _load_scan(self, i: int) -> np.ndarray:
        path, frame = self._scans[i], self._frames[i]
        _check_scan_size(path, frame)
        try:
            scan = _pykitti().utils.load_velo_scan(str(path))
        except OSError as exc:  # a folder in its place, a permission, an I/O error: the file and its frame
            raise DatasetError(f"{path}: unreadable scan (frame {frame}): {exc.strerror or exc}") from None
        if np.isfinite(scan).all():  # the common case, 40x cheaper than the per-row mask below
            check_scan_values(scan, path, frame)
            return scan
        bad = ~np.isfinite(scan).all(axis=1)
        if bad.any():
            raise DatasetError(
                f"{path}: {int(bad.sum())} of {len(scan)} points have NaN or infinite values (frame {frame})"
            )
        return scan


def _pykitti() -> Any:
    """pykitti, imported on first use: it imports pandas (~0.3 s), which a command's --help need not wait for."""
    import pykitti
    import pykitti.utils

    return pykitti


def _pykitti_odometry(root: str, sequence: str) -> Any:
    """pykitti's odometry loader without its pose reading (which prints instead of raising)."""

    class _PykittiOdometry(_pykitti().odometry):  # type: ignore[misc]
        def _load_poses(self) -> None:
            self.poses: list[np.ndarray] = []

    return _PykittiOdometry(root, sequence)


class KittiOdometry(_KittiSequence):
    """KITTI odometry sequence `root/sequences/NN` with ground truth from `root/poses/NN.txt` when present."""

    name = "kitti_odometry"

    def __init__(self, root: str | Path, sequence: str, frames: FrameSelection = None, camera: int = 0) -> None:
        root, camera = Path(root), _check_camera(camera)
        seq_dir = root / "sequences" / sequence
        if not seq_dir.is_dir():
            raise DatasetError(f"{seq_dir}: no such odometry sequence directory")
        image_dir, scan_dir = seq_dir / f"image_{camera}", seq_dir / "velodyne"
        images, scans = _numbered_files(image_dir, ".png"), _numbered_files(scan_dir, ".bin")
        _hint_other_cameras(images, image_dir, [seq_dir / f"image_{c}" for c in CAMERAS])
        n = _check_listing(images, image_dir, scans, scan_dir)
        selected = select_frames(frames, n, f"sequence {sequence} ({n} frames in {image_dir})")
        _read_calib(seq_dir / "calib.txt", {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "Tr": 12})
        times_file = seq_dir / "times.txt"
        times = _read_times(times_file, n)
        try:
            data = _pykitti_odometry(str(root), sequence)
        except (OSError, ValueError, KeyError) as exc:
            raise DatasetError(f"{seq_dir}: pykitti cannot load the sequence: {exc}") from None
        width, height = _image_size(images[selected[0]], selected[0])
        synthetic = (seq_dir / SYNTH_MARKER).is_file()
        offset = KITTI_LIDAR_ELEVATION_OFFSET_DEG
        if synthetic:  # a generated sequence says how its lidar sweeps and what elevation error it carries
            lidar = _scene_lidar(seq_dir / SYNTH_MARKER)
            offset = _elevation_offset(lidar, seq_dir / SYNTH_MARKER)
            self.scans_compensated = not _swept(lidar)
        calib = check_calibration(_calibration(data.calib, camera, width, height, offset), str(seq_dir / "calib.txt"))
        pose_file = root / "poses" / f"{sequence}.txt"
        if not pose_file.is_file() and (seq_dir / "poses.txt").is_file():  # SemanticKITTI keeps it in the sequence
            pose_file = seq_dir / "poses.txt"
        gt = _odometry_gt(pose_file, selected, calib.T_cam0_cam)
        self.truth_source = None if gt is None else str(pose_file)
        self._init_frames(sequence, calib, selected, images, scans, times[list(selected)], gt, camera)


def _scene_lidar(scene_file: Path) -> dict:
    """A generated sequence's scene.json -> its `lidar` block ({} when it has none)."""
    try:
        scene = json.loads(scene_file.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{scene_file}: unreadable scene description: {exc}") from None
    lidar = scene.get("lidar") if isinstance(scene, dict) else None
    return lidar if isinstance(lidar, dict) else {}


def _swept(lidar: dict) -> bool:
    """Whether a scene's lidar sweeps over the frame, each return at its own time (the twins' `lidar.sweep_s` > 0;
    a realistic odometry twin's scans are motion-compensated, as KITTI's are)."""
    return float(lidar.get("sweep_s", 0.0) or 0.0) > 0.0 and not lidar.get("motion_compensated", False)


def _elevation_offset(lidar: dict, scene_file: Path) -> float:
    """The vertical-angle error a generated lidar's returns carry (a realistic twin's is KITTI's; the readers raise
    the scans by it as they do KITTI's own), 0 where the scene does not say."""
    value = lidar.get("elevation_offset_deg", 0.0)
    try:
        offset = float(value)
    except (TypeError, ValueError):
        offset = float("nan")
    if not np.isfinite(offset) or abs(offset) > 5.0:
        raise DatasetError(f"{scene_file}: field 'lidar.elevation_offset_deg' must be a small angle in degrees, "
                           f"got {value!r}")
    return offset


def _read_times(path: Path, n: int) -> np.ndarray:
    """times.txt -> (M,) seconds with M >= n, naming the file and line of a bad value."""
    if not path.is_file():
        raise DatasetError(f"{path}: timestamps file not found")
    values = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values.append(float(line))
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not a timestamp: {line.strip()!r}") from None
    if len(values) < n:
        raise DatasetError(f"{path}: {len(values)} timestamps for {n} frames")
    return np.asarray(values)


def _odometry_gt(pose_file: Path, frames: tuple[int, ...], T_cam0_cam: np.ndarray) -> np.ndarray | None:
    if not pose_file.is_file():
        log.info("no ground truth: %s not found", pose_file)
        return None
    try:
        poses = read_kitti_poses(pose_file)
    except TrajectoryError as exc:
        raise DatasetError(str(exc)) from None
    if len(poses) <= max(frames):
        raise DatasetError(f"{pose_file}: {len(poses)} poses, but frame {max(frames)} is selected")
    return poses[list(frames)] @ T_cam0_cam


class KittiRaw(_KittiSequence):
    """KITTI raw synced drive `root/DATE/DATE_drive_NNNN_sync`; ground truth from oxts (cam0 of frame 0 = world);
    raw sweeps, each frame at the instant its sweep faced forward, each return's time from its azimuth over that
    frame's sweep (see the module doc)."""

    name = "kitti_raw"
    scans_compensated = False

    def __init__(self, root: str | Path, drive: str, frames: FrameSelection = None, camera: int = 0) -> None:
        root, camera = Path(root), _check_camera(camera)
        match = RAW_DRIVE.match(drive)
        if match is None:
            raise DatasetError(f"raw drive {drive!r}: expected a name like 2011_09_26_drive_0009")
        date, number = match.group(1), match.group(2)
        drive_dir = root / date / f"{date}_drive_{number}_sync"
        if not drive_dir.is_dir():
            raise DatasetError(f"{drive_dir}: no such raw drive directory")
        image_dir = drive_dir / f"image_0{camera}" / "data"
        scan_dir, oxts_dir = drive_dir / "velodyne_points" / "data", drive_dir / "oxts" / "data"
        images, scans = _numbered_files(image_dir, ".png"), _numbered_files(scan_dir, ".bin")
        _hint_other_cameras(images, image_dir, [drive_dir / f"image_0{c}" / "data" for c in CAMERAS])
        n = _check_listing(images, image_dir, scans, scan_dir)
        _check_oxts_listing(oxts_dir, n)
        selected = select_frames(frames, n, f"drive {date}_drive_{number} ({n} frames in {image_dir})")
        _check_raw_calib(root / date)
        stamps = drive_dir / "oxts" / "timestamps.txt"
        if not stamps.is_file():
            raise DatasetError(f"{stamps}: timestamps file not found")
        if len(stamps.read_text().splitlines()) < n:
            raise DatasetError(f"{stamps}: fewer timestamps than the {n} frames")
        times, self._sweep_s = _velodyne_sweeps(drive_dir / "velodyne_points", selected)
        records = _oxts_records(oxts_dir, stamps, selected)
        data = _load_pykitti_raw(root, date, number, records, oxts_dir)
        width, height = _image_size(images[selected[0]], selected[0])
        offset = KITTI_LIDAR_ELEVATION_OFFSET_DEG
        scene_file = drive_dir / SYNTH_MARKER  # a twin of a raw drive says what elevation error its lidar carries
        if scene_file.is_file():
            offset = _elevation_offset(_scene_lidar(scene_file), scene_file)
        calib = check_calibration(_calibration(data.calib, camera, width, height, offset),
                                  f"{root / date} calib_*.txt")
        forward = _read_stamps(drive_dir / "velodyne_points" / "timestamps.txt", (0, *selected))
        gt = _raw_gt(data, calib.T_cam0_cam, _read_stamps(stamps, records), forward)
        self.truth_source = f"{oxts_dir.parent} (GPS/INS)"
        self._init_frames(f"{date}_drive_{number}", calib, selected, images, scans, times, gt, camera)

    def _scan_times(self, i: int, scan: np.ndarray) -> np.ndarray:
        return azimuth_times(scan, float(self._sweep_s[i]))


_STAMP = re.compile(r"^\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2}(\.\d{1,9})?$")
_MAX_SWEEP_S = 1.0  # a spinning lidar's sweep; the HDL-64E's is 0.1


def _read_stamps(path: Path, frames: tuple[int, ...]) -> np.ndarray:
    """A raw drive's timestamps file (one `YYYY-MM-DD HH:MM:SS.fffffffff` line a frame) -> (len(frames),) int64
    nanoseconds of the given frames, naming the file, line and frame of a missing or bad one."""
    if not path.is_file():
        raise DatasetError(f"{path}: timestamps file not found")
    lines = path.read_text().splitlines()
    out = np.empty(len(frames), np.int64)
    for j, k in enumerate(frames):
        if k >= len(lines):
            raise DatasetError(f"{path}: no timestamp for frame {k} ({len(lines)} lines)")
        text = lines[k].strip()
        try:
            if not _STAMP.match(text):
                raise ValueError(text)
            out[j] = np.datetime64(text.replace(" ", "T"), "ns").astype(np.int64)
        except ValueError:
            what = "no timestamp" if not text else f"not a timestamp: {text!r}"
            raise DatasetError(f"{path}:{k + 1}: {what} (frame {k})") from None
    return out


def _velodyne_sweeps(velo_dir: Path, frames: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A raw drive's velodyne timestamps -> (the frames' times (len,) in seconds since the drive's first frame faced
    forward, their sweeps' durations (len,) in seconds), checked: each sweep 0-1 s long, facing forward within it,
    the frames in time order."""
    with_first = (0, *frames)
    start, forward, end = (_read_stamps(velo_dir / name, with_first)
                           for name in ("timestamps_start.txt", "timestamps.txt", "timestamps_end.txt"))
    for j, k in enumerate(with_first):
        sweep = 1e-9 * float(end[j] - start[j])
        if not 0.0 < sweep < _MAX_SWEEP_S:
            raise DatasetError(f"{velo_dir / 'timestamps_end.txt'}:{k + 1}: the sweep of frame {k} ends {sweep:.6f} s "
                               f"after it starts (timestamps_start.txt), expected 0-{_MAX_SWEEP_S:g} s")
        if not start[j] <= forward[j] <= end[j]:
            raise DatasetError(f"{velo_dir / 'timestamps.txt'}:{k + 1}: frame {k} faces forward outside its sweep "
                               "(timestamps_start.txt .. timestamps_end.txt)")
    step = np.diff(forward[1:])
    if np.any(step <= 0):
        j = int(np.flatnonzero(step <= 0)[0]) + 1
        raise DatasetError(f"{velo_dir / 'timestamps.txt'}:{frames[j] + 1}: frame {frames[j]} is not after frame "
                           f"{frames[j - 1]}")
    return 1e-9 * (forward[1:] - forward[0]).astype(np.float64), 1e-9 * (end[1:] - start[1:]).astype(np.float64)


def _check_oxts_listing(oxts_dir: Path, n: int) -> None:
    oxts = _numbered_files(oxts_dir, ".txt")
    for k in range(n):
        if k not in oxts:
            raise DatasetError(f"{_name_of(oxts, oxts_dir, k, '.txt')}: missing oxts record (frame {k})")


def _check_raw_calib(date_dir: Path) -> None:
    _read_calib(date_dir / "calib_imu_to_velo.txt", {"R": 9, "T": 3})
    _read_calib(date_dir / "calib_velo_to_cam.txt", {"R": 9, "T": 3})
    needed = {f"P_rect_0{c}": 12 for c in CAMERAS} | {f"R_rect_0{c}": 9 for c in CAMERAS}
    _read_calib(date_dir / "calib_cam_to_cam.txt", needed)


def _oxts_records(oxts_dir: Path, stamps: Path, selected: tuple[int, ...]) -> tuple[int, ...]:
    """The oxts records the truth of frame 0 and the selected frames is interpolated from: each of those frames'
    own and its neighbours' where the drive has them (a record and its timestamp), in order, frame 0 first."""
    files = _numbered_files(oxts_dir, ".txt")
    lines = stamps.read_text().splitlines()
    wanted = {0, *selected}
    near = {j for k in wanted for j in (k - 1, k, k + 1)}
    usable = {j for j in near if j in files and j < len(lines) and lines[j].strip()}
    return tuple(sorted(usable | wanted))


def _load_pykitti_raw(root: Path, date: str, number: str, records: tuple[int, ...], oxts_dir: Path) -> Any:
    """pykitti.raw over the given oxts records, frame 0 first (the origin of pykitti's oxts poses)."""
    try:
        return _pykitti().raw(str(root), date, number, frames=list(records))
    except (ValueError, TypeError, IndexError) as exc:
        for k in records:
            path = oxts_dir / f"{k:010d}.txt"
            fields = path.read_text().split() if path.is_file() else []
            if len(fields) != _OXTS_FIELDS or not all(_is_number(f) for f in fields):
                raise DatasetError(
                    f"{path}: expected one line of {_OXTS_FIELDS} numbers, got {len(fields)} fields (frame {k})"
                ) from None
        stamps = oxts_dir.parent / "timestamps.txt"
        raise DatasetError(f"{stamps} or {oxts_dir}: pykitti cannot read drive {number}: {exc}") from None


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _raw_gt(data: Any, T_cam0_cam: np.ndarray, record_ns: np.ndarray, frame_ns: np.ndarray) -> np.ndarray:
    """(len,4,4) T_world_cam of the selected frames at their own times, world = cam0 of frame 0 at its time, from
    pykitti's oxts T_w_imu of the loaded records (their timestamps record_ns (R,)) and the frames' times frame_ns
    (1 + len,: frame 0, then the selection).

    A synced drive's oxts record of a frame is the GPS/INS's 100 Hz sample nearest its image's timestamp: on
    2011_09_26_drive_0009 11-38 ms after the frame's forward instant, in a pattern that repeats every three frames
    (the frames' 0.1035 s against the 10 ms samples), which at 11 m/s puts +-5 cm of timing jitter into every step
    of the truth (both plvo and KISS-ICP saw it, their step errors correlated 0.93). Each frame's pose is therefore
    interpolated to its own time between the records either side (positions linearly, rotations along the
    geodesic), extrapolated from the nearest two at a drive's end."""
    T_imu_cam0 = se3.inv(np.asarray(data.calib.T_cam0_imu, dtype=np.float64))
    T_w_cam0 = np.stack([np.asarray(o.T_w_imu) @ T_imu_cam0 for o in data.oxts])
    t = 1e-9 * (np.asarray(record_ns, np.int64) - int(frame_ns[0])).astype(np.float64)
    at = np.stack([_pose_at(T_w_cam0, t, 1e-9 * float(f - frame_ns[0])) for f in frame_ns])
    return se3.inv(at[0]) @ at[1:] @ T_cam0_cam


def _pose_at(poses: np.ndarray, times: np.ndarray, t: float) -> np.ndarray:
    """(R,4,4) poses at increasing times (R,) -> the pose at t, interpolated between the two records around it
    (or the nearest two)."""
    if len(poses) == 1:
        return poses[0]
    j = int(np.clip(np.searchsorted(times, t), 1, len(times) - 1))
    a, b = poses[j - 1], poses[j]
    span = times[j] - times[j - 1]
    w = (t - times[j - 1]) / span if span > 0 else 0.0
    out = np.eye(4)
    out[:3, :3] = a[:3, :3] @ se3.so3_exp(w * se3.so3_log(a[:3, :3].T @ b[:3, :3]))
    out[:3, 3] = a[:3, 3] + w * (b[:3, 3] - a[:3, 3])
    return out

