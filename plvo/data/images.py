"""Camera images of any source -> the pipeline's grey image and, for colour sources, the viewers' RGB image.

One grey conversion (OpenCV's BT.601 weights) serves every colour source, so a KITTI colour camera read from its
PNG files and the same images read from a bag give identical grey frames.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from plvo.errors import DatasetError

if TYPE_CHECKING:
    from pathlib import Path

# ROS encodings (sensor_msgs/image_encodings.h) -> (channels, numpy dtype, OpenCV conversion to RGB or None)
_ENCODINGS: dict[str, tuple[int, str, int | None]] = {
    "mono8": (1, "u1", None),
    "8UC1": (1, "u1", None),
    "mono16": (1, "u2", None),
    "16UC1": (1, "u2", None),
    "rgb8": (3, "u1", None),
    "bgr8": (3, "u1", cv2.COLOR_BGR2RGB),
    "8UC3": (3, "u1", cv2.COLOR_BGR2RGB),  # OpenCV's (cv_bridge's) channel order
    "rgba8": (4, "u1", cv2.COLOR_RGBA2RGB),
    "bgra8": (4, "u1", cv2.COLOR_BGRA2RGB),
    "8UC4": (4, "u1", cv2.COLOR_BGRA2RGB),
    # cv2's Bayer names are of the second row's pattern: ROS rggb is OpenCV's BayerBG (see cv_bridge)
    "bayer_rggb8": (1, "u1", cv2.COLOR_BayerBG2RGB),
    "bayer_bggr8": (1, "u1", cv2.COLOR_BayerRG2RGB),
    "bayer_gbrg8": (1, "u1", cv2.COLOR_BayerGR2RGB),
    "bayer_grbg8": (1, "u1", cv2.COLOR_BayerGB2RGB),
}


def to_gray(rgb: np.ndarray) -> np.ndarray:
    """(H,W,3) uint8 RGB -> (H,W) uint8 grey, the one conversion every colour source uses."""
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:  # 16-bit grey (mono16, 16-bit PNG): keep the high byte
        return (image >> 8).astype(np.uint8)
    raise DatasetError(f"image of {image.dtype} pixels: expected 8 or 16 bits")


def split_gray_color(image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(H,W) grey or (H,W,3) RGB image -> (grey (H,W) uint8, RGB (H,W,3) uint8 or None for a grey source)."""
    image = _to_uint8(image)
    if image.ndim == 2:
        return np.ascontiguousarray(image), None
    rgb = np.ascontiguousarray(image[:, :, :3])
    return to_gray(rgb), rgb


def decode_raw(height: int, width: int, encoding: str, step: int, big_endian: bool, data: np.ndarray,
               where: str) -> np.ndarray:
    """sensor_msgs/Image fields -> (H,W) grey or (H,W,3) RGB array; `where` names topic and stamp in errors."""
    if encoding not in _ENCODINGS:
        raise DatasetError(f"{where}: image encoding {encoding!r} not supported (supported: "
                           f"{', '.join(_ENCODINGS)})")
    channels, kind, conversion = _ENCODINGS[encoding]
    dtype = np.dtype(kind).newbyteorder(">" if big_endian else "<")
    row_bytes = width * channels * dtype.itemsize
    buf = np.asarray(data, dtype=np.uint8).reshape(-1)
    if step < row_bytes or buf.size < step * height:
        raise DatasetError(f"{where}: {buf.size} bytes of data for a {width}x{height} {encoding} image with "
                           f"step {step}")
    rows = buf[: step * height].reshape(height, step)[:, :row_bytes]
    image = np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels).astype(dtype.newbyteorder("="))
    image = image[:, :, 0] if channels == 1 else image
    if conversion is not None:
        image = cv2.cvtColor(image, conversion)
    return image


def decode_compressed(fmt: str, data: np.ndarray, where: str) -> np.ndarray:
    """sensor_msgs/CompressedImage (PNG, JPEG...) -> (H,W) grey or (H,W,3) RGB array."""
    image = cv2.imdecode(np.asarray(data, dtype=np.uint8).reshape(-1), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{where}: cannot decode compressed image (format {fmt!r})")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    elif image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image


def read_image_file(path: str | Path, frame: int) -> np.ndarray:
    """An image file (PNG, JPEG...) -> (H,W) grey or (H,W,3) RGB array, naming the file and frame on error."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: missing or unreadable image (frame {frame})")
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image
