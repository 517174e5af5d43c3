"""ROS message contents -> plvo arrays: image encodings, PointCloud2 layouts, CameraInfo and TF."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from plvo.data.images import decode_compressed, decode_raw, split_gray_color, to_gray
from plvo.data.pointcloud import CloudField, cloud_to_scan
from plvo.errors import DatasetError

RNG = np.random.default_rng(5)
RGB = RNG.integers(0, 256, (6, 5, 3), dtype=np.uint8)


def _raw(image: np.ndarray, pad: int = 0) -> tuple[int, np.ndarray]:
    """Row-major bytes of image with `pad` bytes at the end of each row -> (step, data)."""
    rows = image.reshape(image.shape[0], -1).view(np.uint8)
    data = np.concatenate([rows, np.zeros((rows.shape[0], pad), np.uint8)], axis=1)
    return data.shape[1], data.reshape(-1)


@pytest.mark.parametrize("encoding, make", [
    ("rgb8", lambda: RGB),
    ("bgr8", lambda: RGB[:, :, ::-1].copy()),
    ("rgba8", lambda: np.dstack([RGB, np.full(RGB.shape[:2], 255, np.uint8)])),
    ("bgra8", lambda: np.dstack([RGB[:, :, ::-1], np.zeros(RGB.shape[:2], np.uint8)])),
])
def test_colour_encodings_give_rgb(encoding, make):
    step, data = _raw(make(), pad=3)  # padded rows, as some drivers send
    out = decode_raw(6, 5, encoding, step, False, data, "t")
    np.testing.assert_array_equal(out, RGB)
    gray, color = split_gray_color(out)
    np.testing.assert_array_equal(color, RGB)
    np.testing.assert_array_equal(gray, to_gray(RGB))


def test_mono16_big_endian_and_bayer():
    values = RNG.integers(0, 65536, (4, 6), dtype=np.uint16)
    step, data = _raw(values.astype(">u2"))
    np.testing.assert_array_equal(decode_raw(4, 6, "mono16", step, True, data, "t"), values)
    np.testing.assert_array_equal(split_gray_color(values)[0], (values >> 8).astype(np.uint8))
    bayer = RNG.integers(0, 256, (8, 8), dtype=np.uint8)
    out = decode_raw(8, 8, "bayer_rggb8", 8, False, bayer.reshape(-1), "t")
    np.testing.assert_array_equal(out, cv2.cvtColor(bayer, cv2.COLOR_BayerBG2RGB))
    with pytest.raises(DatasetError, match=r"/cam at 1.5 s: image encoding 'yuv422' not supported"):
        decode_raw(2, 2, "yuv422", 4, False, np.zeros(8, np.uint8), "/cam at 1.5 s")
    with pytest.raises(DatasetError, match=r"t: 10 bytes of data for a 5x6 rgb8 image with step 15"):
        decode_raw(6, 5, "rgb8", 15, False, np.zeros(10, np.uint8), "t")


def test_compressed_png_and_jpeg():
    ok, png = cv2.imencode(".png", RGB[:, :, ::-1])
    np.testing.assert_array_equal(decode_compressed("png", png.reshape(-1), "t"), RGB)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(RGB, cv2.COLOR_RGB2GRAY))
    assert decode_compressed("jpeg", jpg.reshape(-1), "t").ndim == 2
    with pytest.raises(DatasetError, match="cannot decode compressed image"):
        decode_compressed("png", np.zeros(10, np.uint8), "t")


def test_pointcloud_big_endian_organised_with_holes():
    pts = RNG.normal(0, 10, (2, 3, 5)).astype(np.float32)  # 2 rows of 3 points: x y z intensity time
    pts[1, 2, :3] = np.nan  # an organised cloud's hole
    dtype = np.dtype({"names": ["x", "y", "z", "intensity", "time"], "formats": [">f4"] * 3 + [">f8", ">f4"],
                      "offsets": [0, 4, 8, 16, 24], "itemsize": 32})
    rec = np.zeros((2, 3), dtype)
    for k, n in enumerate(dtype.names):
        rec[n] = pts[..., k]
    row = rec.view(np.uint8).reshape(2, -1)
    data = np.concatenate([row, np.zeros((2, 8), np.uint8)], axis=1).reshape(-1)  # row padding
    fields = [CloudField("x", 0, 7), CloudField("y", 4, 7), CloudField("z", 8, 7), CloudField("intensity", 16, 8),
              CloudField("time", 24, 7)]
    scan, times = cloud_to_scan(fields, 32, 3 * 32 + 8, 3, 2, True, data, 100.0, "t")
    want = pts.reshape(-1, 5)[:5]
    np.testing.assert_allclose(scan, want[:, :4], rtol=1e-6)
    np.testing.assert_allclose(times, want[:, 4], rtol=1e-6)


def test_pointcloud_absolute_and_nanosecond_times_and_bad_layouts():
    xyz = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ts", "<f8")])
    xyz["x"] = [1, 2, 3, 4]
    xyz["ts"] = 1_700_000_000.0 + np.array([0.0, 0.01, 0.02, 0.03])  # Hesai: absolute seconds
    fields = [CloudField("x", 0, 7), CloudField("y", 4, 7), CloudField("z", 8, 7), CloudField("timestamp", 12, 8)]
    scan, times = cloud_to_scan(fields, 20, 80, 4, 1, False, xyz.view(np.uint8), 1_700_000_000.0, "t")
    np.testing.assert_allclose(times, [0.0, 0.01, 0.02, 0.03], atol=1e-6)
    assert (scan[:, 3] == 0).all()  # no intensity field
    with pytest.raises(DatasetError, match=r"/points at 2.0 s: unknown point layout, no field z \(fields: x@0:7"):
        cloud_to_scan(fields[:2], 20, 80, 4, 1, False, xyz.view(np.uint8), 0.0, "/points at 2.0 s")
    with pytest.raises(DatasetError, match=r"field 'x' has datatype 9"):
        cloud_to_scan([CloudField("x", 0, 9), *fields[1:]], 20, 80, 4, 1, False, xyz.view(np.uint8), 0.0, "t")
    with pytest.raises(DatasetError, match=r"field 'timestamp' at offset 16 does not fit in point_step 20"):
        cloud_to_scan([*fields[:3], CloudField("timestamp", 16, 8)], 20, 80, 4, 1, False, xyz.view(np.uint8), 0.0,
                      "t")
