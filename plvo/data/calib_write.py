"""KITTI calibration -> the plain folder's calib.yaml (`plvo calib write`).

Reads an odometry `calib.txt` (P0..P3, Tr) or a raw recording day's `calib_cam_to_cam.txt` + `calib_velo_to_cam.txt`
with the KITTI readers' own parser and checks (plvo.data.kitti), and gives the chosen camera's Calibration exactly as
KittiOdometry / KittiRaw would: the folder reader then gives the same K and T_cam_lidar from the YAML written.

A calibration file does not say the images' size (the raw day's files do, as S_rect_0N): it is taken from the
first image beside the calibration (`image_N/` of an odometry sequence, `image_0N/data` of a raw drive), or given.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from plvo.data.calib_check import check_calibration
from plvo.data.calib_yaml import write_calib_yaml
from plvo.data.camera_model import CameraModel
from plvo.data.kitti import (
    CAMERAS,
    KITTI_LIDAR_ELEVATION_OFFSET_DEG,
    SYNTH_MARKER,
    _calibration,
    _check_camera,
    _elevation_offset,
    _image_size,
    _read_calib,
    _scene_lidar,
)
from plvo.errors import CalibrationError
from plvo.types import Calibration

ODOMETRY_FILE = "calib.txt"
RAW_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt")
_ODOMETRY_KEYS = {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "Tr": 12}
_RAW_CAM_KEYS = {f"P_rect_0{c}": 12 for c in CAMERAS} | {f"R_rect_0{c}": 9 for c in CAMERAS}


@dataclass(frozen=True)
class KittiCalibration:
    """The chosen camera's calibration and what it was read from (`files`, `size_from`: the image or key that gave
    the width and height)."""

    calib: Calibration
    camera: int
    files: tuple[Path, ...]
    size_from: str


def _first_png(directory: Path) -> Path | None:
    if not directory.is_dir():
        return None
    return min((p for p in directory.glob("*.png") if p.stem.isdigit()), default=None)


def _odometry(calib_file: Path, camera: int) -> SimpleNamespace:
    """The odometry calib.txt -> pykitti's calib fields, computed as pykitti.odometry does: it reads only a file
    named calib.txt inside a sequence folder, and one may come under another name (the shared data's
    calib/04-10.txt). Each camera's transform is cam0's shifted along x by its P's baseline, as pykitti has it."""
    data = _read_calib(calib_file, _ODOMETRY_KEYS)
    T_cam0_velo = np.vstack([np.reshape(data["Tr"], (3, 4)), [0.0, 0.0, 0.0, 1.0]])
    fields: dict[str, np.ndarray] = {}
    for c in CAMERAS:
        P = np.reshape(data[f"P{c}"], (3, 4))
        shift = np.eye(4)
        shift[0, 3] = P[0, 3] / P[0, 0]
        fields[f"T_cam{c}_velo"] = T_cam0_velo if c == 0 else shift.dot(T_cam0_velo)
        fields[f"K_cam{c}"] = P[0:3, 0:3]
    return SimpleNamespace(**fields)


def _raw(cam_to_cam: Path, velo_to_cam: Path) -> SimpleNamespace:
    """A raw day's two files -> pykitti.raw's calib fields, by pykitti's own code (it needs no drive for these)."""
    import pykitti

    _read_calib(velo_to_cam, {"R": 9, "T": 3})
    _read_calib(cam_to_cam, _RAW_CAM_KEYS)
    reader = pykitti.raw.__new__(pykitti.raw)  # only its calibration method is used: no drive to open
    reader.calib_path = str(cam_to_cam.parent)
    return SimpleNamespace(**reader._load_calib_cam_to_cam(str(velo_to_cam), str(cam_to_cam)))


def _raw_size(cam_to_cam: Path, camera: int) -> tuple[int, int] | None:
    key = f"S_rect_0{camera}"
    for line in cam_to_cam.read_text().splitlines():
        name, sep, value = line.partition(":")
        if sep and name.strip() == key:
            try:
                w, h = (float(v) for v in value.split())
            except ValueError:
                raise CalibrationError(f"{cam_to_cam}: '{key}' is not two numbers (width height)") from None
            return int(round(w)), int(round(h))
    return None


def _locate(path: Path) -> tuple[str, Path, Path | None, Path | None]:
    """(kind, calibration file, velo_to_cam for raw, folder the images are beside) for a file or folder."""
    if path.is_dir():
        if (path / ODOMETRY_FILE).is_file():
            return "odometry", path / ODOMETRY_FILE, None, path
        for day in (path, path.parent):  # a raw day's folder, or one of its drives
            if all((day / name).is_file() for name in RAW_FILES):
                return "raw", day / RAW_FILES[0], day / RAW_FILES[1], path if day != path else None
        raise CalibrationError(f"{path}: no KITTI calibration here: expected {ODOMETRY_FILE} (odometry) or "
                               f"{' + '.join(RAW_FILES)} (raw)")
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file not found")
    text = path.read_text(errors="replace")
    keys = {line.partition(":")[0].strip() for line in text.splitlines() if ":" in line}
    if "Tr" in keys or "P0" in keys:
        return "odometry", path, None, path.parent
    if "P_rect_00" in keys or path.name == RAW_FILES[0]:
        return "raw", path, path.parent / RAW_FILES[1], None
    if {"R", "T"} <= keys:  # the velo_to_cam alone: the camera's half is beside it
        return "raw", path.parent / RAW_FILES[0], path, None
    raise CalibrationError(f"{path}: not a KITTI calibration file: no 'Tr' or 'P0' (odometry calib.txt) and no "
                           "'P_rect_00' (raw calib_cam_to_cam.txt)")


def read_kitti_calibration(path: Path | str, camera: int = 0, size: tuple[int, int] | None = None
                           ) -> KittiCalibration:
    """A KITTI calibration file or folder -> the camera's Calibration as the KITTI readers give it.

    `path`: an odometry calib.txt (any name, told by its keys) or the sequence folder holding it; a raw day's
    calib_cam_to_cam.txt or calib_velo_to_cam.txt (the other one beside it), its folder or one of its drives.
    `size` (width, height) overrides the size found; without one the images beside the calibration, then (raw) the
    S_rect_0N line, say it."""
    camera = _check_camera(camera)
    kind, calib_file, velo_file, beside = _locate(Path(path))
    offset, size_from = KITTI_LIDAR_ELEVATION_OFFSET_DEG, "--size"
    files: tuple[Path, ...]
    if kind == "odometry":
        fields, files = _odometry(calib_file, camera), (calib_file,)
        image = _first_png(beside / f"image_{camera}") if beside is not None else None
        scene = beside / SYNTH_MARKER if beside is not None else None
        if scene is not None and scene.is_file():  # a generated sequence says its lidar's elevation error
            offset = _elevation_offset(_scene_lidar(scene), scene)
    else:
        assert velo_file is not None
        for f in (calib_file, velo_file):
            if not f.is_file():
                raise CalibrationError(f"{f}: calibration file not found (a raw calibration is "
                                       f"{' + '.join(RAW_FILES)}, side by side)")
        fields, files = _raw(calib_file, velo_file), (calib_file, velo_file)
        image = _first_png(beside / f"image_0{camera}" / "data") if beside is not None else None
    if size is None and image is not None:
        size, size_from = _image_size(image, int(image.stem)), str(image)
    if size is None and kind == "raw":
        size, size_from = _raw_size(calib_file, camera), f"{calib_file} S_rect_0{camera}"
    if size is None:
        raise CalibrationError(f"{calib_file}: holds no image size and no image_{camera}/ is beside it: give "
                               "--size WIDTHxHEIGHT (the images' size in pixels)")
    calib = check_calibration(_calibration(fields, camera, size[0], size[1], offset), str(calib_file))
    return KittiCalibration(calib, camera, files, size_from)


def write_folder_calib(path: Path | str, kc: KittiCalibration) -> None:
    """The Calibration as the folder layout's calib.yaml (pinhole, no distortion: KITTI's images are rectified)."""
    c = kc.calib
    sources = " + ".join(str(f) for f in kc.files)
    comment = (f"written by plvo calib write from {sources}, camera {kc.camera}; image size from {kc.size_from}")
    if kc.camera != 0:
        comment += (f"\nposes of a folder run are of this camera (camera {kc.camera}), not of KITTI's cam0 "
                    "as a KITTI run reports them")
    write_calib_yaml(path, CameraModel(c.width, c.height, c.K, D=np.zeros(5)), c.T_cam_velo,
                     c.lidar_elevation_offset_deg, comment=comment)
