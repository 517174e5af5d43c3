"""The dataset protocol every sequence source follows (KITTI odometry, KITTI raw, synthetic town, ROS bags, plain
folders), and the options a bag or folder needs (SourceOptions).

A dataset is a selected range of frames of one sequence. Positions `0..len-1` index that range; each Frame
carries the dataset's own frame number in `Frame.index`. Images and scans are read lazily by `__getitem__`.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from plvo.errors import DatasetError
from plvo.types import Calibration, Frame


@runtime_checkable
class Dataset(Protocol):
    """A selected range of frames of one sequence.

    name: the source ("kitti_odometry", "kitti_raw", ...); sequence: its sequence name ("04",
    "2011_09_26_drive_0009"); calib: calibration of the chosen camera.
    """

    name: str
    sequence: str
    calib: Calibration

    def __len__(self) -> int:
        """Number of selected frames."""
        ...

    def __getitem__(self, i: int) -> Frame:
        """Frame at position i (0..len-1, negatives from the end); IndexError outside; Frame.index = frame number."""
        ...

    @property
    def gt_T_world_cam(self) -> np.ndarray | None:
        """(len,4,4) ground-truth poses of the chosen camera in the world (cam0 of the sequence's frame 0), or None."""
        ...

    @property
    def frame_indices(self) -> tuple[int, ...]:
        """The dataset's frame numbers of positions 0..len-1."""
        ...

    @property
    def times(self) -> np.ndarray:
        """(len,) timestamps in seconds."""
        ...


class SelectedFrames:
    """What every dataset class shares: the selection (`_frames`, the dataset's frame numbers), their times
    (`_times`, (len,)) and ground truth (`_gt`, (len,4,4) or None), set by the subclass."""

    _frames: tuple[int, ...]
    _times: np.ndarray
    _gt: np.ndarray | None
    truth_source: str | None = None  # where the ground truth was read (a file or folder), for the run's summary

    def __len__(self) -> int:
        return len(self._frames)

    def _position(self, i: int) -> int:
        """Position i (negatives from the end) -> 0..len-1; IndexError outside."""
        n = len(self._frames)
        if not -n <= i < n:
            raise IndexError(f"position {i} out of range for {n} frames")
        return i % n

    @property
    def gt_T_world_cam(self) -> np.ndarray | None:
        return None if self._gt is None else self._gt.copy()

    @property
    def frame_indices(self) -> tuple[int, ...]:
        return self._frames

    @property
    def times(self) -> np.ndarray:
        return self._times.copy()


def iter_frames(dataset: Dataset) -> Iterator[Frame]:
    """Frames of a dataset in order, read one at a time."""
    for i in range(len(dataset)):
        yield dataset[i]


FrameSelection = slice | range | Sequence[int] | None


def _format_selection(frames: FrameSelection) -> str:
    if isinstance(frames, slice):
        parts = ["" if v is None else str(v) for v in (frames.start, frames.stop)]
        if frames.step is not None:
            parts.append(str(frames.step))
        return ":".join(parts)
    if isinstance(frames, range):
        return f"range({frames.start}, {frames.stop}, {frames.step})"
    return repr(frames)


def select_frames(frames: FrameSelection, n: int, where: str) -> tuple[int, ...]:
    """Frame numbers picked by `frames` among 0..n-1: a slice (Python semantics, but bounds beyond n are errors),
    a range or a sequence of frame numbers, or None for all. `where` names the sequence in error messages."""
    label = _format_selection(frames)
    if frames is None:
        selected: Sequence[int] = range(n)
    elif isinstance(frames, slice):
        if frames.step == 0:
            raise DatasetError(f"frames {label}: step must not be 0")
        for bound in (frames.start, frames.stop):
            if bound is not None and not -n <= bound <= n:
                raise DatasetError(f"frames {label}: out of range, {where} has frames 0..{n - 1}")
        selected = range(n)[frames]
    else:
        selected = [int(i) for i in frames]
        bad = [i for i in selected if not 0 <= i < n]
        if bad:
            raise DatasetError(f"frames {label}: frame {bad[0]} out of range, {where} has frames 0..{n - 1}")
    if len(selected) == 0:
        raise DatasetError(f"frames {label}: no frame selected, {where} has frames 0..{n - 1}")
    return tuple(int(i) for i in selected)


@dataclass(frozen=True)
class SourceOptions:
    """What a bag or a plain folder cannot tell by itself (all optional; the CLIs' --image-topic, --cloud-topic,
    --calib, --max-pair-dt).

    image_topic, cloud_topic: topics to read (None: the only one of its kind). calib: calibration YAML
    (plvo.data.calib_yaml; None: the bag's CameraInfo and /tf_static, or the folder's calib.yaml). max_pair_dt:
    seconds an image and its scan may be apart. lidar_elevation_offset_deg: the lidar's vertical-angle error
    (Calibration.lidar_elevation_offset_deg; KITTI's HDL-64E: 0.205), overriding the calibration YAML's (None: the
    YAML's, or 0 for CameraInfo + TF, which cannot carry it). beams: resample the (HDL-64E) scans to 16 or 32
    beams by ring, of any source (None: as recorded).
    """

    image_topic: str | None = None
    cloud_topic: str | None = None
    calib: str | None = None
    max_pair_dt: float = 0.05
    lidar_elevation_offset_deg: float | None = None
    beams: int | None = None  # resample 64-beam scans to this many beams (plvo.lidar.beams); None: as recorded
