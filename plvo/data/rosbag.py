"""ROS 1 and ROS 2 bags as datasets, read without ROS by `rosbags` (0.11, typestore API).

A bag is a `.bag` file (ROS 1), a ROS 2 folder with metadata.yaml (sqlite3 or mcap storage) or a bare `.mcap`.
One image topic (sensor_msgs Image or CompressedImage) and one cloud topic (PointCloud2) are read: the ones named
in SourceOptions, or the only one of each kind. Each image is paired with the scan nearest in header stamp within
SourceOptions.max_pair_dt. Calibration comes from a YAML file (plvo.data.calib_yaml) or from the bag: CameraInfo
(the one beside the image topic) and the static transform (/tf_static) between the image's and the cloud's frames;
one INFO line for K and one for T_cam_lidar say which file, topic, message and frames they came from.
Distorted images are rectified. The bag is indexed once (stamps of every message read); frames are read lazily.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from plvo.data.calib_check import check_calibration
from plvo.data.calib_yaml import read_calib_yaml
from plvo.data.dataset import FrameSelection, SelectedFrames, SourceOptions, select_frames
from plvo.data.images import split_gray_color
from plvo.data.ros_messages import (
    CLOUD_TYPE,
    IMAGE_TYPES,
    INFO_TYPE,
    TF_TYPE,
    StaticTransforms,
    camera_model,
    cloud_scan,
    image_array,
    stamp_ns,
)
from plvo.data.trajectory import pair_nearest
from plvo.errors import CalibrationError, DatasetError
from plvo.types import Frame

if TYPE_CHECKING:
    from plvo.data.camera_model import CameraModel, Rectifier
    from plvo.types import Calibration

log = logging.getLogger(__name__)

TF_STATIC_TOPICS = ("/tf_static", "tf_static")


def is_bag(path: Path | str | None) -> bool:
    """Whether `path` is a ROS 1 bag, a bare .mcap or a ROS 2 bag folder."""
    if path is None:
        return False
    path = Path(path)
    if path.is_file():
        return path.suffix in (".bag", ".mcap", ".db3")
    return (path / "metadata.yaml").is_file()


@dataclass(frozen=True)
class _Ref:
    """Where one message is: bag receive time, its rank among the topic's messages at that time, header stamp."""

    bag_ns: int
    rank: int
    stamp_ns: int


def _open_reader(path: Path) -> Any:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    paths = [path]
    if path.suffix == ".db3":  # a ROS 2 sqlite file given instead of its folder
        paths = [path.parent]
    reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own reader errors, KeyError and struct errors on bad files
        raise DatasetError(f"{path}: cannot read bag ({type(exc).__name__}: {exc})") from None
    return reader


def _choose(path: Path, connections: list, wanted: str | None, types: tuple[str, ...], kind: str, option: str
            ) -> tuple[str, str]:
    """(topic, msgtype) chosen: the named topic, else the only one of `types`."""
    topics = {c.topic: c for c in connections}
    if wanted is not None:
        if wanted not in topics:
            raise DatasetError(f"{path}: no topic {wanted!r} ({option}); topics: {', '.join(sorted(topics))}")
        if topics[wanted].msgtype not in types:
            raise DatasetError(f"{path}: topic {wanted!r} is {topics[wanted].msgtype}, not {' or '.join(types)}")
        return wanted, topics[wanted].msgtype
    found = sorted({c.topic for c in connections if c.msgtype in types})
    if not found:
        listing = ", ".join(f"{c.topic} ({c.msgtype})" for c in connections) or "none"
        raise DatasetError(f"{path}: no {kind} topic ({' or '.join(types)}); topics: {listing}")
    if len(found) > 1:
        raise DatasetError(f"{path}: {len(found)} {kind} topics ({', '.join(found)}): choose one with {option}")
    return found[0], topics[found[0]].msgtype


def _camera_info(connections: list, image_topic: str) -> str | None:
    """The CameraInfo topic beside the image topic (same namespace, or one up for image_raw/compressed), else the
    only one, else None."""
    infos = sorted({c.topic for c in connections if c.msgtype == INFO_TYPE})
    namespace = image_topic.rsplit("/", 1)[0]
    for topic in infos:
        if topic.rsplit("/", 1)[0] == namespace or topic == image_topic.rsplit("/", 2)[0] + "/camera_info":
            return topic
    return infos[0] if len(infos) == 1 else None


class RosbagDataset(SelectedFrames):
    """A ROS 1 / ROS 2 bag as a Dataset: paired image + scan frames, no ground truth."""

    name = "rosbag"
    _gt = None  # a bag carries no ground truth

    def __init__(self, path: str | Path, frames: FrameSelection = None, options: SourceOptions | None = None) -> None:
        self.path = Path(path)
        opts = options or SourceOptions()
        if not self.path.exists():
            raise DatasetError(f"{self.path}: no such bag")
        self.sequence = self.path.stem if self.path.is_file() else self.path.name
        self._reader_pid: int | None = None
        self._reader_obj = None
        reader = self._reader()
        conns = list(reader.connections)
        self.image_topic, self._image_type = _choose(self.path, conns, opts.image_topic, IMAGE_TYPES, "image",
                                                     "--image-topic")
        self.cloud_topic, _ = _choose(self.path, conns, opts.cloud_topic, (CLOUD_TYPE,), "point cloud",
                                      "--cloud-topic")
        self._info_topics = sorted({c.topic for c in conns if c.msgtype == INFO_TYPE})
        images, scans, first = self._index(reader, _camera_info(conns, self.image_topic))
        self._pair(images, scans, opts.max_pair_dt)
        selected = select_frames(frames, len(self._pairs), f"bag {self.path} ({len(self._pairs)} paired frames)")
        self._frames = selected
        self.calib, self._rectify = self._calibration(opts, first)
        self._times = np.array([1e-9 * self._pairs[k][0].stamp_ns for k in selected])
        log.info("%s: %d frames of %s + %s, %dx%d", self.path, len(selected), self.image_topic,
                 self.cloud_topic, self.calib.width, self.calib.height)

    # --- indexing ---------------------------------------------------------------------------------------------

    def _index(self, reader: Any, info_topic: str | None) -> tuple[list[_Ref], list[_Ref], dict[str, object]]:
        images, scans = [], []
        ranks: dict[tuple[str, int], int] = {}
        self._info, self._tf = None, StaticTransforms()
        self._info_topic, self._info_stamp_ns, self._info_count = info_topic, 0, 0
        first: dict[str, object] = {}
        wanted = [c for c in reader.connections if c.topic in (self.image_topic, self.cloud_topic, info_topic)
                  or (c.msgtype == TF_TYPE and c.topic in TF_STATIC_TOPICS)]
        for conn, bag_ns, raw in reader.messages(connections=wanted):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:  # rosbags' deserialisation errors
                raise DatasetError(f"{self.path}: cannot decode {conn.topic} message at {bag_ns * 1e-9:.6f} s "
                                   f"({exc})") from None
            if conn.msgtype == TF_TYPE:
                self._tf.add(msg)
                continue
            if conn.topic == info_topic:
                if self._info is None:
                    self._info, self._info_stamp_ns = msg, stamp_ns(msg, bag_ns)
                self._info_count += 1
                continue
            key = (conn.topic, bag_ns)
            ranks[key] = ranks.get(key, -1) + 1
            ref = _Ref(bag_ns, ranks[key], stamp_ns(msg, bag_ns))
            if conn.topic == self.image_topic:
                images.append(ref)
                first.setdefault("image", msg)
            else:
                scans.append(ref)
                first.setdefault("cloud", msg)
        if not images:
            raise DatasetError(f"{self.path}: topic {self.image_topic} has no messages")
        if not scans:
            raise DatasetError(f"{self.path}: topic {self.cloud_topic} has no messages")
        return images, scans, first

    def _pair(self, images: list[_Ref], scans: list[_Ref], max_dt: float) -> None:
        images = sorted(images, key=lambda r: r.stamp_ns)
        scans = sorted(scans, key=lambda r: r.stamp_ns)
        image_ns = np.array([r.stamp_ns for r in images], dtype=np.int64)
        scan_ns = np.array([r.stamp_ns for r in scans], dtype=np.int64)
        nearest, ok = pair_nearest(image_ns, scan_ns, int(round(max_dt * 1e9)))
        if not ok.any():
            i = int(np.argmin(np.abs(scan_ns[nearest] - image_ns)))
            raise DatasetError(
                f"{self.path}: no image on {self.image_topic} has a scan on {self.cloud_topic} within "
                f"{max_dt:g} s: closest pair is image stamp {image_ns[i] * 1e-9:.6f} s and scan stamp "
                f"{scan_ns[nearest[i]] * 1e-9:.6f} s (--max-pair-dt raises the limit)")
        if not ok.all():
            bad = int(np.flatnonzero(~ok)[0])
            log.warning("%s: %d of %d images have no scan within %g s and are skipped (first: image stamp %.6f s, "
                        "nearest scan %.6f s)", self.path, int((~ok).sum()), len(ok), max_dt, image_ns[bad] * 1e-9,
                        scan_ns[nearest[bad]] * 1e-9)
        self._pairs = [(images[i], scans[int(nearest[i])]) for i in np.flatnonzero(ok)]

    def _calibration(self, opts: SourceOptions, first: dict) -> tuple[Calibration, Rectifier | None]:
        image = image_array(first["image"], self._image_type, f"{self.path} {self.image_topic}")
        height, width = image.shape[:2]
        if opts.calib is not None:
            cf = read_calib_yaml(opts.calib)
            camera, T_cam_lidar, offset, source = cf.camera, cf.T_cam_lidar, cf.elevation_offset_deg, opts.calib
            has_own = self._info is not None or bool(self._tf.frames)
            unused = "; the bag's own CameraInfo and /tf_static not used" if has_own else ""
            log.info("calibration: K from %s (--calib)%s", opts.calib, unused)
            log.info("calibration: T_cam_lidar from %s (--calib)%s", opts.calib, unused)
        else:
            camera, T_cam_lidar = self._bag_calibration(first)
            offset, source = 0.0, f"{self.path} CameraInfo"
        if (camera.width, camera.height) != (width, height):
            raise CalibrationError(f"{source}: calibration is for {camera.width}x{camera.height} images, but "
                                   f"{self.image_topic} has {width}x{height}")
        if opts.lidar_elevation_offset_deg is not None:
            offset = opts.lidar_elevation_offset_deg
        return check_calibration(camera.calibration(T_cam_lidar, offset), str(source)), camera.rectifier()

    def _bag_calibration(self, first: dict) -> tuple[CameraModel, np.ndarray]:
        if self._info is None:
            others = ", ".join(self._info_topics)
            which = f"none of the CameraInfo topics ({others}) is beside it" if others else "no CameraInfo topic"
            raise CalibrationError(f"{self.path}: no calibration: no CameraInfo topic for {self.image_topic} "
                                   f"({which}); give a calibration YAML with --calib")
        camera = camera_model(self._info, f"{self.path} CameraInfo")
        cam_frame = self._info.header.frame_id or first["image"].header.frame_id
        cam_from = "CameraInfo" if self._info.header.frame_id else f"{self.image_topic} (the CameraInfo names none)"
        lidar_frame = first["cloud"].header.frame_id
        found = self._tf.chain(cam_frame, lidar_frame)
        if found is None:
            frames = ", ".join(self._tf.frames) or "none"
            raise CalibrationError(f"{self.path}: no calibration: no static transform between camera frame "
                                   f"{cam_frame!r} and lidar frame {lidar_frame!r} on /tf_static (frames: {frames}); "
                                   "give a calibration YAML with --calib")
        T, path = found
        # a bag's CameraInfo may change over the bag (a recalibration) and /tf_static may hold several trees: say
        # which message and which edges the run took
        log.info("calibration: K from %s (the first of its %d messages, stamp %.6f s%s)", self._info_topic,
                 self._info_count, 1e-9 * self._info_stamp_ns,
                 f", {camera.model} distortion, rectified" if camera.needs_rectification else "")
        log.info("calibration: T_cam_lidar from /tf_static %s (camera frame %r from %s, lidar frame %r from %s)",
                 " <- ".join(path), cam_frame, cam_from, lidar_frame, self.cloud_topic)
        return camera, T

    # --- reading ----------------------------------------------------------------------------------------------

    def _reader(self) -> Any:
        if self._reader_obj is None or self._reader_pid != os.getpid():
            self._reader_obj, self._reader_pid = _open_reader(self.path), os.getpid()
        return self._reader_obj

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_reader_obj"], state["_reader_pid"] = None, None  # reopened where it is used
        return state

    def close(self) -> None:
        if self._reader_obj is not None and self._reader_pid == os.getpid():
            self._reader_obj.close()
        self._reader_obj = None

    def _message(self, topic: str, ref: _Ref) -> object:
        reader = self._reader()
        conns = [c for c in reader.connections if c.topic == topic]
        for k, (conn, _, raw) in enumerate(reader.messages(connections=conns, start=ref.bag_ns, stop=ref.bag_ns + 1)):
            if k == ref.rank:
                return reader.deserialize(raw, conn.msgtype)
        raise DatasetError(f"{self.path}: {topic} message at {ref.bag_ns * 1e-9:.6f} s vanished from the bag")

    def __getitem__(self, i: int) -> Frame:
        k = self._frames[self._position(i)]
        image_ref, scan_ref = self._pairs[k]
        where = f"{self.path} {self.image_topic} at stamp {image_ref.stamp_ns * 1e-9:.6f} s (frame {k})"
        raw = image_array(self._message(self.image_topic, image_ref), self._image_type, where)
        if raw.shape[:2] != (self.calib.height, self.calib.width):
            raise DatasetError(f"{where}: image is {raw.shape[1]}x{raw.shape[0]}, the calibration's "
                               f"{self.calib.width}x{self.calib.height}")
        if self._rectify is not None:
            raw = self._rectify(raw)
        gray, color = split_gray_color(raw)
        cloud_where = f"{self.path} {self.cloud_topic} at stamp {scan_ref.stamp_ns * 1e-9:.6f} s (frame {k})"
        scan, scan_time = cloud_scan(self._message(self.cloud_topic, scan_ref), cloud_where)
        if scan_time is not None:  # after the cloud's stamp -> after the frame's time (the image's stamp)
            scan_time = scan_time + 1e-9 * (scan_ref.stamp_ns - image_ref.stamp_ns)
        # drivers that stamp each return deliver it in the sensor frame at that time (Velodyne, Ouster, Hesai)
        return Frame(index=k, time=1e-9 * image_ref.stamp_ns, image=gray, scan=scan, calib=self.calib,
                     gt_T_world_cam=None, color=color, scan_time=scan_time, scan_compensated=scan_time is None)


