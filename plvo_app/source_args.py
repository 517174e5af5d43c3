"""The options every command that opens a dataset shares: which KITTI camera, which bag topics, which calibration."""

from __future__ import annotations

import argparse

from plvo.data.dataset import SourceOptions


def add_source_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("data source (KITTI camera; ROS bag or plain folder given as --root)")
    g.add_argument("--camera", type=int, default=0, choices=(0, 1, 2, 3),
                   help="KITTI camera: 0/1 grey left/right, 2/3 colour left/right (grey for the pipeline, colour "
                        "kept for the viewers); default 0")
    g.add_argument("--image-topic", default=None, help="bag: image topic (Image or CompressedImage); default the "
                   "only one")
    g.add_argument("--cloud-topic", default=None, help="bag: PointCloud2 topic; default the only one")
    g.add_argument("--calib", default=None, metavar="FILE.yaml",
                   help="calibration YAML (camera + T_cam_lidar, see README); default: the bag's CameraInfo and "
                        "/tf_static, or the folder's calib.yaml")
    g.add_argument("--max-pair-dt", type=float, default=SourceOptions.max_pair_dt, metavar="S",
                   help="bag: seconds an image and its scan may be apart (default %(default)s)")
    g.add_argument("--lidar-elevation-offset", type=float, default=None, metavar="DEG",
                   help="bag/folder: the lidar's vertical-angle error in degrees (KITTI's HDL-64E: 0.205); default "
                        "the calibration YAML's, else 0")
    g.add_argument("--beams", type=int, default=None, choices=(8, 16, 32, 64),
                   help="resample the 64-beam scans to this many beams by elevation ring (a sparser lidar)")


def source_options(args: argparse.Namespace) -> SourceOptions:
    return SourceOptions(image_topic=args.image_topic, cloud_topic=args.cloud_topic, calib=args.calib,
                         max_pair_dt=args.max_pair_dt, lidar_elevation_offset_deg=args.lidar_elevation_offset,
                         beams=args.beams)
