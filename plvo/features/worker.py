"""Feature extraction as a worker core (plvo.runtime.workers): in the deployed mode it runs in a process of its own.

Measured on KITTI 04 (plvo-viz, the defaults): in the tracker's process, ORB (22 ms of CPU a frame) and LSD with
its repair (25 ms) ran in two threads that got half a core each (51 and 48 ms of wall time), sharing the GIL with
the tracker and the recorder, and the tracker waited for them; the two cores were ~10 % idle. In a process of
their own, with the frames read ahead one frame further (plvo.runtime.prefetch's `finish`): 0.89 -> 0.95 of
KISS-ICP's frames a second in `plvo bench` (18 runs each way, alternating). Features are a function of the image
and the config alone, so the trajectory is the same to the last bit.

Here the LBD descriptors are computed in one thread (`extract_features`' split_lbd=False): the frames are extracted
ahead of the tracker, so what the second thread's share would save in latency is not waited for, while its own
gradient images cost CPU that the tracker and the back end want (real KITTI 04: 35.4 -> 34.2 ms of CPU a frame).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from plvo.config import LineConfig, OrbConfig
from plvo.features.extract import extract_features
from plvo.types import FeatureSet


@dataclass(frozen=True)
class FeaturesJob:
    """A frame's image, with its index so that a failure names the frame (plvo.runtime.workers)."""

    frame_index: int
    image: np.ndarray


class FeaturesCore:
    """A frame's image in, its features and the seconds they took out (what Frame.features / features_s hold)."""

    def __init__(self, orb: OrbConfig, lines: LineConfig, points_only: bool):
        self._extract = extract_features
        self._args = (orb, lines, points_only)

    def process(self, job: FeaturesJob) -> tuple[FeatureSet, float]:
        t0 = time.perf_counter()
        features = self._extract(job.image, *self._args, split_lbd=False)
        return features, time.perf_counter() - t0
