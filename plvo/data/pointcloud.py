"""Lidar scans of any source -> the pipeline's (N,4) float32 x,y,z,intensity in the lidar frame.

sensor_msgs/PointCloud2 in any field layout (fields at any offset, any numeric type, either byte order, padded
points and rows, organised clouds with NaN holes); per-point time read when one of the usual fields is present.
Scan files: KITTI .bin (float32 x,y,z,reflectance), .pcd and .ply (through open3d's tensor I/O, which keeps the
intensity attribute).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plvo.errors import DatasetError

log = logging.getLogger(__name__)

# sensor_msgs/PointField datatypes
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INTENSITY_FIELDS = ("intensity", "reflectance", "reflectivity", "i")
# Velodyne/rslidar `time` (float s), Ouster `t` (uint32 ns), Hesai `timestamp` (float64 absolute s), Livox
# `offset_time` (uint32 ns)
TIME_FIELDS = ("time", "t", "timestamp", "time_stamp", "offset_time", "time_offset")
_ABSOLUTE_TIME_S = 1e6  # per-point times above this are absolute (epoch) seconds, not offsets


@dataclass(frozen=True)
class CloudField:
    """One sensor_msgs/PointField, as plain values (ROS 1 and ROS 2 messages alike)."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def cloud_to_scan(fields: list[CloudField], point_step: int, row_step: int, width: int, height: int,
                  big_endian: bool, data: np.ndarray, stamp_s: float, where: str
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """PointCloud2 contents -> (scan (N,4) float32 x,y,z,intensity, per-point seconds after stamp_s (N,) or None).

    Returns with NaN or infinite coordinates are dropped (organised clouds mark holes so). `where` names the topic
    and stamp in errors; an unknown point layout (no x, y, z or a field type outside PointField's) raises one.
    """
    by_name = {f.name: f for f in fields}
    names = ", ".join(f"{f.name}@{f.offset}:{f.datatype}" for f in fields) or "none"
    missing = [axis for axis in "xyz" if axis not in by_name]
    if missing:
        raise DatasetError(f"{where}: unknown point layout, no field {', '.join(missing)} (fields: {names})")
    wanted = ["x", "y", "z"]
    intensity = next((n for n in INTENSITY_FIELDS if n in by_name), None)
    time_name = next((n for n in TIME_FIELDS if n in by_name), None)
    wanted += [n for n in (intensity, time_name) if n is not None]
    order = ">" if big_endian else "<"
    formats = []
    for name in wanted:
        f = by_name[name]
        if f.datatype not in _POINT_FIELD_TYPES:
            raise DatasetError(f"{where}: unknown point layout, field {name!r} has datatype {f.datatype} "
                               f"(PointField types are 1..8)")
        fmt = np.dtype(order + _POINT_FIELD_TYPES[f.datatype])
        if f.offset + fmt.itemsize > point_step:
            raise DatasetError(f"{where}: unknown point layout, field {name!r} at offset {f.offset} does not fit "
                               f"in point_step {point_step}")
        formats.append(fmt)
    dtype = np.dtype({"names": wanted, "formats": formats, "offsets": [by_name[n].offset for n in wanted],
                      "itemsize": point_step})
    buf = np.asarray(data, dtype=np.uint8).reshape(-1)
    if buf.size < row_step * height or row_step < width * point_step:
        raise DatasetError(f"{where}: {buf.size} bytes of data for {width}x{height} points of {point_step} bytes "
                           f"(row_step {row_step})")
    rows = buf[: row_step * height].reshape(height, row_step)[:, : width * point_step]
    points = np.ascontiguousarray(rows).reshape(-1).view(dtype)
    scan = np.empty((len(points), 4), dtype=np.float32)
    for k, axis in enumerate("xyz"):
        scan[:, k] = points[axis]
    scan[:, 3] = points[intensity] if intensity else 0.0
    times = None if time_name is None else _relative_times(points[time_name], stamp_s)
    keep = np.isfinite(scan[:, :3]).all(axis=1)
    if not keep.all():
        scan = scan[keep]
        times = None if times is None else times[keep]
    if len(scan) == 0:
        raise DatasetError(f"{where}: scan has no finite point")
    return scan, times


def _relative_times(values: np.ndarray, stamp_s: float) -> np.ndarray:
    """Per-point time field -> seconds after the scan stamp: integer fields are nanoseconds, floats seconds."""
    if np.issubdtype(values.dtype, np.integer):
        return values.astype(np.float64) * 1e-9
    seconds = values.astype(np.float64)
    if len(seconds) and np.nanmedian(seconds) > _ABSOLUTE_TIME_S:
        seconds = seconds - stamp_s
    return seconds


def read_scan_file(path: Path, frame: int) -> np.ndarray:
    """A scan file (.bin KITTI, .pcd, .ply) -> (N,4) float32 x,y,z,intensity (0 where the file has none)."""
    suffix = path.suffix.lower()
    if suffix == ".bin":
        size = path.stat().st_size if path.is_file() else -1
        if size <= 0 or size % 16:
            raise DatasetError(f"{path}: {size} bytes is not a positive multiple of 16 (float32 x,y,z,reflectance) "
                               f"(frame {frame})")
        try:
            scan = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        except OSError as exc:  # a permission, an I/O error: the file and its frame
            raise DatasetError(f"{path}: unreadable scan (frame {frame}): {exc.strerror or exc}") from None
    elif suffix in (".pcd", ".ply"):
        scan = _read_open3d(path, frame)
    else:
        raise DatasetError(f"{path}: scan format {suffix!r} not supported (.bin, .pcd, .ply) (frame {frame})")
    bad = ~np.isfinite(scan).all(axis=1)
    if bad.any():
        scan = scan[~bad]
    if len(scan) == 0:
        raise DatasetError(f"{path}: scan has no finite point (frame {frame})")
    check_scan_values(scan, path, frame)
    return scan


# No automotive lidar measures beyond a few hundred metres; a file whose points lie past this is not x,y,z in
# metres (float64 or integer data read as float32 give values spread over 1e-30..1e30).
IMPLAUSIBLE_RANGE_M = 1e4
_IMPLAUSIBLE_SHARE = 0.01  # a stray return may be garbage; a whole scan's worth is the wrong kind of file


def check_scan_values(scan: np.ndarray, path: Path | None, frame: int) -> None:
    """Refuse a scan whose coordinates are not plausible metres (DatasetError naming the file and frame)."""
    if len(scan) and scan.min() >= -IMPLAUSIBLE_RANGE_M and scan.max() <= IMPLAUSIBLE_RANGE_M:
        return  # every value near enough (intensities too): two whole-array reductions, 0.5 ms for 124k points
        # where the per-point test below took 5 ms a KITTI frame on the reading thread
    far = np.abs(scan[:, :3]).max(axis=1) > IMPLAUSIBLE_RANGE_M
    share = float(far.mean()) if len(far) else 0.0
    if share <= _IMPLAUSIBLE_SHARE:
        return
    hint = ""
    if scan.dtype == np.float32 and path is not None and str(path).lower().endswith(".bin"):
        hint = "; is it float64? KITTI .bin scans are float32 x,y,z,reflectance"
    raise DatasetError(f"{path}: {100 * share:.0f} % of the points lie beyond {IMPLAUSIBLE_RANGE_M:.0f} m "
                       f"(largest coordinate {float(np.abs(scan[:, :3]).max()):.3g}): not a scan in metres{hint} "
                       f"(frame {frame})")


def _read_open3d(path: Path, frame: int) -> np.ndarray:
    import open3d as o3d  # heavy import, only for these formats

    if not path.is_file():
        raise DatasetError(f"{path}: missing scan (frame {frame})")
    cloud = o3d.t.io.read_point_cloud(Path(path))
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        raise DatasetError(f"{path}: no points read (frame {frame})")
    xyz = cloud.point.positions.numpy().astype(np.float32).reshape(-1, 3)
    scan = np.zeros((len(xyz), 4), dtype=np.float32)
    scan[:, :3] = xyz
    for name in INTENSITY_FIELDS:
        if name in cloud.point:
            scan[:, 3] = cloud.point[name].numpy().reshape(-1)[: len(xyz)]
            break
    return scan


def write_pcd(path: Path, scan: np.ndarray) -> None:
    """(N,4) x,y,z,intensity -> binary PCD (for users converting data and for tests)."""
    scan = np.asarray(scan, dtype=np.float32)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
        f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {len(scan)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(scan)}\n"
        "DATA binary\n"
    )
    Path(path).write_bytes(header.encode() + scan.tobytes())
