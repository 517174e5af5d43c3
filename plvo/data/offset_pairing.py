"""Images paired with the scans a stated camera-lidar time offset says were taken at their instants.

A source pairs each image with a scan: by frame number (KITTI) or by nearest stamp (a bag, a folder). When the
scans are taken `offset_s` after the images they are paired with (a driver's clock, a pairing a frame off), the scan
of the image at time t is the one taken nearest t: the scan paired with the image nearest t - offset_s. Re-paired so,
what is left of the offset (under half a frame interval) is small, and the tracker moves each scan by it with the
motion model (Frame.scan_delay_s, plvo.tracking.frontend) instead of by the whole offset (the looping town with its
scans a frame late, 60 frames: ATE 0.0168 m re-paired, 0.025 m each scan moved by the whole 0.1 s, 0.0170 m with
the scans paired right; tests/test_time_offset.py).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from plvo.types import Frame

_NEGLIGIBLE_S = 0.002


def nearest_scans(times: np.ndarray, offset_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(len,) image times (s), the offset -> (positions of each image's scan (len,), each scan's delay after its
    image (s, (len,))): the scan paired with position q is taken at times[q] + offset_s; each image gets the one
    taken nearest its own time."""
    t = np.asarray(times, float)
    if not len(t):
        return np.zeros(0, int), np.zeros(0)
    taken = t + offset_s
    order = np.argsort(taken, kind="stable")
    at = np.clip(np.searchsorted(taken[order], t), 1, max(len(t) - 1, 1))
    before, after = order[at - 1], order[np.minimum(at, len(t) - 1)]
    scan_of = np.where(np.abs(taken[before] - t) <= np.abs(taken[after] - t), before, after)
    return scan_of, taken[scan_of] - t


class OffsetPaired:
    """A Dataset whose frames carry the scan taken nearest their image's instant under a stated offset (every other
    attribute is the wrapped dataset's)."""

    def __init__(self, dataset, offset_s: float) -> None:
        self._dataset, self.offset_s = dataset, float(offset_s)
        self._scan_of, self._delay = nearest_scans(np.asarray(dataset.times, float), self.offset_s)
        # what is left under 2 ms (3 cm at 15 m/s) is not worth moving a scan for (15-25 ms a keyframe's scan)
        self._delay[np.abs(self._delay) < _NEGLIGIBLE_S] = 0.0
        self._held: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}  # scans read for another frame, by position

    def __getattr__(self, name: str):
        if name == "_dataset":  # not set yet (unpickling)
            raise AttributeError(name)
        return getattr(self._dataset, name)

    def __len__(self) -> int:
        return len(self._dataset)

    @property
    def scan_positions(self) -> np.ndarray:
        """(len,) the position whose scan each frame carries."""
        return self._scan_of.copy()

    def __getitem__(self, i: int) -> Frame:
        frame = self._dataset[i]
        p = i % len(self)
        q = int(self._scan_of[p])
        self._hold(p, (frame.scan, frame.scan_time))  # the next frame's, when its image's scan is this one
        if q == p:
            return replace(frame, scan_delay_s=float(self._delay[p]))
        scan, times = self._scan(q)
        return replace(frame, scan=scan, scan_time=times, scan_delay_s=float(self._delay[p]))

    def _scan(self, q: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Position q's scan; frames read in order want the same few scans again (a frame late: the previous
        frame's), so the last few are held."""
        if q not in self._held:
            inner = self._dataset
            if callable(getattr(inner, "load_timed_scan", None)):
                self._hold(q, inner.load_timed_scan(q))
            else:
                other = inner[q]
                self._hold(q, (other.scan, other.scan_time))
        return self._held[q]

    def _hold(self, q: int, scan: tuple[np.ndarray, np.ndarray | None]) -> None:
        self._held[q] = scan
        while len(self._held) > 4:
            self._held.pop(next(iter(self._held)))
