"""Test helper: write a ROS 1 or ROS 2 bag (rosbags' writers) from the frames of a plvo dataset.

Stamps are the dataset's times plus BASE_S; scans are stamped SCAN_LAG_S after their image so that pairing is
by nearest stamp, not equality. Calibration goes in as CameraInfo + /tf_static (camera and lidar both hung off
base_link, so the reader must chain two transforms) unless `camera_info=False` / `tf=False`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from plvo.geometry import se3

BASE_S = 1_700_000_000.0
SCAN_LAG_S = 0.012
T_BASE_VELO = np.array([[1.0, 0, 0, 0.3], [0, 1, 0, 0.0], [0, 0, 1, 1.73], [0, 0, 0, 1]])
CLOUD_LAYOUTS = ("xyzi", "padded_time", "ouster")  # and "no_xyz", a layout the reader must refuse


@dataclass(frozen=True)
class BagSpec:
    ros: int = 2  # 1: .bag; 2: folder (sqlite3) or mcap
    storage: str = "sqlite3"  # ROS 2: sqlite3 or mcap
    compressed: bool = False  # CompressedImage (PNG, lossless)
    cloud_layout: str = "xyzi"  # xyzi: x,y,z,intensity float32; padded_time: velodyne-style with float `time`
    #                             and a ring; ouster: uint32 nanosecond `t` and intensity as float at odd offsets
    camera_info: bool = True
    tf: bool = True
    image_topic: str = "/camera/image_raw"
    cloud_topic: str = "/velodyne_points"
    extra_image_topic: str | None = None  # a second image topic (for the "two candidates" error)
    images: bool = True  # False: no image topic at all
    drop_scans: tuple[int, ...] = ()  # frames whose scan is not written (a lidar dropout)
    distortion: tuple[float, ...] = ()  # CameraInfo D (plumb_bob); the images must have been taken so
    scan_lag_s: float = SCAN_LAG_S


def _typestore(ros: int):
    ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


class _Msgs:
    def __init__(self, ros: int) -> None:
        self.ros, self.ts = ros, _typestore(ros)
        self.T = self.ts.types

    def header(self, t_s: float, frame: str):
        sec = int(np.floor(t_s))
        stamp = self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t_s - sec) * 1e9)))
        H = self.T["std_msgs/msg/Header"]
        return H(seq=0, stamp=stamp, frame_id=frame) if self.ros == 1 else H(stamp=stamp, frame_id=frame)

    def image(self, t_s: float, image: np.ndarray, compressed: bool):
        h = self.header(t_s, "camera")
        if compressed:
            ok, buf = cv2.imencode(".png", image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            assert ok
            return self.T["sensor_msgs/msg/CompressedImage"](header=h, format="png", data=buf.reshape(-1))
        enc, step = ("mono8", image.shape[1]) if image.ndim == 2 else ("rgb8", 3 * image.shape[1])
        return self.T["sensor_msgs/msg/Image"](header=h, height=image.shape[0], width=image.shape[1], encoding=enc,
                                               is_bigendian=0, step=step, data=image.reshape(-1).copy())

    def cloud(self, t_s: float, scan: np.ndarray, layout: str):
        PF = self.T["sensor_msgs/msg/PointField"]
        n = len(scan)
        if layout == "xyzi":
            names, offsets, types, step = ["x", "y", "z", "intensity"], [0, 4, 8, 12], [7, 7, 7, 7], 16
        elif layout == "no_xyz":  # a range image: no cartesian fields
            names, offsets, types, step = ["x", "range_m", "azimuth", "intensity"], [0, 4, 8, 12], [7, 7, 7, 7], 16
        elif layout == "padded_time":  # PCL PointXYZIR + time: x y z (pad) intensity ring (pad) time
            names, offsets, types, step = ["x", "y", "z", "intensity", "ring", "time"], [0, 4, 8, 16, 20, 24], \
                [7, 7, 7, 7, 4, 7], 32
        else:  # ouster: x y z (pad) t intensity reflectivity ring, t in ns
            names, offsets, types, step = ["x", "y", "z", "t", "intensity", "ring"], [0, 4, 8, 16, 20, 28], \
                [7, 7, 7, 6, 7, 4], 48
        np_types = {4: "<u2", 6: "<u4", 7: "<f4"}
        rec = np.zeros(n, dtype=np.dtype({"names": names, "formats": [np_types[t] for t in types],
                                          "offsets": offsets, "itemsize": step}))
        for k, name in enumerate(("x", "y", "z", "intensity")):
            if name in names:
                rec[name] = scan[:, k]
        azimuth = np.arctan2(scan[:, 1], scan[:, 0])
        fraction = (np.pi - azimuth) / (2 * np.pi)  # sweep time, 0..0.1 s
        if "time" in names:
            rec["time"] = 0.1 * fraction
        if "t" in names:
            rec["t"] = np.round(1e8 * fraction).astype(np.uint32)
        fields = [PF(name=nm, offset=o, datatype=t, count=1) for nm, o, t in zip(names, offsets, types)]
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self.header(t_s, "velodyne"), height=1, width=n, fields=fields, is_bigendian=False,
            point_step=step, row_step=step * n, data=rec.view(np.uint8).reshape(-1).copy(), is_dense=True)

    def camera_info(self, t_s: float, calib, distortion=()):
        K = np.asarray(calib.K, dtype=np.float64)
        P = np.zeros((3, 4))
        P[:, :3] = K
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                         do_rectify=False)
        D = np.asarray(distortion, dtype=np.float64) if len(distortion) else np.zeros(5)
        fields = {"d": D, "k": K.reshape(-1), "r": np.eye(3).reshape(-1), "p": P.reshape(-1)}
        if self.ros == 1:
            fields = {k.upper(): v for k, v in fields.items()}
        return self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(t_s, "camera"), height=calib.height, width=calib.width, distortion_model="plumb_bob",
            binning_x=0, binning_y=0, roi=roi, **fields)

    def tf_static(self, t_s: float, T_cam_velo: np.ndarray):
        T_base_cam = T_BASE_VELO @ se3.inv(T_cam_velo)
        out = []
        for child, T in (("velodyne", T_BASE_VELO), ("camera", T_base_cam)):
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            tr = self.T["geometry_msgs/msg/Transform"](
                translation=self.T["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=self.T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
            out.append(self.T["geometry_msgs/msg/TransformStamped"](header=self.header(t_s, "base_link"),
                                                                    child_frame_id=child, transform=tr))
        return self.T["tf2_msgs/msg/TFMessage"](transforms=out)


def write_bag(path: Path, dataset, spec: BagSpec = BagSpec(), color: bool = False) -> Path:
    """Write every frame of `dataset` into a bag at `path` (.bag for ROS 1; a folder, or .mcap, for ROS 2)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    m = _Msgs(spec.ros)
    if spec.ros == 1:
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if spec.storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    image_type = "sensor_msgs/msg/CompressedImage" if spec.compressed else "sensor_msgs/msg/Image"
    topics = [(spec.image_topic, image_type)] if spec.images else []
    topics.append((spec.cloud_topic, "sensor_msgs/msg/PointCloud2"))
    if spec.extra_image_topic:
        topics.append((spec.extra_image_topic, image_type))
    if spec.camera_info:
        topics.append((spec.image_topic.rsplit("/", 1)[0] + "/camera_info", "sensor_msgs/msg/CameraInfo"))
    if spec.tf:
        topics.append(("/tf_static", "tf2_msgs/msg/TFMessage"))
    serialize = m.ts.serialize_ros1 if spec.ros == 1 else m.ts.serialize_cdr
    with writer:
        conns = {t: writer.add_connection(t, ty, typestore=m.ts) for t, ty in topics}

        def put(topic: str, t_s: float, msg) -> None:
            writer.write(conns[topic], int(round(t_s * 1e9)), serialize(msg, msg.__msgtype__))

        t0 = BASE_S + float(dataset[0].time)
        if spec.tf:
            put("/tf_static", t0, m.tf_static(t0, dataset.calib.T_cam_velo))
        for i in range(len(dataset)):
            frame = dataset[i]
            t = BASE_S + float(frame.time)
            image = frame.color if (color and frame.color is not None) else frame.image
            if spec.images:
                put(spec.image_topic, t, m.image(t, image, spec.compressed))
            if spec.extra_image_topic:
                put(spec.extra_image_topic, t, m.image(t, image, spec.compressed))
            if spec.camera_info:
                put(spec.image_topic.rsplit("/", 1)[0] + "/camera_info", t,
                    m.camera_info(t, dataset.calib, spec.distortion))
            if i not in spec.drop_scans:
                put(spec.cloud_topic, t + spec.scan_lag_s, m.cloud(t + spec.scan_lag_s, frame.scan, spec.cloud_layout))
    if spec.ros == 2 and spec.storage == "mcap":
        return next(Path(path).glob("*.mcap"))  # the bare .mcap file, as a user may have it
    return Path(path)


def distort_image(ideal: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The image a lens with distortion D would have taken of the ideal pinhole image (same K)."""
    h, w = ideal.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=-1).reshape(-1, 1, 2)
    undist = cv2.undistortPoints(pts, K, D, None, None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-6))
    maps = undist.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(ideal, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)
