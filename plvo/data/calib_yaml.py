"""Calibration YAML: a ROS camera_calibration file (ost.yaml) plus the lidar -> camera transform.

```yaml
image_width: 1226
image_height: 370
camera_matrix: {rows: 3, cols: 3, data: [707.09, 0, 601.89, 0, 707.09, 183.11, 0, 0, 1]}  # or a flat list
distortion_model: plumb_bob            # optional (also rational_polynomial, equidistant)
distortion_coefficients: [0, 0, 0, 0, 0]   # optional, OpenCV order; {rows, cols, data} also read
rectification_matrix: ...              # optional 3x3 (stereo rectification rotation)
projection_matrix: ...                 # optional 3x4; its left 3x3 is the rectified camera matrix
T_cam_lidar: [r11, r12, r13, tx, ...]   # 16 (or 12) numbers row-major, or nested rows; or T_lidar_cam
lidar_elevation_offset_deg: 0.0        # optional, the lidar's vertical-angle error (KITTI's HDL-64E: 0.205)
```
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from plvo.atomic import write_text_atomic
from plvo.data.camera_model import CameraModel
from plvo.errors import CalibrationError
from plvo.geometry import se3


@dataclass(frozen=True)
class CalibFile:
    """A calibration YAML's contents: the camera, T_cam_lidar (4,4), the lidar elevation offset (deg)."""

    camera: CameraModel
    T_cam_lidar: np.ndarray
    elevation_offset_deg: float = 0.0


def _matrix(path: Path, data: dict, key: str, sizes: tuple[int, ...], required: bool = True) -> np.ndarray | None:
    if key not in data or data[key] is None:
        if required:
            raise CalibrationError(f"{path}: no '{key}'")
        return None
    value = data[key]
    if isinstance(value, dict):  # ROS / OpenCV style {rows, cols, data}
        value = value.get("data")
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: '{key}' is not a list of numbers") from None
    if arr.size not in sizes:
        raise CalibrationError(f"{path}: '{key}' has {arr.size} numbers, expected {' or '.join(map(str, sizes))}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{path}: '{key}' has NaN or infinite values")
    return arr


def _transform(path: Path, data: dict) -> np.ndarray:
    for key, invert in (("T_cam_lidar", False), ("T_lidar_cam", True)):
        arr = _matrix(path, data, key, (12, 16), required=False)
        if arr is not None:
            T = np.eye(4)
            T[:3, :] = arr[:12].reshape(3, 4)
            R = T[:3, :3]
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
                raise CalibrationError(f"{path}: '{key}' rotation is not orthonormal")
            return se3.inv(T) if invert else T
    raise CalibrationError(f"{path}: no 'T_cam_lidar' (lidar -> camera, 4x4 row-major) or 'T_lidar_cam'")


def read_calib_yaml(path: Path | str) -> CalibFile:
    """Calibration YAML -> CalibFile; errors name the file and key."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: calibration file not found") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise CalibrationError(f"{path}: cannot read calibration YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a YAML mapping of calibration keys")
    size = []
    for key in ("image_width", "image_height"):
        value = data.get(key)
        if not isinstance(value, int) or value <= 0:
            raise CalibrationError(f"{path}: '{key}' must be a positive integer, got {value!r}")
        size.append(value)
    K = _matrix(path, data, "camera_matrix", (9,))
    assert K is not None  # required: _matrix raised otherwise
    K = K.reshape(3, 3)
    D = _matrix(path, data, "distortion_coefficients", tuple(range(0, 15)), required=False)
    R = _matrix(path, data, "rectification_matrix", (9,), required=False)
    P = _matrix(path, data, "projection_matrix", (12,), required=False)
    camera = CameraModel(
        width=size[0], height=size[1], K=K, D=np.zeros(0) if D is None else D,
        model=str(data.get("distortion_model") or "plumb_bob"), R=np.eye(3) if R is None else R.reshape(3, 3),
        P=None if P is None else P.reshape(3, 4)[:, :3].copy())
    offset = data.get("lidar_elevation_offset_deg", 0.0)
    if not isinstance(offset, (int, float)):
        raise CalibrationError(f"{path}: 'lidar_elevation_offset_deg' must be a number, got {offset!r}")
    return CalibFile(camera, _transform(path, data), float(offset))


def write_calib_yaml(path: Path | str, camera: CameraModel, T_cam_lidar: np.ndarray,
                     elevation_offset_deg: float = 0.0, comment: str | None = None) -> None:
    """CameraModel and T_cam_lidar (4,4) -> calibration YAML readable by read_calib_yaml, written atomically;
    `comment` (lines) heads the file as YAML comments, e.g. where the calibration came from."""
    def flat(a: np.ndarray) -> list[float]:
        return [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]

    data = {
        "image_width": int(camera.width), "image_height": int(camera.height),
        "camera_matrix": {"rows": 3, "cols": 3, "data": flat(camera.K)},
        "distortion_model": camera.model,
        "distortion_coefficients": {"rows": 1, "cols": int(len(camera.D)), "data": flat(camera.D)},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": flat(camera.R)},
        "T_cam_lidar": {"rows": 4, "cols": 4, "data": flat(T_cam_lidar)},
        "lidar_elevation_offset_deg": float(elevation_offset_deg),
    }
    if camera.P is not None:
        P = np.zeros((3, 4))
        P[:, :3] = camera.P
        data["projection_matrix"] = {"rows": 3, "cols": 4, "data": flat(P)}
    head = "".join(f"# {line}\n" for line in comment.splitlines()) if comment else ""
    write_text_atomic(path, head + yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120))
