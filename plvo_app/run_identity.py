"""What a recording needs to be turned back into the run that produced it: the dataset's identity (layout,
sequence, root, frames, calibration), a hash of each input file, the machine, and optionally the raw inputs of a
short window (lossless: the image as PNG, the scan's float32 bytes), so that the recording alone reruns them.

`dataset_identity` is made by the CLI before the run (it knows the dataset); the recorder logs it and the hashes
as recording properties, and the embedded inputs on the `inputs/*` entities.
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import xxhash

from plvo.types import Calibration, Frame

INPUT_IMAGE = "inputs/image"  # PNG bytes of the frame's image (what the dataset decoded, re-encoded losslessly)
INPUT_SCAN = "inputs/scan"  # the scan's (N,4) float32 bytes, as read


def input_files(dataset) -> dict[int, tuple[str, str]]:
    """frame number -> (image file, scan file) for the datasets that read files (KITTI layouts, the town)."""
    images, scans = getattr(dataset, "_images", None), getattr(dataset, "_scans", None)
    if images is None or scans is None:
        return {}
    return {int(f): (str(i), str(s)) for f, i, s in zip(dataset.frame_indices, images, scans)}


def dataset_identity(dataset, root: Path | str | None, frames_arg: str | None, synthetic: bool) -> dict[str, Any]:
    """What names the input: layout, sequence, root (as given and resolved), frame selection, calibration."""
    c = dataset.calib
    return {
        "layout": getattr(dataset, "name", type(dataset).__name__), "sequence": dataset.sequence,
        "root": "" if root is None else str(Path(root).resolve()), "frames_arg": frames_arg or "",
        "frames": list(map(int, dataset.frame_indices)), "synthetic_town": bool(synthetic),
        "calib": calib_to_dict(c),
    }


def calib_to_dict(c: Calibration) -> dict[str, Any]:
    return {"K": np.asarray(c.K, float).ravel().tolist(),
            "T_cam_velo": np.asarray(c.T_cam_velo, float).ravel().tolist(),
            "width": int(c.width), "height": int(c.height),
            "T_cam0_cam": np.asarray(c.T_cam0_cam, float).ravel().tolist(),
            "lidar_elevation_offset_deg": float(getattr(c, "lidar_elevation_offset_deg", 0.0))}


def calib_from_dict(d: dict[str, Any]) -> Calibration:
    return Calibration(K=np.asarray(d["K"], float).reshape(3, 3), T_cam_velo=np.asarray(d["T_cam_velo"], float)
                       .reshape(4, 4), width=int(d["width"]), height=int(d["height"]),
                       T_cam0_cam=np.asarray(d["T_cam0_cam"], float).reshape(4, 4),
                       lidar_elevation_offset_deg=float(d.get("lidar_elevation_offset_deg", 0.0)))


def machine() -> dict[str, str]:
    """The machine and the libraries that decide the numbers."""
    out = {"host": platform.node(), "platform": platform.platform(), "processor": platform.processor() or
           platform.machine(), "cpus": str(os.cpu_count()), "python": sys.version.split()[0],
           "numpy": np.__version__, "opencv": cv2.__version__,
           "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "")}
    for name, dist in (("gtsam", "gtsam"), ("open3d", "open3d"), ("scipy", "scipy"), ("poselib", "poselib"),
                       ("rerun", "rerun-sdk")):
        try:
            out[name] = version(dist)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


# The recorded digests guard against changed or mixed-up input files, not against forgery: xxh3-128 reads a KITTI
# frame's 2.4 MB of files in 0.05 ms where sha256 took 1.3 (of the ~100 ms of CPU a frame costs). Recordings made
# before it hold sha256 prefixes; `file_digest` computes either.
INPUT_HASH = "xxh3_128"


def file_digest(path: str | Path, algorithm: str = INPUT_HASH) -> str:
    """The hex digest of a file's bytes by `algorithm` ("xxh3_128" or "sha256")."""
    if algorithm == "xxh3_128":
        h: Any = xxhash.xxh3_128()
    elif algorithm == "sha256":
        h = hashlib.sha256()
    else:
        raise ValueError(f"unknown input hash {algorithm!r}: this plvo knows xxh3_128 and sha256")
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def encode_inputs(frame: Frame) -> tuple[bytes, bytes]:
    """(PNG of the image, float32 bytes of the scan): lossless, decoded back by `decode_inputs`."""
    ok, png = cv2.imencode(".png", frame.image)
    if not ok:
        raise ValueError(f"frame {frame.index}: the image cannot be encoded as PNG")
    return png.tobytes(), np.ascontiguousarray(frame.scan, np.float32).tobytes()


def decode_inputs(png: bytes, scan: bytes) -> tuple[np.ndarray, np.ndarray]:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    return image, np.frombuffer(scan, np.float32).reshape(-1, 4).copy()
