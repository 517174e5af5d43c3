"""Synthetic town: KITTI-like sequences (cam0 images, HDL-64E scans, poses) with exact ground truth.

`generate_sequence(out_root, ...)` writes one sequence in the KITTI odometry layout; `default_sequence_root()`
returns the cached default sequence that `plvo-viz` runs without a dataset.
"""

from plvo_synth.cache import DEFAULT_SEQUENCE, DEFAULT_SETTINGS, cached_sequence_root, default_sequence_root
from plvo_synth.generate import (
    SynthSettings,
    Trajectory,
    exposure_gains,
    generate_sequence,
    plan_trajectory,
)

__all__ = [
    "DEFAULT_SEQUENCE",
    "DEFAULT_SETTINGS",
    "SynthSettings",
    "Trajectory",
    "cached_sequence_root",
    "default_sequence_root",
    "exposure_gains",
    "generate_sequence",
    "plan_trajectory",
]
