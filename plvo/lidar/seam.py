"""What a spinning lidar's scan shows where its sweep begins and ends: whether it was motion-compensated, how much of
the sweep's motion the compensation removed, and whether a ring holds more than one turn.

A sweep turning clockwise seen from above begins and ends behind the sensor (azimuth +-180 deg; KITTI's HDL-64E
and the twins, plvo_synth.twin.lidars), its start on the left (just below +180) and its end on the right
(just above -180), one sweep's duration apart. In a raw sweep one ring's returns on flat ground lie on a circle
round the sensor however it moved, so they meet at the seam. A compensation moves every return into the sensor
frame at one instant: the start's back by the motion before that instant, the end's forward by the motion after
it, so that on the ground one ring's returns at the seam lie the motion it removed apart along the direction of
travel (seam_ground_split): about the car's speed times the sweep for a good compensation, 0 for a raw sweep.
Against the truth's motion over the sweep, the difference is what the compensation left (or removed too much).

numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.errors import PlvoError

SEAM_WINDOW_DEG = 1.5  # returns this close to the seam, each side
SEAM_RETURNS = 8  # at most this many returns of a ring each side
GROUND_BELOW_M = 1.3  # ground returns: this far below the sensor (KITTI's HDL-64E is 1.73 m up)
MAX_SPREAD_M = 0.3  # one side's returns span at most this along x (one smooth stretch of ground)


def storage_rings(scan: np.ndarray) -> np.ndarray:
    """(N,>=2) scan stored ring by ring -> (N,) ring of each return, from the storage order: each ring a turn of
    increasing azimuth from facing forward (KITTI's files) or of decreasing azimuth from behind (the twins)."""
    az = np.arctan2(scan[:, 1], scan[:, 0])
    if len(az) < 2:
        return np.zeros(len(az), np.int64)
    counter_clockwise = np.median(np.angle(np.exp(1j * np.diff(az)))) > 0
    start = (az[:-1] < 0.0) & (az[1:] >= 0.0) if counter_clockwise else np.diff(az) > np.pi
    return np.concatenate([[0], np.cumsum(start)]).astype(np.int64)


@dataclass(frozen=True)
class RingTurns:
    """How much of a turn each ring of a scan holds: returns (R,), span_deg (R,) from its first return to the
    farthest in storage order, step_deg (R,) median azimuth step, densest (R,) returns in its densest sector of
    SECTOR_DEG over the median sector's. An overlap (the sweep's end stored over its start) shows as a sector of
    about twice the returns: interleaved with the ring's start, or continued past its turn (storage_rings then takes
    the extra returns into a neighbouring ring's run, which holds those azimuths twice)."""

    returns: np.ndarray
    span_deg: np.ndarray
    step_deg: np.ndarray
    densest: np.ndarray


SECTOR_DEG = 10.0


def ring_turns(scan: np.ndarray, rings: np.ndarray | None = None) -> RingTurns:
    """Each ring's returns, azimuth span, step and densest sector; rings: each return's ring (None: from the storage
    order, storage_rings)."""
    ring = storage_rings(scan) if rings is None else np.asarray(rings)
    if len(ring) != len(scan):
        raise PlvoError(f"ring_turns: {len(ring)} rings for {len(scan)} returns")
    az = np.degrees(np.arctan2(scan[:, 1], scan[:, 0]))
    sector = ((az + 180.0) // SECTOR_DEG).astype(np.int64) % int(round(360.0 / SECTOR_DEG))
    out: dict[str, list] = {k: [] for k in ("returns", "span_deg", "step_deg", "densest")}
    for r in np.unique(ring):
        k = ring == r
        a = az[k]
        if len(a) < 3:
            continue
        unwrapped = np.degrees(np.unwrap(np.radians(a)))
        counts = np.bincount(sector[k], minlength=int(round(360.0 / SECTOR_DEG)))
        out["returns"].append(len(a))
        out["span_deg"].append(float(np.abs(unwrapped - unwrapped[0]).max()))
        out["step_deg"].append(float(np.median(np.abs(np.diff(unwrapped)))))
        out["densest"].append(float(counts.max() / max(np.median(counts), 1.0)))
    return RingTurns(**{k: np.asarray(v) for k, v in out.items()})


def seam_ground_split(scan: np.ndarray, rings: np.ndarray | None = None, max_range_m: float = 40.0) -> np.ndarray:
    """(R',) for each ring with ground returns on both sides of the seam behind the sensor: x of the sweep's end
    (azimuth just above -180 deg) minus x of its start (just below +180 deg), medians of up to SEAM_RETURNS
    returns within SEAM_WINDOW_DEG each side, in metres along the sensor's x: the motion a compensation removed
    over the sweep (0 for a raw sweep). rings: each return's ring (None: from the storage order)."""
    ring = storage_rings(scan) if rings is None else np.asarray(rings)
    if len(ring) != len(scan):
        raise PlvoError(f"seam_ground_split: {len(ring)} rings for {len(scan)} returns")
    az = np.degrees(np.arctan2(scan[:, 1], scan[:, 0]))
    near = np.abs(az) > 180.0 - SEAM_WINDOW_DEG
    out = []
    for r in np.unique(ring[near]):
        k = np.flatnonzero(near & (ring == r))
        start = k[az[k] > 0]
        end = k[az[k] < 0]
        start = start[np.argsort(-az[start])][:SEAM_RETURNS]  # the last returns before the seam
        end = end[np.argsort(az[end])][:SEAM_RETURNS]  # the first after it
        if len(start) < 3 or len(end) < 3:
            continue
        xs, xe = scan[start, 0], scan[end, 0]
        ground = (scan[start, 2] < -GROUND_BELOW_M).all() and (scan[end, 2] < -GROUND_BELOW_M).all()
        smooth = np.ptp(xs) < MAX_SPREAD_M and np.ptp(xe) < MAX_SPREAD_M
        if ground and smooth and abs(np.median(xs)) < max_range_m:
            out.append(float(np.median(xe) - np.median(xs)))
    return np.asarray(out)
