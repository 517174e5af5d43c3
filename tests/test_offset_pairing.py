"""A stated camera-lidar time offset pairs each image with the scan taken nearest its instant
(plvo.data.offset_pairing); the tracker moves the scan by what is left."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.data.offset_pairing import OffsetPaired, nearest_scans
from plvo.types import Calibration, Frame

CALIB = Calibration(K=np.eye(3), T_cam_velo=np.eye(4), width=4, height=4)


class Numbered:
    """Frames at 10 Hz whose scan and image are filled with their position; counts the reads."""

    name, sequence, calib = "numbered", "00", CALIB

    def __init__(self, n: int, times: np.ndarray | None = None):
        self.times = np.arange(n) * 0.1 if times is None else times
        self.reads: list[int] = []
        self.scan_reads: list[int] = []

    def __len__(self) -> int:
        return len(self.times)

    def __getitem__(self, i: int) -> Frame:
        self.reads.append(i)
        return Frame(index=100 + i, time=float(self.times[i]), image=np.full((4, 4), i, np.uint8),
                     scan=np.full((3, 4), i, np.float32), calib=CALIB)

    def load_timed_scan(self, i: int):
        self.scan_reads.append(i)
        return np.full((3, 4), i, np.float32), None


@pytest.mark.parametrize("offset, scan_of, delay", [
    (0.1, [0, 0, 1, 2, 3], [0.1, 0, 0, 0, 0]),  # a frame late: the previous image's scan; the first keeps its own
    (-0.1, [1, 2, 3, 4, 4], [0, 0, 0, 0, -0.1]),  # a frame early
    (0.04, [0, 1, 2, 3, 4], [0.04] * 5),  # under half a frame: paired as given, the scan moved by all of it
    (0.16, [0, 0, 0, 1, 2], [0.16, 0.06, -0.04, -0.04, -0.04]),  # two frames late less 40 ms
])
def test_each_image_gets_the_scan_taken_nearest_its_instant(offset, scan_of, delay):
    q, d = nearest_scans(np.arange(5) * 0.1, offset)
    assert q.tolist() == scan_of
    np.testing.assert_allclose(d, delay, atol=1e-12)


def test_frames_carry_the_paired_scan_and_what_is_left_of_the_offset():
    ds = Numbered(6)
    paired = OffsetPaired(ds, 0.1)
    frames = [paired[i] for i in range(len(paired))]
    assert [f.index for f in frames] == [100 + i for i in range(6)]  # the images' frames, in order
    assert [int(f.image[0, 0]) for f in frames] == list(range(6))
    assert [int(f.scan[0, 0]) for f in frames] == [0, 0, 1, 2, 3, 4]
    assert [f.scan_delay_s for f in frames] == [0.1, 0, 0, 0, 0, 0]
    assert ds.reads == list(range(6)) and ds.scan_reads == []  # in order, each scan read once, with its image
    assert paired.calib is CALIB and len(paired) == 6  # the rest is the wrapped dataset's


def test_a_scan_read_alone_where_its_image_was_not_read_before():
    ds = Numbered(5)
    paired = OffsetPaired(ds, -0.1)  # each image wants the next frame's scan
    assert int(paired[2].scan[0, 0]) == 3 and ds.scan_reads == [3]


def test_a_residual_under_two_milliseconds_is_not_moved_for():
    times = np.array([0.0, 0.1003, 0.1998, 0.3001])  # a real clock's jitter
    paired = OffsetPaired(Numbered(4, times), 0.1)
    assert [paired[i].scan_delay_s for i in range(4)] == [0.1, 0.0, 0.0, 0.0]
