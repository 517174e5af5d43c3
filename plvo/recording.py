"""The Recorder protocol: how the library hands what each stage saw and decided to viewers and loggers.

The library never imports a viewer. `plvo.runtime.system` calls these methods with typed, frozen results; the Rerun and
viser recorders in `plvo_app` implement them. Recorders must not mutate what they are given.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from plvo.depth.extract import DepthDebug
from plvo.errors import PlvoError
from plvo.results import GraphResult, KeyframeResult, LoopResult, MapResult, MetricsResult, TimingResult, TrackingResult
from plvo.types import Calibration, DepthPriors, FeatureMatches, FeatureSet, Frame

# What the stages hand the recorders (on_stage); a stage may hand a subclass (the tracker's FrontendResult)
StageResult = (FeatureSet | FeatureMatches | DepthPriors | DepthDebug | TrackingResult | KeyframeResult | GraphResult
               | MapResult | LoopResult | TimingResult | MetricsResult)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunInfo:
    """What a run is: logged once at the start.

    gt_T_world_cam: (N,4,4) ground truth of the frames that will run, or None. config: the resolved config as
    nested dicts. frame_indices: the dataset indices that will run, in order.
    """

    name: str
    sequence: str
    calib: Calibration
    frame_indices: tuple[int, ...]
    gt_T_world_cam: np.ndarray | None
    config: dict[str, Any]
    version: str
    git_revision: str
    command_line: str
    extra: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Recorder(Protocol):
    def on_run_start(self, info: RunInfo) -> None:
        """Once, before the first frame."""

    def on_restart(self, info: RunInfo) -> None:
        """The run starts again from its first frame (plvo.runtime.system.System.restart): what was recorded of the
        frames so far is superseded; `info` carries the new config and, in extra["restart"], why and at which frame."""

    def on_frame(self, frame: Frame) -> None:
        """A new input frame (image and scan) is about to be processed; sets the current time."""

    def on_stage(self, frame_index: int, result: StageResult) -> None:
        """A typed stage result (FeatureSet, DepthPriors, a tracking or back-end result...) for a frame."""

    def close(self) -> None:
        """Flush and close; called once, also after an error or Ctrl-C."""


class NullRecorder:
    """Does nothing: the default when no viewer is wanted."""

    def on_run_start(self, info: RunInfo) -> None:
        pass

    def on_restart(self, info: RunInfo) -> None:
        pass

    def on_frame(self, frame: Frame) -> None:
        pass

    def on_stage(self, frame_index: int, result: StageResult) -> None:
        pass

    def close(self) -> None:
        pass


class FanOut:
    """Hands every call to each recorder in turn. A failing recorder is logged and dropped, never fatal
    to the run: a viewer crash must not lose the trajectory. A PlvoError is the exception: a recorder that cannot
    write the file the user asked for (a full disk) stops the run, which then says so on one line."""

    def __init__(self, recorders: list[Recorder]):
        self.recorders = list(recorders)

    def _each(self, method: str, *args: Any) -> None:
        for rec in list(self.recorders):
            try:
                getattr(rec, method)(*args)
            except PlvoError:
                raise
            except Exception:  # noqa: BLE001 - deliberately isolating recorder faults
                log.exception("recorder %s failed in %s; dropping it", type(rec).__name__, method)
                self.recorders.remove(rec)

    def on_run_start(self, info: RunInfo) -> None:
        self._each("on_run_start", info)

    def on_restart(self, info: RunInfo) -> None:
        self._each("on_restart", info)

    def on_frame(self, frame: Frame) -> None:
        self._each("on_frame", frame)

    def on_stage(self, frame_index: int, result: StageResult) -> None:
        self._each("on_stage", frame_index, result)

    def close(self) -> None:
        """Close every recorder; the first PlvoError (a recording's last write failed) is raised after all."""
        error: PlvoError | None = None
        for rec in self.recorders:
            try:
                rec.close()
            except PlvoError as exc:
                error = error or exc
            except Exception:  # noqa: BLE001
                log.exception("recorder %s failed to close", type(rec).__name__)
        if error is not None:
            raise error
