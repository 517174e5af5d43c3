"""Sparser lidars from a dense one: an HDL-64E scan resampled to 32 or 16 beams by elevation ring.

KITTI's scans have no ring field, so a return's ring is the HDL-64E beam whose nominal elevation is nearest to the
return's elevation angle (after the lidar's elevation error is taken out, see plvo.lidar.scan). Keeping every
2nd ring gives a 32-beam scan with HDL-32E-like spacing in the upper block, every 4th a 16-beam (VLP-16-like,
about 1.3 to 2 degrees apart). This thins real scans; sequences with VLP-16, HDL-32 or OS-128 geometry of their own
are generated as twins (`plvo synth --lidar`, plvo_synth/twin/lidars.py).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from plvo.errors import PlvoError
from plvo.lidar.scan import raise_elevation

if TYPE_CHECKING:
    from plvo.types import Frame

# HDL-64E nominal elevations (deg): 32 lasers from +2 to -8.33 (1/3 deg apart) and 32 from -8.83 to -24.8 (about
# 1/2 deg apart), as the synthetic town's Velodyne model (plvo_synth.sensors) has them
HDL64E_ELEVATIONS_DEG = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])
BEAM_COUNTS = (8, 16, 32, 64)


def elevation_deg(scan: np.ndarray) -> np.ndarray:
    """(N,3|4) lidar-frame points -> (N,) elevation angles in degrees (0: horizontal, positive up)."""
    return np.degrees(np.arctan2(scan[:, 2], np.hypot(scan[:, 0], scan[:, 1])))


def beam_rings(scan: np.ndarray, elevation_offset_deg: float = 0.0,
               elevations_deg: np.ndarray = HDL64E_ELEVATIONS_DEG) -> np.ndarray:
    """(N,) int ring of each return: the beam of `elevations_deg` (top first) nearest to its elevation, once the
    lidar's elevation error `elevation_offset_deg` is corrected."""
    el = elevation_deg(raise_elevation(scan, elevation_offset_deg))
    order = np.argsort(elevations_deg)
    table = np.asarray(elevations_deg)[order]
    right = np.clip(np.searchsorted(table, el), 1, len(table) - 1)
    nearer_left = np.abs(el - table[right - 1]) <= np.abs(table[right] - el)
    return order[np.where(nearer_left, right - 1, right)]


def resample_beams(scan: np.ndarray, n_beams: int, elevation_offset_deg: float = 0.0) -> np.ndarray:
    """(N,4) HDL-64E scan -> the returns of every (64 / n_beams)-th ring, (M,4) in the same order; n_beams one
    of 8, 16, 32, 64 (64: the scan itself)."""
    if n_beams not in BEAM_COUNTS:
        raise PlvoError(f"beams {n_beams}: must be one of {', '.join(map(str, BEAM_COUNTS))} (a 64-beam scan "
                        "thinned by ring)")
    if n_beams == 64:
        return scan
    keep = beam_rings(scan, elevation_offset_deg) % (64 // n_beams) == 0
    return scan[keep]


class BeamResampled:
    """A Dataset whose scans are resampled to n_beams (every other attribute is the wrapped dataset's)."""

    def __init__(self, dataset: Any, n_beams: int) -> None:
        resample_beams(np.zeros((0, 4), np.float32), n_beams)  # checks n_beams
        self._dataset, self.n_beams = dataset, int(n_beams)

    def __getattr__(self, name: str) -> Any:
        if name == "_dataset":  # not set yet (unpickling)
            raise AttributeError(name)
        return getattr(self._dataset, name)

    def __len__(self) -> int:
        return len(self._dataset)

    def __getitem__(self, i: int) -> Frame:
        from dataclasses import replace

        frame = self._dataset[i]
        if self.n_beams == 64:
            return frame
        scan, times = self._thin(frame.scan, frame.scan_time)
        return replace(frame, scan=scan, scan_time=times)

    # The lidar-only peers read scans through these, not through __getitem__: without them __getattr__ would hand
    # them the wrapped dataset's full scans.
    def load_scan(self, i: int) -> np.ndarray:
        return self.load_timed_scan(i)[0]

    def load_timed_scan(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        inner = self._dataset
        if callable(getattr(inner, "load_timed_scan", None)):
            scan, times = inner.load_timed_scan(i)
        elif callable(getattr(inner, "load_scan", None)):
            scan, times = inner.load_scan(i), None
        else:
            frame = inner[i]
            scan, times = frame.scan, frame.scan_time
        return self._thin(scan, times)

    def _thin(self, scan: np.ndarray, times: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        if self.n_beams == 64:
            return scan, times
        keep = beam_rings(scan, self.calib.lidar_elevation_offset_deg) % (64 // self.n_beams) == 0
        return scan[keep], None if times is None else times[keep]
