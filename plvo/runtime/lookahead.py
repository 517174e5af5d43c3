"""Frames read and prepared ahead of the tracker: read up to two ahead in a thread at the look-ahead's priority
(plvo.priority, plvo.runtime.prefetch) while the frames before are tracked, their features extracted there or, in the
deployed mode, in the features process, one more frame ahead. Features depend on the image and the config alone,
so where they are extracted changes the frames a second, never the trajectory."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Generator
from typing import TYPE_CHECKING

from plvo.features.worker import FeaturesJob
from plvo.priority import LOOKAHEAD_NICENESS
from plvo.runtime.prefetch import prefetched
from plvo.runtime.workers import OrderedWorker
from plvo.tracking.frontend import Frontend
from plvo.types import Frame

if TYPE_CHECKING:
    from plvo.data.dataset import Dataset


class Lookahead:
    """frontend: whose feature extraction prepares the frames (None before the stages are built: frames as read);
    features: the features process (None: extracted in the reading thread); timeout_s: how long the tracker
    waits for a frame before the run fails naming it."""

    def __init__(self, frontend: Frontend | None, features: OrderedWorker | None, timeout_s: float):
        self._frontend, self._features, self._timeout_s = frontend, features, timeout_s

    def frames(self, dataset: Dataset) -> Generator[Frame, None, None]:
        if self._features is None:
            return prefetched(dataset, prepare=self.prepare, niceness=LOOKAHEAD_NICENESS, timeout_s=self._timeout_s)
        return prefetched(dataset, prepare=self.start, finish=self.finish, niceness=LOOKAHEAD_NICENESS,
                          timeout_s=self._timeout_s)

    def prepare(self, frame: Frame) -> Frame:
        """The frame with the tracker's features extracted here (`Frame.features`)."""
        if self._frontend is None or frame.features is not None:
            return frame
        t0 = time.perf_counter()
        features = self._frontend.features(frame.image)
        return dataclasses.replace(frame, features=features, features_s=time.perf_counter() - t0)

    def start(self, frame: Frame) -> bool:
        """Queue the frame's image in the features process -> whether it was (not when it has its features)."""
        if frame.features is not None or self._features is None:
            return False
        self._features.submit(FeaturesJob(frame.index, frame.image))
        return True

    def finish(self, frame: Frame, started: bool) -> Frame:
        """The frame with the features the process extracted (as it is when `start` did not queue it)."""
        if not started or self._features is None:
            return frame
        features, seconds = self._features.take()
        return dataclasses.replace(frame, features=features, features_s=seconds)
