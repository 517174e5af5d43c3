"""A plain folder of images and scans, for data that is neither KITTI nor a bag.

```
my_run/
  images/     000000.png ...          any names, frames in name order (.png, .jpg, .jpeg)
  scans/      000000.bin ...          one per image, in the same order (.bin KITTI float32 x,y,z,i / .pcd / .ply)
  calib.yaml                          plvo.data.calib_yaml (or give --calib)
  times.txt                           optional: one time in seconds a frame (default 0.1 s apart)
  poses.txt                           optional ground truth of the camera: KITTI (12 numbers a line, one a frame)
                                      or TUM (time tx ty tz qx qy qz qw, matched to times.txt within 10 ms)
```
Ground truth is re-based so that the camera of the folder's first frame is the world, as in KITTI.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from plvo.data.calib_check import check_calibration
from plvo.data.calib_yaml import read_calib_yaml
from plvo.data.dataset import FrameSelection, SelectedFrames, SourceOptions, select_frames
from plvo.data.images import read_image_file, split_gray_color
from plvo.data.pointcloud import read_scan_file
from plvo.data.trajectory import read_kitti_poses, read_tum
from plvo.errors import DatasetError, TrajectoryError
from plvo.geometry import se3
from plvo.types import Frame

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
SCAN_SUFFIXES = (".bin", ".pcd", ".ply")
DEFAULT_PERIOD_S = 0.1
TUM_MATCH_S = 0.01


def is_folder(path: Path | str | None) -> bool:
    return path is not None and (Path(path) / "images").is_dir() and (Path(path) / "scans").is_dir()


def _listing(directory: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.suffix.lower() in suffixes and not p.name.startswith("."))


def _read_times(path: Path, n: int) -> np.ndarray:
    values = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values.append(float(line.split()[0]))
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not a timestamp: {line!r}") from None
    if len(values) != n:
        raise DatasetError(f"{path}: {len(values)} timestamps for {n} images")
    times = np.asarray(values)
    if np.any(np.diff(times) <= 0):
        raise DatasetError(f"{path}:{int(np.argmax(np.diff(times) <= 0)) + 2}: timestamps must increase")
    return times


def _read_gt(path: Path, times: np.ndarray, have_times: bool) -> np.ndarray:
    """poses.txt (KITTI or TUM, told by its column count) -> (n,4,4) T_world_cam, world = camera of frame 0."""
    first = next((ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")), "")
    try:
        if len(first.replace(",", " ").split()) == 8:
            if not have_times:
                raise DatasetError(f"{path}: TUM ground truth needs the frames' times.txt beside it")
            stamps, poses = read_tum(path)
            idx = np.clip(np.searchsorted(stamps, times), 1, len(stamps) - 1)
            idx = np.where(np.abs(stamps[idx - 1] - times) < np.abs(stamps[idx] - times), idx - 1, idx)
            far = np.abs(stamps[idx] - times) > TUM_MATCH_S
            if far.any():
                k = int(np.argmax(far))
                raise DatasetError(f"{path}: no pose within {TUM_MATCH_S} s of frame {k} (time {times[k]:.6f} s; "
                                   f"nearest {stamps[idx[k]]:.6f} s)")
            poses = poses[idx]
        else:
            poses = read_kitti_poses(path)
            if len(poses) != len(times):
                raise DatasetError(f"{path}: {len(poses)} poses for {len(times)} frames")
    except TrajectoryError as exc:
        raise DatasetError(str(exc)) from None
    return se3.inv(poses[0]) @ poses


class FolderDataset(SelectedFrames):
    """images/ + scans/ + calib.yaml (+ times.txt, poses.txt) as a Dataset."""

    name = "folder"

    def __init__(self, root: str | Path, frames: FrameSelection = None, options: SourceOptions | None = None) -> None:
        self.root = Path(root)
        opts = options or SourceOptions()
        if not is_folder(self.root):
            raise DatasetError(f"{self.root}: not a plain folder dataset (needs images/ and scans/)")
        self.sequence = self.root.resolve().name
        self._images = _listing(self.root / "images", IMAGE_SUFFIXES)
        self._scans = _listing(self.root / "scans", SCAN_SUFFIXES)
        if not self._images:
            raise DatasetError(f"{self.root / 'images'}: no images ({', '.join(IMAGE_SUFFIXES)})")
        if len(self._scans) != len(self._images):
            raise DatasetError(f"{self.root}: {len(self._images)} images in images/ but {len(self._scans)} scans in "
                               "scans/ (one scan an image, paired in name order)")
        n = len(self._images)
        self._frames = select_frames(frames, n, f"folder {self.root} ({n} frames)")
        calib_path = Path(opts.calib) if opts.calib else self.root / "calib.yaml"
        cf = read_calib_yaml(calib_path)
        first = read_image_file(self._images[self._frames[0]], self._frames[0])
        if (cf.camera.width, cf.camera.height) != (first.shape[1], first.shape[0]):
            raise DatasetError(f"{calib_path}: calibration is for {cf.camera.width}x{cf.camera.height} images, but "
                               f"{self._images[self._frames[0]]} is {first.shape[1]}x{first.shape[0]}")
        offset = cf.elevation_offset_deg if opts.lidar_elevation_offset_deg is None else opts.lidar_elevation_offset_deg
        self.calib = check_calibration(cf.camera.calibration(cf.T_cam_lidar, offset), str(calib_path))
        self._rectify = cf.camera.rectifier()
        times_file, poses_file = self.root / "times.txt", self.root / "poses.txt"
        all_times = _read_times(times_file, n) if times_file.is_file() else DEFAULT_PERIOD_S * np.arange(n)
        gt = _read_gt(poses_file, all_times, times_file.is_file()) if poses_file.is_file() else None
        sel = list(self._frames)
        self._times, self._gt = all_times[sel], None if gt is None else gt[sel]
        self.truth_source = None if gt is None else str(poses_file)
        log.info("folder %s: %d frames, %dx%d%s", self.root, len(sel), self.calib.width, self.calib.height,
                 ", with ground truth" if gt is not None else "")

    def __getitem__(self, i: int) -> Frame:
        i = self._position(i)
        k = self._frames[i]
        raw = read_image_file(self._images[k], k)
        if raw.shape[:2] != (self.calib.height, self.calib.width):
            raise DatasetError(f"{self._images[k]}: image is {raw.shape[1]}x{raw.shape[0]}, the calibration's "
                               f"{self.calib.width}x{self.calib.height} (frame {k})")
        if self._rectify is not None:
            raw = self._rectify(raw)
        gray, color = split_gray_color(raw)
        return Frame(index=k, time=float(self._times[i]), image=gray, scan=read_scan_file(self._scans[k], k),
                     calib=self.calib, gt_T_world_cam=None if self._gt is None else self._gt[i].copy(),
                     color=color)
