"""ROS messages (ROS 1 or ROS 2, as rosbags deserialises them) -> plvo's arrays and calibration.

ROS 1 and ROS 2 differ in a few field names (CameraInfo `K` vs `k`); these helpers read either.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from plvo.data.camera_model import CameraModel
from plvo.data.images import decode_compressed, decode_raw
from plvo.data.pointcloud import CloudField, cloud_to_scan
from plvo.errors import CalibrationError
from plvo.geometry import se3

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)


def stamp_ns(msg: Any, fallback_ns: int) -> int:
    """Header stamp in nanoseconds; the bag's receive time when the header is unset (some drivers)."""
    stamp = msg.header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(getattr(stamp, "nanosec", getattr(stamp, "nsec", 0)))
    return ns if ns > 0 else int(fallback_ns)


def image_array(msg: Any, msgtype: str, where: str) -> np.ndarray:
    """Image or CompressedImage -> (H,W) grey or (H,W,3) RGB."""
    if msgtype == COMPRESSED_TYPE:
        return decode_compressed(msg.format, msg.data, where)
    return decode_raw(int(msg.height), int(msg.width), str(msg.encoding), int(msg.step), bool(msg.is_bigendian),
                      msg.data, where)


def cloud_scan(msg: Any, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """PointCloud2 -> (scan (N,4) float32, per-point seconds after the stamp or None)."""
    fields = [CloudField(str(f.name), int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]
    stamp = msg.header.stamp
    stamp_s = int(stamp.sec) + 1e-9 * int(getattr(stamp, "nanosec", getattr(stamp, "nsec", 0)))
    return cloud_to_scan(fields, int(msg.point_step), int(msg.row_step), int(msg.width), int(msg.height),
                         bool(msg.is_bigendian), msg.data, stamp_s, where)


def _field(msg: Any, name: str) -> np.ndarray:
    value = getattr(msg, name, None)
    if value is None:
        value = getattr(msg, name.upper())
    return np.asarray(value, dtype=np.float64).reshape(-1)


def camera_model(msg: Any, where: str) -> CameraModel:
    """CameraInfo -> CameraModel (K, D, R and the rectified matrix from P); `where` names the topic."""
    K = _field(msg, "k")
    if K.size != 9 or abs(K[0]) < 1e-12:
        raise CalibrationError(f"{where}: CameraInfo has no camera matrix (K is all zero)")
    r, p = _field(msg, "r"), _field(msg, "p")
    R = r.reshape(3, 3) if r.size == 9 and abs(r).sum() > 0 else np.eye(3)
    P = p.reshape(3, 4)[:, :3].copy() if p.size == 12 and abs(p[0]) > 1e-12 else None
    model = str(msg.distortion_model or "plumb_bob")
    return CameraModel(width=int(msg.width), height=int(msg.height), K=K.reshape(3, 3), D=_field(msg, "d"),
                       model=model, R=R, P=P)


def _transform_matrix(tf: Any) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    t, q = tf.transform.translation, tf.transform.rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [t.x, t.y, t.z]
    return T


def _strip(frame: str) -> str:
    return frame.lstrip("/")  # ROS 1 tf allowed a leading slash


class StaticTransforms:
    """The /tf_static tree: T_parent_child per edge; `lookup(target, source)` chains them either way."""

    def __init__(self) -> None:
        self._edges: dict[str, dict[str, np.ndarray]] = {}

    def add(self, msg: Any) -> None:
        """One tf2_msgs/TFMessage."""
        for tf in msg.transforms:
            parent, child = _strip(tf.header.frame_id), _strip(tf.child_frame_id)
            T = _transform_matrix(tf)
            self._edges.setdefault(parent, {})[child] = T
            self._edges.setdefault(child, {})[parent] = se3.inv(T)

    @property
    def frames(self) -> list[str]:
        return sorted(self._edges)

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """(4,4) T_target_source (maps points in `source` into `target`), or None when not connected."""
        found = self.chain(target, source)
        return None if found is None else found[0]

    def chain(self, target: str, source: str) -> tuple[np.ndarray, list[str]] | None:
        """(T_target_source, the frames from target to source it passes through), or None when not connected;
        the frames say where a calibration came from (`camera <- base_link <- velodyne`)."""
        target, source = _strip(target), _strip(source)
        if target == source:
            return np.eye(4), [target]
        seen, queue = {target: np.eye(4)}, deque([target])
        parent: dict[str, str] = {}
        while queue:  # breadth first from target; seen[f] = T_target_f
            frame = queue.popleft()
            for nxt, T_frame_nxt in self._edges.get(frame, {}).items():
                if nxt not in seen:
                    seen[nxt], parent[nxt] = seen[frame] @ T_frame_nxt, frame
                    if nxt == source:
                        path = [nxt]
                        while path[-1] != target:
                            path.append(parent[path[-1]])
                        return seen[nxt], path[::-1]
                    queue.append(nxt)
        return None
