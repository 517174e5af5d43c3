"""plvo: lidar-monocular visual odometry and SLAM with point and line features.

The library imports no viewer: stages hand typed results to `plvo.recording.Recorder` objects, and the
Rerun and viser recorders live in `plvo_app`.

A whole run from Python::

    import plvo

    dataset = plvo.open_dataset("../shared/data/kitti", "04")  # KITTI, a raw drive, a ROS bag or a folder
    out = plvo.run_dataset(dataset, plvo.load_config(None))    # the paper's defaults; or a TOML file
    out.poses  # (N,4,4) T_world_cam0 of every frame, as KITTI's pose files hold them

`plvo.System` steps one frame at a time (`System.step`, frames from `System.read_ahead(dataset)`) for a caller that
wants each frame's result as it comes. The names here are imported on first use, so that `import plvo.config` (or
a command's --help) does not load the pipeline's libraries.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# name -> the module that defines it
_PUBLIC = {
    "System": "plvo.runtime.system",
    "run_dataset": "plvo.runtime.run",
    "RunOutput": "plvo.runtime.run",
    "load_config": "plvo.config",
    "SystemConfig": "plvo.config",
    "open_dataset": "plvo.data.registry",
    "Frame": "plvo.types",
    "Calibration": "plvo.types",
    "Recorder": "plvo.recording",
}
__all__ = ["Calibration", "Frame", "Recorder", "RunOutput", "System", "SystemConfig", "load_config", "open_dataset",
           "run_dataset"]

if TYPE_CHECKING:
    from plvo.config import SystemConfig, load_config
    from plvo.data.registry import open_dataset
    from plvo.recording import Recorder
    from plvo.runtime.run import RunOutput, run_dataset
    from plvo.runtime.system import System
    from plvo.types import Calibration, Frame


def __getattr__(name: str) -> Any:
    where = _PUBLIC.get(name)
    if where is None:
        raise AttributeError(f"module 'plvo' has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
